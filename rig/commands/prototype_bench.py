"""`rig bench prototype`: the prototype's tracking targets measured on the simulated stand in simulated time,
through the runtime (Session, the compiled period kernel, the recorder), as `rig run --layout prototype`
operates it:

  sine      a 10 um 5 Hz sine tracked: rms error in % of the amplitude (sensor noise and floor motion on)
  step      a 2 um step: settling to 2 % and overshoot after the request, command peak, clamp (the stand's
            response itself: sensor noise and floor off)
  frf       |x_p / r| of the run (lock-in on sine references, 5-95 Hz) against the analysed closed loop
            (controllers/tracking.py tracking_response), with the feedforward and for the PID alone
  switches  random mode switches while live: the largest period-to-period change of the command written and
            of the controllers' output at a switch (not into `off`), against the slew limit; refusals
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

import h5py
import numpy as np

from controllers.prototype import StandLoops, step_figures
from controllers.tracking import tracking_from_config, tracking_response
from rig import operated
from rig.runtime.clock import SimClock
from rig.runtime.session import Session

FREQS_HZ = (5.0, 20.0, 50.0, 95.0)


def quiet(cfg):
    """The config without sensor noise and floor motion (the stand's response itself)."""
    return cfg.replace(stand=dataclasses.replace(cfg.stand, position_noise_m=0.0, accel_noise_mps2=0.0,
                                                 base_motion_rms_m=0.0))


def _run(cfg, path, *, seconds, mode=None, script=None) -> Path:
    with Session(cfg, "sim", clock=SimClock(), record=path, mode=mode, script=script) as s:
        s.run(seconds=seconds, activate_after_s=0.05)
        if s.loop.lc.fault_reason:
            raise RuntimeError(f"the simulated prototype faulted: {s.loop.lc.fault_reason}")
    return Path(path)


def _read(path, *names):
    with h5py.File(path) as f:
        cols = [np.asarray(f[k][()]).ravel() for k in names]
        ev = [(float(a), b.decode()) for a, b in zip(f["events/time_s"][()], f["events/text"][()])]
    return cols, ev


def sine(cfg, workdir) -> dict:
    path = _run(cfg, Path(workdir) / "sine.h5", seconds=2.3, mode="track sine:amp=10um,freq=5")
    tr = next(d for d in operated.figures(operated.load_operated(path)) if d["mode"] == "track")
    return {k: tr[k] for k in ("rms_error_um", "rms_error_pct", "max_error_um", "peak_command_V", "limited_pct")}


def step(cfg, workdir, amp_um: float = 2.0) -> dict:
    cfg = quiet(cfg)
    path = _run(cfg, Path(workdir) / "step.h5", seconds=0.4, script=[(0.2, f"track step:amp={amp_um}um")])
    (t, x, u), ev = _read(path, "time_s", "stroke_m", "valve_cmd_V")
    t_req = next(a for a, b in ev if ": mode track step" in b)
    sel = t >= t_req - 1e-9
    return step_figures(t[sel], x[sel] - x[sel][0], u[sel], amp_um * 1e-6, cfg.safety.valve_limit_V)


def frf(cfg, workdir, ff: float, freqs=FREQS_HZ) -> list[dict]:
    """Per frequency: the run's |x_p / r| and the analysis', in dB, and their difference."""
    cfg = quiet(cfg)
    cfg = cfg.replace(controller=dataclasses.replace(cfg.controller, track_ff=ff))
    dt = 1.0 / cfg.loop.rate_hz
    loops = StandLoops(cfg, dt)
    c = tracking_from_config(cfg, dt, act=loops.act)
    out = []
    for f in freqs:
        amp = min(2e-6, 0.8 * cfg.controller.track_rate_m_per_s / (2 * math.pi * f))
        cycles = max(6, int(round(0.25 * f)))
        path = _run(cfg, Path(workdir) / f"frf{f:g}.h5", seconds=0.15 + (2 + cycles) / f,
                    mode=f"track sine:amp={amp!r}m,freq={f!r}")
        (t, x, r), _ = _read(path, "time_s", "stroke_m", "reference_m")
        r0 = r[np.isfinite(r)][0]
        t0 = t[np.argmax(np.isfinite(r) & (np.abs(r - r0) > 1e-12))]        # the reference starts moving
        sel = (t >= t0 + 1.5 / f) & (t < t0 + (1.5 + cycles) / f)           # whole cycles after the fade-in
        c_ = np.exp(-2j * np.pi * f * t[sel])
        run = abs(np.mean(x[sel] * c_) / np.mean(r[sel] * c_))
        ana = abs(tracking_response(loops.act, c, np.array([f]), cfg.controller.track_delay_periods,
                                    feedforward=ff > 0)[0])
        out.append({"frequency_hz": f, "run_db": 20 * math.log10(run), "analysis_db": 20 * math.log10(ana),
                    "difference_db": 20 * math.log10(run / ana)})
    return out


def switches(cfg, workdir, n: int = 100, seed: int = 18) -> dict:
    rng = np.random.default_rng(seed)
    t, script = 0.3, []
    for _ in range(n):
        kind = rng.choice(["off", "hold", "holdat", "isolate", "sine", "step"])
        script.append((round(t, 4), {"off": "off", "hold": "hold", "isolate": "isolate",
                                     "holdat": f"hold {rng.uniform(-15, 15):.2f}um",
                                     "sine": f"track sine:amp={rng.uniform(1, 8):.2f}um,freq={rng.uniform(1, 8):.2f}",
                                     "step": f"track step:amp={rng.uniform(-3, 3):.2f}um"}[kind]))
        t += rng.uniform(0.02, 0.08)
    path = _run(cfg, Path(workdir) / "switches.h5", seconds=t + 0.1, script=script)
    (tt, u, raw, lim), ev = _read(path, "time_s", "valve_cmd_V", "valve_cmd_raw_V", "cmd_limited")
    slew = cfg.safety.slew_V_per_s / cfg.loop.rate_hz
    done = [(a, b) for a, b in ev if ": mode " in b]
    jumps = [abs(raw[k] - u[k - 1]) for k, b in ((int(np.searchsorted(tt, a - 1e-9)), b) for a, b in done)
             if not b.endswith(": mode off")]
    return {"requests": n, "switches": len(done), "refused": sum("refused" in b for _, b in ev),
            "slew_limit_V_per_period": slew, "max_command_step_V": float(np.abs(np.diff(u)).max()),
            "max_takeover_step_V": float(max(jumps)), "limited_pct": float(100 * lim.mean())}


def run(cfg, *, workdir=None, switch_count: int = 100, seed: int = 18, progress=print) -> dict:
    """All four, in a temporary folder unless workdir is given."""
    with tempfile.TemporaryDirectory(prefix="rig-bench-prototype-") as tmp:
        wd = workdir or tmp
        progress("sine 10 um 5 Hz")
        res = {"sine_10um_5hz": sine(cfg, wd)}
        progress("step 2 um")
        res["step_2um"] = step(cfg, wd)
        progress("closed loop against the analysis: with the feedforward, then the PID alone")
        res["frf_feedforward"] = frf(cfg, wd, 1.0)
        res["frf_pid"] = frf(cfg, wd, 0.0)
        progress(f"{switch_count} random mode switches")
        res["switches"] = switches(cfg, wd, switch_count, seed)
    return res


def text(res: dict) -> str:
    s, st, sw = res["sine_10um_5hz"], res["step_2um"], res["switches"]
    lines = [f"sine 10 um 5 Hz: rms error {s['rms_error_um']:.4f} um = {s['rms_error_pct']:.2f} % of the amplitude "
             f"(max {s['max_error_um']:.3f} um, command peak {s['peak_command_V']:.2f} V)",
             f"step 2 um: settles within 2 % in {st['settling_2pct_ms']:.1f} ms, overshoot {st['overshoot_pct']:.2f} %,"
             f" command peak {st['peak_command_V']:.2f} V, {'AT' if st['at_clamp'] else 'off'} the clamp"]
    for key, what in (("frf_feedforward", "with the feedforward"), ("frf_pid", "PID alone (Fig. 4)")):
        lines.append(f"|x/r| run vs analysis, {what}: " + ", ".join(
            f"{d['frequency_hz']:g} Hz {d['run_db']:+.2f}/{d['analysis_db']:+.2f} dB ({d['difference_db']:+.3f})"
            for d in res[key]))
    lines.append(f"{sw['requests']} random mode requests: {sw['switches']} switches, {sw['refused']} refused; largest "
                 f"command step {sw['max_command_step_V']:.3f} V, at a take-over {sw['max_takeover_step_V']:.3f} V "
                 f"(slew limit {sw['slew_limit_V_per_period']:.3f} V per period); limiter active "
                 f"{sw['limited_pct']:.2f} % of periods")
    return "\n".join(lines)

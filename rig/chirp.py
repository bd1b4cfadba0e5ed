"""The identification chirp run (`rig chirp`, and the console's chirp button): the actuator alone on its test stand,
open loop, the valve command following a linear sine chirp (f0 -> f1 over duration, paper: 0.1 -> 100 Hz in 100 s),
or the same sweep at several levels, or an odd random-phase multisine (rig/excitation.py), through the runtime
loop (a Session: the port from the registry). Each loop period reads the sensors, writes the sample (through the
safety limiter) and records time_s, valve_cmd_V, position_m, accel_mps2 of the chirped mount. Position is sampled at
t_k before the command of period k acts (ZOH), as the shared recordings and rig.identify assume.

Backends: sim (one StandPlant with the configured Table 1 parameters and sensor noise; simulated time by default;
effects and sensor noise from the config's [stand] section), hil (the real drivers against the emulated devices,
each mount an actuator alone on its stand; real time), hardware (the real rig; the chirp goes to --mount, the other
valves stay at null; real time).
"""
from __future__ import annotations


import math
import os
import threading
import time
from dataclasses import replace
from pathlib import Path

from controllers.playback import SignalPlayback
from rig import cliargs, excitation
from rig.config import hil_run_config, layout_mounts
from rig.errors import FaultError, RigError
from rig.recordings.rigformat import save_columns_csv
from rig.runtime.clock import MonotonicClock, SimClock
from rig.runtime.lifecycle import State
from rig.runtime.recorder import Channel, read_recording
from rig.runtime.session import Session
from rig.runtime.tap import Columns
from sim_backend.actuator import Effects, StandBank, StandPlant
from sim_backend.linear import ActuatorParams


def chirp_samples(amplitude_V: float, f0_hz: float, f1_hz: float, duration_s: float, dt: float) -> list[float]:
    """The linear sine chirp, one sample per period: u_k = A sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))), t = k dt,
    for k dt < T (controllers/playback.py plays it from activation on, null after)."""
    c = (f1_hz - f0_hz) / (2 * duration_s)
    out = []
    k = 0
    while k * dt < duration_s:
        t = k * dt
        out.append(amplitude_V * math.sin(2 * math.pi * (f0_hz * t + c * t * t)))
        k += 1
    return out


def chirp_columns(mount: int) -> Columns:
    """The recording of a chirp run: time, command, position and acceleration of the chirped mount."""
    return Columns([(Channel("time_s", "s", description="loop time since start"), "time_s", 0),
                    (Channel("valve_cmd_V", "V", description="valve command written (after limits)"),
                     "valve_cmd_V", mount),
                    (Channel("position_m", "m", description="displacement transducer at t_k"), "stroke_m", mount),
                    (Channel("accel_mps2", "m/s^2", description="accelerometer at t_k"), "accel_mps2", mount)])


def _sim_effects(cfg, seed: int | None):
    """The [stand] section: effect switches and sensor noise (real sensors are never bit-exact constant, and
    the loop's stuck check relies on that)."""
    fx = Effects.from_config(cfg)
    return fx if seed is None else replace(fx, seed=seed)


def chirp_port_options(cfg, backend: str, dt: float, *, seed: int | None = None, stand_params=None,
                       stand_effects=None) -> dict:
    """The backend's options for a chirp: sim, one actuator on its stand; hil, each mount an actuator alone on
    its stand behind the emulated devices; hardware, the rig as it is."""
    fx = stand_effects or _sim_effects(cfg, seed)
    p = stand_params or ActuatorParams.from_config(cfg)
    if backend == "sim":
        return dict(mode="stand", seed=seed or 0, stand_params=p, stand_effects=fx)
    if backend == "hil":
        return dict(plant=StandBank([StandPlant(p, replace(fx, seed=fx.seed + i), 1.0 / dt)
                                     for i in range(len(layout_mounts(cfg)))]))
    return {}


OPTIONS = {"amplitude": "--amplitude", "f0/f1": "--f0/--f1", "duration": "--duration", "f1": "--f1"}  # rig chirp's


def chirp_rate(cfg, backend: str, rate_hz: float | None = None) -> float:
    """The chirp's sample rate: as given, else the HIL rate on the emulated rig, the loop's elsewhere."""
    return float(rate_hz or (cfg.hil.rate_hz if backend == "hil" else cfg.loop.rate_hz))


def check_chirp(cfg, backend: str, amplitude_V: float, f0_hz: float, f1_hz: float, duration_s: float,
                names: dict = OPTIONS) -> None:
    """A sine sweep's request checked as run_chirp checks it, before anything stops or starts (the console's
    page asks with its own field names)."""
    _check_signal(cfg, chirp_rate(cfg, backend), amplitude_V, f0_hz, f1_hz, duration_s,
                  2 * math.pi * f1_hz * amplitude_V, names)


def _check_signal(cfg, rate: float, amplitude_V: float, f0_hz: float, f1_hz: float, duration_s: float,
                  slew_V_per_s: float, names: dict = OPTIONS) -> None:
    """The signal within the safety limits and below Nyquist (one line naming the option otherwise)."""
    if not 0 < amplitude_V <= cfg.safety.valve_limit_V:            # (so NaN is refused too)
        raise RigError(f"{names['amplitude']}: expected 0 < V <= safety.valve_limit_V = "
                       f"{cfg.safety.valve_limit_V:g}, got {amplitude_V:g}")
    if not 0 <= f0_hz < f1_hz < rate / 2:
        raise RigError(f"{names['f0/f1']}: expected 0 <= f0 < f1 < rate/2 = {rate / 2:g} Hz, got {f0_hz:g}, "
                       f"{f1_hz:g}")
    if not 0 < duration_s <= cliargs.MAX_CHIRP_S:
        raise RigError(f"{names['duration']}: expected 0 < s <= {cliargs.MAX_CHIRP_S:g}, got {duration_s:g}")
    if slew_V_per_s > cfg.safety.slew_V_per_s:
        raise RigError(f"{names['amplitude']}/{names['f1']}: the chirp slews {slew_V_per_s:.0f} V/s, above "
                       f"safety.slew_V_per_s = {cfg.safety.slew_V_per_s:g}")


def run_chirp(cfg, *, backend: str = "sim", amplitude_V: float = 2.0, f0_hz: float = 0.1, f1_hz: float = 100.0,
              duration_s: float = 100.0, rate_hz: float | None = None, out: Path, csv: bool = False,
              mount: str = "front_left", settle_s: float = 0.05, sim_time: bool | None = None, seed: int | None = None,
              stand_params=None, stand_effects=None, progress=None, on_session=None, levels_V=None,
              multisine: bool = False, period_s: float = 10.0) -> dict:
    """Run the chirp through rig.runtime.loop and write the recording. Returns a summary dict.
    levels_V: the same chirp at each level back to back; multisine: an odd random-phase multisine instead
    (both from rig.excitation, played back sample by sample).
    progress: optional callable(t_s, total_s) polled from a helper thread; on_session: optional
    callable(session) once the session is built (a console stops it safely from another thread)."""
    rate = chirp_rate(cfg, backend, rate_hz)
    cliargs.check_rate(cfg, rate, sections=("stand",))
    if backend == "hil":
        # driver threads deliver samples asynchronously: HIL runs use their own stale limit, watchdog and rate
        cfg = hil_run_config(cfg, rate)
    signal = excitation.for_chirp_run(rate, duration_s, f0_hz, f1_hz, amplitude_V, levels_V=levels_V,
                                      multisine=multisine, period_s=period_s, seed=seed or 0)
    if signal is not None:
        amplitude_V, duration_s = signal.peak_V, signal.duration_s
    _check_signal(cfg, rate, amplitude_V, f0_hz, f1_hz, duration_s,
                  2 * math.pi * f1_hz * amplitude_V if signal is None else signal.slew_V_per_s)
    sim_time = (backend == "sim") if sim_time is None else sim_time
    if sim_time and backend != "sim":
        raise RigError("simulated time only with --backend sim")
    dt = 1.0 / rate
    out = Path(out)
    if out.is_dir():
        raise RigError(f"--out {out}: is a folder, expected a recording file name")
    m_idx, names = _chirped_mount(cfg, backend, mount)
    samples = chirp_samples(amplitude_V, f0_hz, f1_hz, duration_s, dt) if signal is None else signal.cmd_V
    ctrls = [SignalPlayback(samples if i == m_idx else [], dt) for i in range(len(names))]
    # recorded beside the output and put in its place only when the chirp completes: a run that fails leaves
    # nothing, and a file the user had there stays until a complete chirp replaces it
    h5_path = out.with_name(out.name + ".part.h5")
    total = settle_s + duration_s + 0.05        # a short null tail after the chirp
    # the valve is driven open loop by the chirp: nothing isolates, so the do-no-harm supervisor (which holds
    # isolation against isolation off) has nothing to judge and would only say it has no reference
    cfg = cfg.replace(supervisor=replace(cfg.supervisor, enabled=False))
    session = Session(cfg, backend, controllers=ctrls, clock=SimClock() if sim_time else MonotonicClock(),
                      rate_hz=rate, names=names, isolation=True,
                      port_options=chirp_port_options(cfg, backend, dt, seed=seed, stand_params=stand_params,
                                                      stand_effects=stand_effects),
                      record=h5_path, columns=chirp_columns(m_idx),
                      record_attrs={"command": "rig chirp", "mount": names[m_idx],
                                    "amplitude_V": amplitude_V, "f0_hz": f0_hz, "f1_hz": f1_hz,
                                    "duration_s": duration_s, "fs_hz": rate, "settle_s": settle_s,
                                    "chirp": "linear" if signal is None else signal.kind,
                                    **({} if signal is None else signal.attrs())})
    wall0 = time.perf_counter()
    try:
        reason = _run_with_progress(session, total, settle_s, progress, on_session)
        loop, rec = session.loop, session.recorder
        if progress and loop.t0_ns is not None:
            progress(min(total, (loop.t_ns - loop.t0_ns) * 1e-9 + loop.dt), total)
        wall = time.perf_counter() - wall0
        if loop.lc.state is State.FAULT:
            raise FaultError(f"chirp stopped by a FAULT after {loop.iterations} periods: {loop.lc.fault_reason} "
                             f"(nothing kept: run the chirp again once the cause is cleared)")
        if reason != "time":      # stopped before the sweep ended: a part of a chirp identifies nothing well
            raise RigError(f"chirp stopped early ({reason}) at t = {loop.iterations * loop.dt:.1f} s of "
                           f"{total:.1f} s (nothing kept)")
        if csv:             # the rows as recorded: rows the recorder dropped stay missing, not invented
            save_columns_csv(read_recording(h5_path), out)
        else:
            os.replace(h5_path, out)
    finally:
        try:
            h5_path.unlink(missing_ok=True)
        except NotADirectoryError:          # no part was made (a file where its folder should be): the error
            pass                            # that said so is the one to raise
    tm = loop.timing_us()
    return {"recording": str(out), "format": "csv" if csv else "hdf5", "backend": backend, "rate_hz": loop.rate_hz,
            "periods": loop.iterations, "rows_written": rec.rows_written, "dropped_rows": rec.dropped_rows,
            "overruns": loop.overruns, "skipped_periods": loop.skipped, "stop_reason": reason,
            "wall_s": wall, "simulated_time": sim_time, "compute_us": tm["compute_us"]}


def _chirped_mount(cfg, backend: str, mount: str) -> tuple[int, tuple[str, ...] | list[str]]:
    """The chirped mount's index and the run's mount names: sim, the one actuator on its stand; otherwise
    --mount among the layout's mounts (the default, front_left, is the first mount of a one-mount layout)."""
    mounts = layout_mounts(cfg)
    if len(mounts) == 1 and mount == "front_left":          # the default names the machine's first mount
        mount = mounts[0]
    if mount not in mounts:                                  # a wrong name is refused on sim too: never ignored
        raise RigError(f"--mount: expected one of {', '.join(mounts)}, got {mount!r}")
    return (0, ("stand",)) if backend == "sim" else (mounts.index(mount), mounts)


def _run_with_progress(session, total_s: float, settle_s: float, progress, on_session) -> str:
    """Run the session for total_s, activating after settle_s; progress(t_s, total_s), if given, polled every
    0.1 s from a helper thread. Returns the stop reason."""
    done = threading.Event()
    with session:
        loop = session.loop
        if on_session is not None:
            on_session(session)

        def poll():
            while not done.wait(0.1):
                if progress and loop.t0_ns is not None:
                    progress(min(total_s, (loop.t_ns - loop.t0_ns) * 1e-9), total_s)

        threading.Thread(target=poll, name="rig-chirp-progress", daemon=True).start()
        try:
            return session.run(seconds=total_s, activate_after_s=settle_s)
        finally:
            done.set()

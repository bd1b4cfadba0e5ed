"""`rig chirp --out REC`: the paper's identification run, through the runtime loop.

The actuator alone on its test stand, open loop: the valve command follows a linear sine chirp (f0 -> f1 over
duration, paper: 0.1 -> 100 Hz in 100 s). Each loop period reads the sensors, writes the chirp sample (through
the safety limiter) and records time_s, valve_cmd_V, position_m, accel_mps2 of the chirped mount. Position is
sampled at t_k before the command of period k acts (ZOH), as the shared recordings and rig.identify assume.

Backends: sim (one StandPlant with the configured Table 1 parameters and sensor noise; simulated time by
default; effects and sensor noise from the config's [stand] section), hil (the real drivers against the emulated devices, each mount an actuator alone on its stand; real
time), hardware (the real rig; the chirp goes to --mount, the other valves stay at null; real time).
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from pathlib import Path

from rig.errors import RigError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=("sim", "hil", "hardware"), default=None,
                   help="backend (default: [backend] name in the config, else sim)")
    p.add_argument("--amplitude", type=float, default=2.0, metavar="V", help="chirp amplitude, V (default 2)")
    p.add_argument("--f0", type=float, default=0.1, metavar="HZ", help="start frequency, Hz (default 0.1)")
    p.add_argument("--f1", type=float, default=100.0, metavar="HZ", help="end frequency, Hz (default 100)")
    p.add_argument("--duration", type=float, default=100.0, metavar="S", help="chirp length, s (default 100)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="loop (and recording) rate, Hz (default: [loop] rate_hz; hil: [hil] rate_hz)")
    p.add_argument("--mount", default="front_left", help="mount whose valve is chirped (hil/hardware)")
    p.add_argument("--settle", type=float, default=0.05, metavar="S",
                   help="seconds INACTIVE (valve at null, sensors checked) before the chirp (default 0.05)")
    p.add_argument("--realtime", action="store_true", help="sim backend: pace on the wall clock (default: "
                   "simulated time, as fast as possible)")
    p.add_argument("--seed", type=int, default=None, help="sim backend: sensor noise seed (default: [stand] seed)")
    p.add_argument("--out", metavar="REC", type=Path, required=True,
                   help="recording to write (HDF5; with --csv the shared CSV format, gzip if it ends in .gz)")
    p.add_argument("--csv", action="store_true", help="write the shared CSV format instead of HDF5")
    from rig.excitation import parse_levels
    p.add_argument("--levels", type=parse_levels, default=None, metavar="V,V,...",
                   help="the same sweep at several amplitudes back to back, e.g. 0.5,1.5,3.0 (each --duration "
                        "long; rig diagnose then shows gain by level: saturation, deadband, linear)")
    p.add_argument("--multisine", action="store_true",
                   help="an odd random-phase multisine over f0..f1 instead of the chirp (--period per period, "
                        "--duration rounded to whole periods); its empty lines detect nonlinearity")
    p.add_argument("--period", type=float, default=10.0, metavar="S",
                   help="multisine period, s (default 10: 0.1 Hz line spacing)")


class ChirpController:
    """Open-loop controller for rig.loop: ignores the sensors, outputs the chirp. State = [k, running].

    The chirp starts (k = 0) when the loop enables the controller at activation (set_enabled(state, True));
    while disabled (INACTIVE, where the loop still steps controllers to keep them warm) it outputs null and
    does not advance. u_k = A sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))), t = k dt, for k dt < T; null after."""

    def __init__(self, amplitude_V: float, f0_hz: float, f1_hz: float, duration_s: float, active: bool = True):
        self.A, self.f0, self.f1, self.T = amplitude_V, f0_hz, f1_hz, duration_s
        self.active = active
        self._c = (f1_hz - f0_hz) / (2 * duration_s)

    def initial_state(self) -> list[float]:
        return [0.0, 0.0]

    def set_enabled(self, state, on):
        if on and not state[1]:
            return [0.0, 1.0]              # (re)start the chirp from its first sample
        return [state[0], 1.0 if on else 0.0]

    def step(self, state, meas, dt):
        k, running = state
        if not running:
            return 0.0, state
        t = k * dt
        if not self.active or t >= self.T:
            return 0.0, [k + 1.0, 1.0]
        return self.A * math.sin(2 * math.pi * (self.f0 * t + self._c * t * t)), [k + 1.0, 1.0]


class _ChirpRows:
    """Recorder adapter for the loop: keeps time, command, position and acceleration of one mount from the
    loop's row (column offsets from rig.loop.loop_channels, the layout the loop pushes). Never blocks."""

    def __init__(self, recorder, channels, mount: int) -> None:
        off, col = {}, 0
        for c in channels:
            off[c.name] = col
            col += c.width
        self.rec = recorder
        self.i_t = off["time_s"]
        self.i_u = off["valve_cmd_V"] + mount
        self.i_x = off["stroke_m"] + mount
        self.i_a = off["accel_mps2"] + mount

    def push(self, *row) -> bool:
        return self.rec.push(row[self.i_t], row[self.i_u], row[self.i_x], row[self.i_a])

    def event(self, t_s: float, text: str) -> None:
        self.rec.event(t_s, text)


class _StandBank:
    """Four actuators alone on their stands as a four-mount plant (for the HIL emulator)."""

    def __init__(self, stands) -> None:
        self.stands = stands
        self.accel_mps2 = [0.0] * len(stands)
        self.stroke_m = [0.0] * len(stands)
        self.table_m = self.stroke_m
        self.t_s = 0.0

    def step(self, valve_cmd_V) -> None:
        for i, s in enumerate(self.stands):
            x, a = s.step(float(valve_cmd_V[i]))
            self.stroke_m[i], self.accel_mps2[i] = float(x), float(a)
        self.t_s = self.stands[0].t_s


def _sim_effects(cfg, seed: int | None):
    """The [stand] section: effect switches and sensor noise (default 2e-8 m, 2e-4 m/s^2 rms as the shared
    recordings; real sensors are never bit-exact constant, and the loop's stuck check relies on that)."""
    from dataclasses import replace
    from sim_backend.actuator import Effects
    fx = Effects.from_config(cfg)
    return fx if seed is None else replace(fx, seed=seed)


def make_chirp_port(cfg, backend: str, dt: float, clock, *, seed: int | None = None, stand_params=None,
                    stand_effects=None):
    if backend == "sim":
        from sim_backend.backend import make_sim_port
        return make_sim_port(cfg, dt, mode="stand", clock=clock, seed=seed or 0, stand_params=stand_params,
                             stand_effects=stand_effects or _sim_effects(cfg, seed))
    try:
        import drivers
    except ImportError as e:
        raise RigError(f"--backend {backend}: the drivers package is not available ({e})") from None
    if backend == "hil":
        from sim_backend.actuator import StandPlant
        from sim_backend.linear import ActuatorParams
        p = stand_params or ActuatorParams.from_config(cfg)
        from dataclasses import replace
        fx = stand_effects or _sim_effects(cfg, seed)
        bank = _StandBank([StandPlant(p, replace(fx, seed=fx.seed + i), 1.0 / dt) for i in range(4)])
        return drivers.make_hil_port(cfg, plant=bank, dt=dt)
    return drivers.make_port(cfg, backend)


def run_chirp(cfg, *, backend: str = "sim", amplitude_V: float = 2.0, f0_hz: float = 0.1, f1_hz: float = 100.0,
              duration_s: float = 100.0, rate_hz: float | None = None, out: Path, csv: bool = False,
              mount: str = "front_left", settle_s: float = 0.05, sim_time: bool | None = None, seed: int | None = None,
              stand_params=None, stand_effects=None, progress=None, levels_V=None, multisine: bool = False,
              period_s: float = 10.0) -> dict:
    """Run the chirp through rig.loop and write the recording. Returns a summary dict.
    levels_V: the same chirp at each level back to back; multisine: an odd random-phase multisine instead
    (both from rig.excitation, played back sample by sample).
    progress: optional callable(t_s, total_s) polled from a helper thread."""
    from rig.clock import MonotonicClock, SimClock
    from rig.config import MOUNTS
    from rig.lifecycle import State
    from rig.loop import Loop, loop_channels
    from rig.recorder import Channel, Recorder
    from rig.recording import load_recording, save_recording_csv

    rate = float(rate_hz or (cfg.hil.rate_hz if backend == "hil" else cfg.loop.rate_hz))
    if backend == "hil":
        # driver threads deliver samples asynchronously: HIL runs use their own stale limit, watchdog and rate
        from rig.config import hil_run_config
        cfg = hil_run_config(cfg, rate)
    from rig import excitation
    signal = excitation.for_chirp_run(rate, duration_s, f0_hz, f1_hz, amplitude_V, levels_V=levels_V,
                                      multisine=multisine, period_s=period_s, seed=seed or 0)
    if signal is not None:
        amplitude_V, duration_s = signal.peak_V, signal.duration_s
    if amplitude_V <= 0 or amplitude_V > cfg.safety.valve_limit_V:
        raise RigError(f"--amplitude: expected 0 < V <= safety.valve_limit_V = {cfg.safety.valve_limit_V:g}, "
                       f"got {amplitude_V:g}")
    if not 0 <= f0_hz < f1_hz < rate / 2:
        raise RigError(f"--f0/--f1: expected 0 <= f0 < f1 < rate/2 = {rate / 2:g} Hz, got {f0_hz:g}, {f1_hz:g}")
    if duration_s <= 0:
        raise RigError(f"--duration: expected > 0 s, got {duration_s:g}")
    slew = 2 * math.pi * f1_hz * amplitude_V if signal is None else signal.slew_V_per_s
    if slew > cfg.safety.slew_V_per_s:
        raise RigError(f"--amplitude/--f1: the chirp slews {slew:.0f} V/s, above safety.slew_V_per_s = "
                       f"{cfg.safety.slew_V_per_s:g}")
    sim_time = (backend == "sim") if sim_time is None else sim_time
    if sim_time and backend != "sim":
        raise RigError("simulated time only with --backend sim")
    clock = SimClock() if sim_time else MonotonicClock()
    dt = 1.0 / rate
    out = Path(out)
    if out.is_dir():
        raise RigError(f"--out {out}: is a folder, expected a recording file name")
    port = make_chirp_port(cfg, backend, dt, clock, seed=seed, stand_params=stand_params,
                           stand_effects=stand_effects)
    n = int(port.n_mounts)
    if n == 1:
        m_idx, names = 0, ("stand",)
    else:
        if mount not in MOUNTS[:n]:
            raise RigError(f"--mount: expected one of {', '.join(MOUNTS[:n])}, got {mount!r}")
        m_idx, names = MOUNTS.index(mount), None
    ctrls = [ChirpController(amplitude_V, f0_hz, f1_hz, duration_s, active=(i == m_idx)) if signal is None
             else excitation.Playback(signal.cmd_V, active=(i == m_idx)) for i in range(n)]
    loop = Loop(cfg, port, ctrls, clock=clock, rate_hz=rate, names=names, isolation=True)
    h5_path = out if not csv else out.with_name(out.name + ".part.h5")
    rec = Recorder(h5_path, [Channel("time_s", "s", description="loop time since start"),
                             Channel("valve_cmd_V", "V", description="valve command written (after limits)"),
                             Channel("position_m", "m", description="displacement transducer at t_k"),
                             Channel("accel_mps2", "m/s^2", description="accelerometer at t_k")],
                   rate_hz=loop.rate_hz, flush_s=cfg.recording.flush_s, ring_s=max(cfg.recording.ring_s, 2.0),
                   chunk_rows=cfg.recording.chunk_rows,
                   attrs={"command": "rig chirp", "backend": backend, "config_source": cfg.source,
                          "mount": names[0] if n == 1 else mount, "amplitude_V": amplitude_V, "f0_hz": f0_hz,
                          "f1_hz": f1_hz, "duration_s": duration_s, "fs_hz": loop.rate_hz, "settle_s": settle_s,
                          "chirp": "linear" if signal is None else signal.kind,
                          **({} if signal is None else signal.attrs())}).start()
    loop.recorder = _ChirpRows(rec, loop_channels(loop.n, loop.state_len, loop.names), m_idx)
    total = settle_s + duration_s + 0.05        # a short null tail after the chirp
    done = threading.Event()

    def poll():
        while not done.wait(0.1):
            if progress and loop.t0_ns is not None:
                progress(min(total, (loop.t_ns - loop.t0_ns) * 1e-9), total)

    poller = threading.Thread(target=poll, name="rig-chirp-progress", daemon=True)
    wall0 = time.perf_counter()
    try:
        loop.configure()
        poller.start()
        reason = loop.run(seconds=total, activate_after_s=settle_s)
    finally:
        done.set()
        try:
            port.close()
        finally:
            rec.close(stop_reason=loop.stop_reason or "", fault_reason=loop.lc.fault_reason or "",
                      iterations=loop.iterations, overruns=loop.overruns, skipped_periods=loop.skipped)
    if progress and loop.t0_ns is not None:
        progress(min(total, (loop.t_ns - loop.t0_ns) * 1e-9 + loop.dt), total)
    wall = time.perf_counter() - wall0
    if loop.lc.state is State.FAULT:
        raise RigError(f"chirp stopped by a FAULT after {loop.iterations} periods: {loop.lc.fault_reason} "
                       f"(partial recording in {h5_path})")
    if csv:
        save_recording_csv(load_recording(h5_path), out)
        h5_path.unlink()
    tm = loop.timing_us()
    return {"recording": str(out), "format": "csv" if csv else "hdf5", "backend": backend, "rate_hz": loop.rate_hz,
            "periods": loop.iterations, "rows_written": rec.rows_written, "dropped_rows": rec.dropped_rows,
            "overruns": loop.overruns, "skipped_periods": loop.skipped, "stop_reason": reason,
            "wall_s": wall, "simulated_time": sim_time, "compute_us": tm["compute_us"]}


def run(args) -> int:
    from rig.config import load_config

    cfg = load_config(args.config)
    backend = args.backend or cfg.backend.name
    if args.realtime and backend != "sim":
        raise RigError("--realtime: only for --backend sim (hil and hardware always run in real time)")
    try:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
        bar = Progress(TextColumn("chirp"), BarColumn(), TextColumn("{task.completed:6.1f}/{task.total:.1f} s"),
                       TimeRemainingColumn(), console=Console(stderr=True), redirect_stdout=False)
    except ImportError:  # pragma: no cover - rich is a dependency
        bar = None
    task = None

    def progress(t_s, total_s):
        nonlocal task
        if bar is None:
            return
        if task is None:
            task = bar.add_task("chirp", total=total_s)
        bar.update(task, completed=t_s)

    if bar is not None:
        bar.start()
    try:
        s = run_chirp(cfg, backend=backend, amplitude_V=args.amplitude, f0_hz=args.f0, f1_hz=args.f1,
                      duration_s=args.duration, rate_hz=args.rate, out=args.out, csv=args.csv, mount=args.mount,
                      settle_s=args.settle, sim_time=(backend == "sim" and not args.realtime), seed=args.seed,
                      progress=progress, levels_V=args.levels, multisine=args.multisine, period_s=args.period)
    finally:
        if bar is not None:
            bar.stop()
    what = ("chirp at levels " + ",".join(f"{v:g}" for v in args.levels) + " V" if args.levels
            else f"odd multisine (period {args.period:g} s)" if args.multisine else "chirp")
    print(f"{what} {args.f0:g}->{args.f1:g} Hz, {args.amplitude:g} V, {args.duration:g} s on the {backend} backend at "
          f"{s['rate_hz']:g} Hz: {s['rows_written']} samples -> {s['recording']} ({s['format']}); "
          f"{s['wall_s']:.1f} s wall, overruns {s['overruns']}, dropped rows {s['dropped_rows']}", file=sys.stderr)
    if s["skipped_periods"]:
        print(f"WARNING: {s['skipped_periods']} loop periods were skipped (overruns): the recording's time is not "
              f"uniform and rig identify will refuse it; lower --rate or free the CPU", file=sys.stderr)
    else:
        print(f"next: rig identify {s['recording']}", file=sys.stderr)
    return 0

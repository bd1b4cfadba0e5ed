"""`rig run`: operate the rig on demand (sim, hil or hardware backend).

Start-up: configure (open the port) -> INACTIVE for --settle seconds (reading and checking, valve at null,
controllers stepped so their filters warm up) -> ACTIVE. On the hil and hardware backends the floor is already
moving when the loop starts, and the isolation controllers' double integration of acceleration needs a few
time constants of its blend to forget its cold start (2 / blend_hz: 5 s for the HIL design, 20 s for the
5 kHz design); activating earlier with isolation on put the HIL valves at the clamp (measured). So --settle
defaults to that warm-up there, and to 0.05 s on the sim backend (the simulated plant starts at rest with
the loop). Stop: --seconds elapsed, Ctrl-C (SIGINT) or SIGTERM -> safe stop (valve to null), recording closed.

Switching isolation while running (bumpless; stroke centring stays on):
  kill -USR1 <pid>                 toggles isolation on/off
  --control FILE                   the file is polled every 0.1 s; write one word into it:
                                   `on` / `off` (isolation), `stop` (safe stop)
The status line on stderr shows state, isolation, loop timing, overruns, strokes and commands.
Exit code: 0 after a normal stop, 1 after a fault (the reason is printed), 2 for a user error.
"""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time

from rig import cliargs
from rig.errors import RigError

log = logging.getLogger("rig.run")


def warmup_s(ctrls) -> float:
    """Time for the controllers' estimators to forget a cold start: 2 / blend_hz (about five time constants of
    the blend's slowest pole), 0.05 s for controllers without a blend."""
    blends = [c.p.blend_hz for c in ctrls if getattr(getattr(c, "p", None), "blend_hz", 0) > 0]
    return min(2.0 / min(blends), 60.0) if blends else 0.05


def add_arguments(p) -> None:
    p.add_argument("--backend", choices=("sim", "hil", "hardware"), default=None,
                   help="backend (default: [backend] name in the config, else sim)")
    p.add_argument("--seconds", type=cliargs.seconds(), default=None, metavar="N",
                   help="run for N seconds of loop time (default: until Ctrl-C / SIGTERM / `stop`)")
    p.add_argument("--isolation", choices=("on", "off"), default="on",
                   help="isolation at start (toggle while running: SIGUSR1 or --control FILE)")
    cliargs.output_arg(p, "--record", metavar="FILE", default=None, help="record the run to this HDF5 file")
    p.add_argument("--control", metavar="FILE", default=None,
                   help="control file polled every 0.1 s: write `on`, `off` or `stop` into it")
    p.add_argument("--settle", type=cliargs.seconds(ge=0, le=3600), default=None, metavar="S",
                   help="seconds INACTIVE (reading, checking, valve null, filters warming) before activation "
                        "(default: sim 0.05, hil/hardware the controllers' warm-up, 2 / blend_hz)")
    p.add_argument("--policy", choices=("skip", "catch_up"), default=None,
                   help="overrun policy (default [loop] overrun_policy)")
    p.add_argument("--no-realtime", action="store_true", help="do not try SCHED_FIFO/affinity/mlockall")
    p.add_argument("--sim-time", action="store_true",
                   help="sim backend only: run in simulated time (as fast as possible, lockstep)")
    p.add_argument("--quiet", action="store_true", help="no status line")


def make_port(cfg, backend: str, dt: float, clock):
    """The port for a backend name; hardware libraries are imported only for hil/hardware."""
    if backend == "sim":
        from sim_backend.backend import make_sim_port
        return make_sim_port(cfg, dt, mode="rig", clock=clock)
    try:
        import drivers
        factory = drivers.make_port
    except (ImportError, AttributeError) as e:
        raise RigError(f"--backend {backend}: needs drivers.make_port(cfg, backend_name) in drivers/__init__.py, "
                       f"which is not available ({e})") from None
    return factory(cfg, backend)


def make_controllers(cfg, dt: float, n_mounts: int):
    try:
        from controllers.isolation import make_isolation_controllers
    except ImportError as e:
        raise RigError(f"controllers: needs make_isolation_controllers(cfg, dt) in controllers/isolation.py, "
                       f"which is not available ({e})") from None
    ctrls = list(make_isolation_controllers(cfg, dt))
    if len(ctrls) != n_mounts:
        raise RigError(f"controllers: make_isolation_controllers gave {len(ctrls)} controllers for "
                       f"{n_mounts} mounts")
    return ctrls


class _Status(threading.Thread):
    """Live status line on stderr (a carriage-return line on a terminal, one line a second otherwise)."""

    def __init__(self, loop, quiet: bool) -> None:
        super().__init__(name="rig-status", daemon=True)
        self.loop, self.quiet = loop, quiet
        self.tty = sys.stderr.isatty()
        self._halt = threading.Event()

    def line(self) -> str:
        lp = self.loop
        t = (lp.t_ns - lp.t0_ns) * 1e-9 if lp.t0_ns is not None else 0.0
        tm = lp.timing_us()
        m = lp.last_meas
        xs = " ".join(f"{x * 1e6:+7.2f}" for x in m.stroke_m) if m is not None else "-"
        us = " ".join(f"{u:+5.2f}" for u in lp.cmd)
        return (f"t={t:7.2f}s {lp.state.name:8s} iso={'on ' if lp.isolation else 'off'} "
                f"wake p99={tm['wake_latency_us']['p99']:6.1f}us compute p99={tm['compute_us']['p99']:5.1f}us "
                f"overruns={lp.overruns} stroke_um=[{xs}] cmd_V=[{us}]")

    def run(self) -> None:
        period = 0.25 if self.tty else 1.0
        while not self._halt.wait(period):
            if not self.quiet:
                s = self.line()
                sys.stderr.write(("\r" + s + "\x1b[K") if self.tty else (s + "\n"))
                sys.stderr.flush()

    def stop(self) -> None:
        self._halt.set()
        if self.ident is None:              # never started (the start-up failed): nothing to join
            return
        self.join(timeout=1.0)
        if self.tty and not self.quiet:
            sys.stderr.write("\n")


class _ControlFile(threading.Thread):
    """Polls a control file every 0.1 s: `on` / `off` switch isolation, `stop` stops safely."""

    def __init__(self, path: str, loop) -> None:
        super().__init__(name="rig-control", daemon=True)
        self.path, self.loop = path, loop
        self._halt = threading.Event()
        self._last = None

    def run(self) -> None:
        while not self._halt.wait(0.1):
            try:
                st = os.stat(self.path)
                key = (st.st_mtime_ns, st.st_size)
                if key == self._last:
                    continue
                self._last = key
                with open(self.path) as f:
                    word = f.read().strip().lower()
            except OSError:
                continue
            if word in ("on", "isolation on"):
                self.loop.request_isolation(True)
            elif word in ("off", "isolation off"):
                self.loop.request_isolation(False)
            elif word == "stop":
                self.loop.stop("control file: stop")
            elif word:
                log.warning("%s: unknown control word %r (expected on, off or stop)", self.path, word)

    def stop(self) -> None:
        self._halt.set()
        if self.ident is not None:          # started
            self.join(timeout=1.0)


def run(args) -> int:
    from rig.clock import MonotonicClock, SimClock
    from rig.config import load_config
    from rig.lifecycle import State
    from rig.loop import Loop, loop_channels
    from rig.recorder import Recorder
    from rig.rt import enter_realtime, leave_realtime

    if not logging.getLogger().handlers:
        # our own INFO lines (lifecycle, start/stop); libraries (canopen, pymodbus) only from WARNING
        logging.basicConfig(level=logging.WARNING, format="rig run: %(message)s", stream=sys.stderr)
        logging.getLogger("rig").setLevel(logging.INFO)
    cfg = load_config(args.config)
    backend = args.backend or cfg.backend.name
    if args.seconds is not None and args.seconds <= 0:
        raise RigError(f"--seconds: expected > 0, got {args.seconds}")
    if args.settle is not None and not 0 <= args.settle <= 3600:
        raise RigError(f"--settle: expected 0 <= S <= 3600, got {args.settle}")
    if args.sim_time and backend != "sim":
        raise RigError("--sim-time: only with --backend sim")
    if args.settle is not None:
        cliargs.check_settle(args.settle, args.seconds)
    hil = getattr(cfg, "hil", None)
    if backend == "hil" and hil is not None:
        # HIL runs at the [hil] rate with its staleness limit and watchdog (Modbus and the shared machine)
        from rig.config import hil_run_config
        cfg = hil_run_config(cfg)
        cliargs.check_rate(cfg, cfg.loop.rate_hz, "[hil] rate_hz", sections=("controller",))
    dt = 1.0 / cfg.loop.rate_hz
    clock = SimClock() if args.sim_time else MonotonicClock()
    port = make_port(cfg, backend, dt, clock)
    ctrls = make_controllers(cfg, dt, port.n_mounts)
    loop = Loop(cfg, port, ctrls, clock=clock, isolation=(args.isolation == "on"), overrun_policy=args.policy)
    dt = loop.dt
    rec = None
    if args.record:
        rec = Recorder(args.record, loop_channels(loop.n, loop.state_len, loop.names), rate_hz=loop.rate_hz,
                       flush_s=cfg.recording.flush_s, ring_s=cfg.recording.ring_s,
                       chunk_rows=cfg.recording.chunk_rows,
                       attrs={"config_source": cfg.source, "backend": backend, "command": "rig run",
                              "isolation_at_start": args.isolation, "overrun_policy": loop.policy}).start()
        loop.recorder = rec

    def on_signal(signum, frame):
        loop.stop(signal.Signals(signum).name)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    old[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, lambda s, f: loop.toggle_isolation())
    status = _Status(loop, args.quiet)
    ctl = _ControlFile(args.control, loop) if args.control else None
    rt = pre = None
    want_rt = cfg.loop.realtime and not args.no_realtime and clock.is_real
    try:
        if want_rt:
            # process-wide part first: mlockall and a GC pass hold up every thread (a driver thread stalled
            # for >100 ms if done after the port was opened); then the port's threads start already locked
            pre = enter_realtime(priority=0, cpu=None, cpu_latency_us=cfg.loop.cpu_latency_us)
        loop.configure()
        log.info("backend %s, %d mounts at %g Hz, isolation %s, pid %d (SIGUSR1 toggles isolation%s)",
                 backend, loop.n, loop.rate_hz, args.isolation, os.getpid(),
                 f", control file {args.control}" if ctl else "")
        status.start()
        if ctl:
            ctl.start()
        if want_rt:   # per-thread part, for the loop thread only: helper threads are already running
            rt = enter_realtime(priority=cfg.loop.rt_priority, cpu=cfg.loop.cpu, lock_memory=False,
                                freeze_gc=False)
        settle = args.settle if args.settle is not None else (0.05 if backend == "sim" else warmup_s(ctrls))
        cliargs.check_settle(settle, args.seconds, default="the default --settle")
        if settle > 1.0:
            log.info("warming up the controllers for %.1f s before activation (valves at null)", settle)
        reason = loop.run(seconds=args.seconds, activate_after_s=settle)
    finally:
        for st in (rt, pre):
            if st is not None:
                leave_realtime(st)
        status.stop()
        if ctl:
            ctl.stop()
        for s, h in old.items():
            signal.signal(s, h)
        try:
            port.close()
        finally:
            if rec is not None:
                rec.close(stop_reason=loop.stop_reason or "", fault_reason=loop.lc.fault_reason or "",
                          iterations=loop.iterations, overruns=loop.overruns, skipped_periods=loop.skipped)
    tm = loop.timing_us()
    log.info("stopped (%s) after %d periods: overruns %d, missed deadlines %.4f %%, wake p99 %.1f us, "
             "compute p99 %.1f us%s", reason, loop.iterations, loop.overruns,
             100 * loop.missed_deadline_fraction, tm["wake_latency_us"]["p99"], tm["compute_us"]["p99"],
             f", recorded to {args.record}" if rec else "")
    if loop.lc.state is State.FAULT:
        return 1                          # the reason was logged once, when it happened
    return 0

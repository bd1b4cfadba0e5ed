"""One way to build a run: `Session` builds and tears down the port, the controllers, the loop, the recorder,
the real-time set-up, signal handling and the helper threads (status line, control file).

    with Session(cfg, "sim", clock=SimClock(), record="run.h5") as s:
        s.run(seconds=10, activate_after_s=0.05)

The commands (rig/commands/) are thin over it, and so is anything that drives a run from another thread
(a console): the requests below are the loop's thread-safe ones, applied at the next period boundary, and
`snapshot()` is the published state. A configuration the loop cannot run raises at construction
(rig.errors.ConfigError), never a silent fallback.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time

from controllers import isolation as _isolation
from controllers.feedforward import make_feedforward_filters
from controllers.isolation import make_isolation_controllers
from rig.backends import make_port
from rig.clock import MonotonicClock
from rig.config import MOUNTS, Config, mount_names
from rig.errors import ConfigError
from rig.kernel import period_entry
from rig.loop import Loop
from rig.recorder import Recorder
from rig.rt import enter_realtime, leave_realtime
from rig.tap import Columns

log = logging.getLogger("rig.session")


class Session:
    """A run from a config and a backend name. controllers: a list (one per mount), a callable
    (cfg, dt) -> list, or None for the isolation controllers of cfg.controller. record: an HDF5 path (the
    loop's layout, or `columns`: a Columns selection of it); realtime: the loop thread's real-time set-up
    (real clock only); signals: SIGINT/SIGTERM stop the run safely, SIGUSR1 toggles isolation;
    status / control_file: the status line on stderr, a control file polled for on/off/stop.
    Floor feedforward ([sensors] floor_accel, isolation controllers on every mount): built into the loop's
    period (controllers/feedforward.py, [controller] ff_*), off at the start unless feedforward=True;
    the mode switches live (request_mode). feedforward=True without floor sensors raises ConfigError."""

    def __init__(self, cfg: Config, backend: str = "sim", *, controllers=None, clock=None,
                 rate_hz: float | None = None, port_options: dict | None = None, isolation: bool = True,
                 overrun_policy: str | None = None, names: tuple[str, ...] | None = None,
                 keep_timing: int = 1 << 15, stop_on_fault: bool = True, watchdog_thread: bool | None = None,
                 record=None, record_attrs: dict | None = None, columns: "Columns | None" = None,
                 realtime: bool = False, signals: bool = False, status: bool = False,
                 control_file: str | None = None, feedforward: bool = False) -> None:
        self.cfg = cfg
        self.backend = backend
        self.clock = clock if clock is not None else MonotonicClock()
        self.rate_hz = float(rate_hz or cfg.loop.rate_hz)
        self.dt = 1.0 / self.rate_hz
        self._controllers = controllers
        self._port_options = dict(port_options or {})
        self._loop_kw = dict(isolation=isolation, overrun_policy=overrun_policy, names=names,
                             keep_timing=keep_timing, stop_on_fault=stop_on_fault, watchdog_thread=watchdog_thread,
                             feedforward_on=bool(feedforward))
        if feedforward and not cfg.sensors.floor_accel:
            raise ConfigError(f"{cfg.source}: the floor feedforward needs floor accelerometers: "
                              f"sensors.floor_accel = true")
        self.record = record
        self._record_attrs = dict(record_attrs or {})
        self.columns = columns
        self.realtime = bool(realtime) and self.clock.is_real
        self._signals, self._status, self._control_file = signals, status, control_file
        self.port = self.loop = self.recorder = None
        self.idle_recorder = None       # what the loop records into between recordings (a console's live ring)
        self._stack: contextlib.ExitStack | None = None
        self._rt_loop = None

    # ---- build and tear down --------------------------------------------------------------------------
    def __enter__(self) -> "Session":
        stack = self._stack = contextlib.ExitStack()
        try:
            if self._signals:
                self._install_signals(stack)
            # the period's compiled entry before the port: a port may start devices (the HIL's emulated rig runs
            # from here on), and a cold numba cache compiles for tens of seconds while they wait unserved
            period_entry(len(MOUNTS), bool(self.cfg.sensors.floor_accel))
            self.port = make_port(self.cfg, self.backend, dt=self.dt, clock=self.clock, **self._port_options)
            stack.callback(self.port.close)         # opened by the loop's configure, closed last
            ctrls = self._controllers
            if ctrls is None:
                ctrls = make_isolation_controllers(self.cfg, self.dt)
            elif callable(ctrls):
                ctrls = ctrls(self.cfg, self.dt)
            self.loop = Loop(self.cfg, self.port, list(ctrls), clock=self.clock, rate_hz=self.rate_hz,
                             feedforward=self._feedforward(ctrls), **self._loop_kw)
            if self.record is not None:
                self.recorder = self._start_recorder(stack)
            stack.callback(self.loop.safe_stop)
            if self.realtime:
                # process-wide part first: mlockall and a GC pass hold up every thread (a driver thread stalled
                # for >100 ms when done after the port was opened); the port's threads then start locked
                pre = enter_realtime(priority=0, cpu=None, cpu_latency_us=self.cfg.loop.cpu_latency_us)
                stack.callback(leave_realtime, pre)
            self.loop.configure()
            if self._status:
                stack.enter_context(_StatusLine(self.loop))
            if self._control_file:
                stack.enter_context(_ControlFile(self._control_file, self))
        except BaseException:
            stack.close()
            raise
        return self

    def _start_recorder(self, stack) -> Recorder:
        cfg, loop = self.cfg, self.loop
        channels = self.columns.channels if self.columns is not None else loop.channels
        rec = Recorder(self.record, channels, rate_hz=self.rate_hz, flush_s=cfg.recording.flush_s,
                       ring_s=cfg.recording.ring_s, chunk_rows=cfg.recording.chunk_rows,
                       attrs={"config_source": cfg.source, "backend": self.backend, **self._record_attrs},
                       wait_when_full=not self.clock.is_real)
        stack.enter_context(rec)
        stack.callback(lambda: rec.set_final_attrs(**self.final_attrs()))
        loop.recorder = self.columns.adapter(rec, loop.kernel.layout) if self.columns is not None else rec
        return rec

    def _feedforward(self, ctrls) -> list | None:
        """The floor feedforward filters, one per mount: with floor accelerometers and isolation controllers
        on every mount (other kinds run without it)."""
        if not self.cfg.sensors.floor_accel or not all(getattr(c, "kind", None) == _isolation.KIND for c in ctrls):
            if self._loop_kw["feedforward_on"]:
                raise ConfigError("Session: feedforward=True needs isolation controllers on every mount")
            return None
        names = self._loop_kw["names"] or mount_names(self.port.n_mounts)
        return make_feedforward_filters(self.cfg, self.dt, names=tuple(names))

    def __exit__(self, *exc) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            stack.close()

    def final_attrs(self) -> dict:
        lp = self.loop
        return {"stop_reason": lp.stop_reason or "", "fault_reason": lp.lc.fault_reason or "",
                "iterations": lp.iterations, "overruns": lp.overruns, "skipped_periods": lp.skipped}

    def _install_signals(self, stack) -> None:
        def on_stop(signum, frame):          # a safe stop while running, an interrupt during set-up
            if self.loop is not None:
                self.loop.stop(signal.Signals(signum).name)
            else:
                raise KeyboardInterrupt
        try:
            old = {s: signal.signal(s, on_stop) for s in (signal.SIGINT, signal.SIGTERM)}
            old[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, lambda s, f: self.loop and
                                                self.loop.toggle_isolation())
        except ValueError:                   # not the main thread: the caller handles signals
            return
        stack.callback(lambda: [signal.signal(s, h) for s, h in old.items()])

    # ---- the run -------------------------------------------------------------------------------------
    def run(self, seconds: float | None = None, iterations: int | None = None,
            activate_after_s: float | None = None) -> str:
        """Run the loop (see Loop.run), the loop thread's real-time set-up held meanwhile. The stop reason."""
        if self.loop is None:
            raise ConfigError("Session.run: use the session in a with-statement")
        rt = None
        if self.realtime:   # per-thread part, for the loop thread only: helper threads are already running
            rt = enter_realtime(priority=self.cfg.loop.rt_priority, cpu=self.cfg.loop.cpu, lock_memory=False,
                                freeze_gc=False)
        try:
            return self.loop.run(seconds=seconds, iterations=iterations, activate_after_s=activate_after_s)
        finally:
            if rt is not None:
                leave_realtime(rt)
                self.rt_summary = rt.summary()

    # ---- requests and published state (any thread) -------------------------------------------------
    def request_isolation(self, on: bool) -> None:
        self.loop.request_isolation(on)

    def request_active(self, on: bool) -> None:
        self.loop.request_active(on)

    def request_mode(self, mode: str) -> None:
        """off / feedback / feedback_feedforward, bumpless, at the next period boundary (rig.gate.MODES)."""
        self.loop.request_mode(mode)

    def reset_fault(self) -> None:
        self.loop.gate.request_reset_fault()

    def safe_stop(self, reason: str = "stop requested") -> None:
        self.loop.stop(reason)

    def start_recording(self, path, **attrs) -> Recorder:
        """Record the loop's rows to `path` from the next period on (a running session)."""
        rec = Recorder(path, self.loop.channels, rate_hz=self.rate_hz, flush_s=self.cfg.recording.flush_s,
                       ring_s=self.cfg.recording.ring_s, chunk_rows=self.cfg.recording.chunk_rows,
                       attrs={"config_source": self.cfg.source, "backend": self.backend, **attrs}).start()
        self.loop.gate.request_recorder(rec)
        return rec

    def stop_recording(self, rec: Recorder, timeout_s: float = 1.0) -> None:
        """Stop recording into `rec` at the next period boundary (back to idle_recorder), then close it."""
        self.loop.gate.request_recorder(self.idle_recorder)
        end = time.monotonic() + timeout_s
        while self.loop.recorder is rec and time.monotonic() < end:
            time.sleep(0.002)
        rec.close(**self.final_attrs())

    def snapshot(self) -> dict:
        """The loop's state as published for other threads (a status line, a console): plain values."""
        lp = self.loop
        m = lp.last_meas
        return {"t_s": (lp.t_ns - lp.t0_ns) * 1e-9 if lp.t0_ns is not None else 0.0, "state": lp.state.name,
                "isolation": lp.isolation, "mode": lp.mode, "fault_reason": lp.lc.fault_reason,
                "iterations": lp.iterations,
                "overruns": lp.overruns, "skipped_periods": lp.skipped, "valve_cmd_V": lp.cmd,
                "stroke_m": list(m.stroke_m) if m is not None else None,
                "accel_mps2": list(m.accel_mps2) if m is not None else None, "timing_us": lp.timing_us()}


class _Helper(threading.Thread):
    """A helper thread of the session: started on entry, halted and joined on exit."""

    def __init__(self, name: str) -> None:
        super().__init__(name=name, daemon=True)
        self._halt = threading.Event()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self._halt.set()
        self.join(timeout=1.0)


class _StatusLine(_Helper):
    """Live status line on stderr (a carriage-return line on a terminal, one line a second otherwise)."""

    def __init__(self, loop) -> None:
        super().__init__("rig-status")
        self.loop = loop
        self.tty = sys.stderr.isatty()

    def __exit__(self, *exc) -> None:
        super().__exit__(*exc)
        if self.tty:
            sys.stderr.write("\n")

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
            s = self.line()
            sys.stderr.write(("\r" + s + "\x1b[K") if self.tty else (s + "\n"))
            sys.stderr.flush()


class _ControlFile(_Helper):
    """Polls a control file every 0.1 s: `on` / `off` switch isolation, `feedback` / `feedback_feedforward`
    the mode, `stop` stops safely."""

    def __init__(self, path: str, session: Session) -> None:
        super().__init__("rig-control")
        self.path, self.session = path, session
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
                self.session.request_isolation(True)
            elif word in ("off", "isolation off"):
                self.session.request_isolation(False)
            elif word == "stop":
                self.session.safe_stop("control file: stop")
            elif word in ("feedback", "feedback_feedforward"):
                try:
                    self.session.request_mode(word)
                except ValueError as e:
                    log.warning("%s: %s", self.path, e)
            elif word:
                log.warning("%s: unknown control word %r (expected on, off, feedback, feedback_feedforward or stop)",
                            self.path, word)

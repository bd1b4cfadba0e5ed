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
import warnings

from controllers import isolation as _isolation
from controllers.analysis import unstable_loops
from controllers.feedforward import make_feedforward_filters
from controllers.isolation import make_isolation_controllers
from controllers.modes import MODES, ModeRequest, make_operating_controllers, parse_request
from rig.backends import devices, make_port
from rig.runtime.clock import MonotonicClock
from rig.config import Config, layout_mounts, mount_names
from rig.errors import ConfigError, RigError
from rig.runtime.gate import ISOLATION_MODES
from rig.runtime.kernel import io_entry
from rig.runtime.lifecycle import State
from rig.runtime.lock import RigLock
from rig.runtime.loop import Loop
from rig.runtime.recorder import WRITER_PRIORITY, Recorder
from rig.runtime.rt import enter_realtime, leave_realtime
from rig.runtime.signals import interrupt, take_held
from rig.runtime.supervisor import warm as warm_supervisor
from rig.runtime.tap import Columns
from rig.textfile import read_text

log = logging.getLogger("rig.session")


class NeverActivated(UserWarning):
    """A run that never went ACTIVE: the controllers ran, the valves stayed at null."""


class Session:
    """A run from a config and a backend name. controllers: a list (one per mount), a callable
    (cfg, dt) -> list, or None for the layout's: the isolation controllers of cfg.controller on the machine,
    the operating modes (controllers/modes.py) on stands, starting in `mode` (a ModeRequest or its text,
    default hold). record: an HDF5 path (the loop's layout, or `columns`: a Columns selection of it);
    realtime: the loop thread's real-time set-up (real clock only); signals: SIGINT/SIGTERM stop the run
    safely, SIGUSR1 toggles isolation (operating modes: isolate <-> hold), SIGUSR2 (operating modes) off <->
    hold (signals held since start-up are applied at the first period, rig/runtime/signals.py); status /
    control_file: the status line on stderr, a control file polled for control words (`control`; its folder
    must exist; only changes after the start count); script: [(loop time s, control word)], applied at those
    period boundaries; stability_check: refuse isolation controllers `rig design` calls unstable; rate_check:
    refuse a rate the loop cannot hold (measured over its first periods, rig/runtime/scheduler.py). The devices the
    backend drives are locked for the session (rig/runtime/lock.py): a second process driving them is refused,
    naming the holder.
    Floor feedforward ([sensors] floor_accel, isolation controllers on every mount): built into the loop's
    period (controllers/feedforward.py, [controller] ff_*), off at the start unless feedforward=True; the
    isolation mode (off / feedback / feedback_feedforward, not an operating mode) switches live
    (request_isolation_mode). feedforward=True without floor sensors raises ConfigError. record_floor: the floor
    accelerometers in the loop and its recording whatever the controllers (`rig commission` checks them against
    the table): without isolation controllers on every mount the feedforward's filters are built switched off and
    stay off (feedback_feedforward is refused), so the commands are the controllers' own."""

    def __init__(self, cfg: Config, backend: str = "sim", *, controllers=None, clock=None,
                 rate_hz: float | None = None, port_options: dict | None = None, isolation: bool = True,
                 overrun_policy: str | None = None, names: tuple[str, ...] | None = None,
                 keep_timing: int = 1 << 15, stop_on_fault: bool = True, watchdog_thread: bool | None = None,
                 rate_check: bool = True, stability_check: bool = False, record=None,
                 record_attrs: dict | None = None, columns: "Columns | None" = None,
                 realtime: bool = False, signals: bool = False, status: bool = False,
                 control_file: str | None = None, mode=None, script=None, feedforward: bool = False,
                 record_floor: bool = False) -> None:
        self.cfg = cfg
        self.backend = backend
        self.clock = clock if clock is not None else MonotonicClock()
        self.rate_hz = float(rate_hz or cfg.loop.rate_hz)
        self.dt = 1.0 / self.rate_hz
        self._controllers = controllers
        self._stability_check = stability_check
        self._port_options = dict(port_options or {})
        self._loop_kw = dict(isolation=isolation, overrun_policy=overrun_policy, names=names,
                             keep_timing=keep_timing, stop_on_fault=stop_on_fault, watchdog_thread=watchdog_thread,
                             rate_check=rate_check, feedforward_on=bool(feedforward))
        for asked, what in ((feedforward, "the floor feedforward"), (record_floor, "recording the floor")):
            if asked and not cfg.sensors.floor_accel:
                raise ConfigError(f"{cfg.source}: {what} needs floor accelerometers: sensors.floor_accel = true")
        self._record_floor = bool(record_floor)
        self._floor_only = False         # the feedforward built for the recording only (it cannot be switched on)
        self.record = record
        self._record_attrs = dict(record_attrs or {})
        self.columns = columns
        self.realtime = bool(realtime) and self.clock.is_real
        self._signals, self._status, self._control_file = signals, status, control_file
        if control_file is not None:
            folder = os.path.dirname(os.path.abspath(control_file))
            if not os.path.isdir(folder):
                raise ConfigError(f"control file {control_file}: folder {folder} does not exist (the file is "
                                  f"polled there for control words)")
            if os.path.exists(control_file) and not os.path.isfile(control_file):
                kind = "a folder" if os.path.isdir(control_file) else "a pipe or device"
                raise ConfigError(f"control file {control_file}: is {kind}, expected a file name (polled for "
                                  f"control words)")
        self._held_signals: list[int] = []     # SIGUSR1/2 before the loop existed: applied at its first period
        self._mode = self.parse(mode, "mode") if isinstance(mode, str) else mode
        self._script = [(float(t), w) for t, w in (script or ())]
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
            stack.enter_context(RigLock(devices(self.cfg, self.backend)))
            ctrls = self._make_controllers()
            for t, w in self._script:              # a word this layout cannot take fails here, not mid-run
                self._check_word(w, any(hasattr(c, "switch") for c in ctrls), f"script at {t:g} s")
            ffs = self._feedforward(ctrls)
            # the period's compiled entry before the port: a port may start devices (the HIL's emulated rig runs
            # from here on), and a cold numba cache compiles for tens of seconds while they wait unserved
            io_entry()
            warm_supervisor()
            self.port = make_port(self.cfg, self.backend, dt=self.dt, clock=self.clock, **self._port_options)
            stack.callback(self.port.close)         # opened by the loop's configure, closed last
            kw = dict(self._loop_kw)
            kw["names"] = self._names(ctrls)
            self.loop = Loop(self.cfg, self.port, ctrls, clock=self.clock, rate_hz=self.rate_hz,
                             feedforward=ffs, **kw)
            if self.realtime:     # the safety net preempts the loop it watches (a hung loop, a busy machine)
                self.loop.sched.watchdog_priority = min(99, self.cfg.loop.rt_priority + 10)
            for t, word in self._script:
                self.loop.gate.schedule(t, lambda w=word, t=t: self.control(w, f"script at {t:g} s"))
            self._apply_held_signals()
            if self.record is not None:
                self.recorder = self._start_recorder(stack)
            stack.callback(self.loop.safe_stop)
            if self.realtime:
                # process-wide part first: mlockall and a GC pass hold up every thread (a driver thread stalled
                # for >100 ms when done after the port was opened); the port's threads then start locked
                pre = enter_realtime(priority=0, cpu=None, cpu_latency_us=self.cfg.loop.cpu_latency_us,
                                     idle_poll=self.cfg.loop.idle_poll)
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
                       compression=cfg.recording.compression,
                       attrs={"config_source": cfg.source, "backend": self.backend,
                              **({"calibration": cfg.drivers.calibration} if cfg.drivers.calibration else {}),
                              **self._record_attrs},
                       wait_when_full=not self.clock.is_real,
                       priority=WRITER_PRIORITY if self.realtime else 0)
        stack.enter_context(rec)
        stack.callback(lambda: rec.set_final_attrs(**self.final_attrs()))
        loop.recorder = self.columns.adapter(rec, loop.kernel.layout) if self.columns is not None else rec
        return rec

    def _make_controllers(self) -> list:
        """The controllers, one per mount: as given, from the callable, or the layout's (operating modes on
        stands, the isolation controllers of cfg.controller on the machine)."""
        ctrls = self._controllers
        if ctrls is None and self.cfg.layout.plant == "stand":
            ctrls = make_operating_controllers(self.cfg, self.dt, self._mode)
        elif ctrls is None:
            if self._mode is not None:
                raise ConfigError(f"{self.cfg.source}: operating modes run on the stand layout "
                                  f"([layout] plant = \"stand\"); the machine runs isolation")
            ctrls = make_isolation_controllers(self.cfg, self.dt)
            if self._stability_check:
                check_stable(self.cfg, ctrls, self.dt)
        elif callable(ctrls):
            ctrls = ctrls(self.cfg, self.dt)
        return list(ctrls)

    def _names(self, ctrls) -> tuple[str, ...] | None:
        """The mount names: as given, else the layout's when the controllers are one per layout mount."""
        names = self._loop_kw["names"]
        if names is None and len(ctrls) == len(layout_mounts(self.cfg)):
            names = layout_mounts(self.cfg)
        return names

    def _feedforward(self, ctrls) -> list | None:
        """The floor feedforward filters, one per mount: with floor accelerometers and isolation controllers
        on every mount (other kinds run without it)."""
        isolating = all(getattr(c, "kind", None) == _isolation.KIND for c in ctrls)
        if not self.cfg.sensors.floor_accel or not (isolating or self._record_floor):
            if self._loop_kw["feedforward_on"]:
                raise ConfigError("Session: feedforward=True needs isolation controllers on every mount")
            return None
        if not isolating and self._loop_kw["feedforward_on"]:
            raise ConfigError("Session: feedforward=True needs isolation controllers on every mount")
        self._floor_only = not isolating
        names = self._names(ctrls) or mount_names(len(ctrls))
        return make_feedforward_filters(self.cfg, self.dt, names=tuple(names))

    def __exit__(self, *exc) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            stack.close()

    def final_attrs(self) -> dict:
        lp = self.loop
        return {"stop_reason": lp.stop_reason or "", "fault_reason": lp.lc.fault_reason or "",
                "iterations": lp.iterations, "overruns": lp.overruns, "skipped_periods": lp.skipped,
                "harm": lp.harm or ""}

    def _install_signals(self, stack) -> None:
        def on_stop(signum, frame):          # a safe stop while running, an interrupt during set-up
            if self.loop is not None:
                self.loop.stop(signal.Signals(signum).name)
            else:
                interrupt(signum)

        def on_usr(signum, frame):
            self._usr_signal(signum)
        try:
            old = {s: signal.signal(s, on_stop) for s in (signal.SIGINT, signal.SIGTERM)}
            old[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, on_usr)
            old[signal.SIGUSR2] = signal.signal(signal.SIGUSR2, on_usr)
        except ValueError:                   # not the main thread: the caller handles signals
            return
        self._held_signals += [signal.SIGUSR1] * take_held()
        stack.callback(lambda: [signal.signal(s, h) for s, h in old.items()])

    def _usr_signal(self, signum: int) -> None:
        """SIGUSR1: isolation toggle (operating modes: isolate <-> hold); SIGUSR2 (operating modes): off <->
        hold. Held until the loop exists."""
        if self.loop is None:
            self._held_signals.append(signum)
        elif not self.operated:
            if signum == signal.SIGUSR1:
                self.loop.toggle_isolation()
        else:
            other = "isolate" if signum == signal.SIGUSR1 else "off"
            self.control("hold" if self.modes()[0] == other else other, signal.Signals(signum).name)

    def _apply_held_signals(self) -> None:
        held, self._held_signals = self._held_signals, []
        if not held:
            return
        if not self.operated:                    # toggles: a pair cancels
            if held.count(signal.SIGUSR1) % 2:
                log.info("isolation toggle (SIGUSR1) received during start-up: applied at the first period")
                self.loop.toggle_isolation()
            return
        log.info("%s received during start-up: applied at the first period",
                 ", ".join(signal.Signals(s).name for s in held))
        for s in held:
            self._usr_signal(s)

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
            reason = self.loop.run(seconds=seconds, iterations=iterations, activate_after_s=activate_after_s)
        finally:
            if rt is not None:
                leave_realtime(rt)
                self.rt_summary = rt.summary()
        if self.loop.iterations == 0 and reason in ("SIGINT", "SIGTERM"):
            interrupt(signal.Signals[reason])       # before the first period: an interrupt of the set-up
        if not self.activated and reason in ("time", "iterations") and self.loop.lc.fault_reason is None:
            warnings.warn(NeverActivated(
                "Session.run: the rig stayed INACTIVE for the whole run (valves at null, nothing controlled): "
                "pass activate_after_s= (e.g. 0.05 in simulated time) or call request_active(True)"), stacklevel=2)
        return reason

    @property
    def activated(self) -> bool:
        """Whether the loop went ACTIVE (valves under control) at any time so far."""
        return self.loop is not None and any(state is State.ACTIVE for _, state in self.loop.lc.history)

    # ---- requests and published state (any thread) -------------------------------------------------
    def request_isolation(self, on: bool) -> None:
        self.loop.request_isolation(on)

    def request_active(self, on: bool) -> None:
        self.loop.request_active(on)

    def request_isolation_mode(self, mode: str) -> None:
        """off / feedback / feedback_feedforward, bumpless, at the next period boundary
        (rig.runtime.gate.ISOLATION_MODES; not an operating mode: request_mode)."""
        if mode == "feedback_feedforward" and self._floor_only:
            raise ValueError("isolation mode feedback_feedforward: the floor is recorded here, its feedforward "
                             "runs with isolation controllers only")
        self.loop.request_isolation_mode(mode)

    def reset_fault(self) -> None:
        self.loop.gate.request_reset_fault()

    # ---- operating modes (the stand layout) ---------------------------------------------------------------
    @property
    def operated(self) -> list[int]:
        """The mounts whose controller has operating modes."""
        return [m for m, c in enumerate(self.loop.ctrls) if hasattr(c, "switch")] if self.loop else []

    def parse(self, text: str, where: str = "mode request") -> ModeRequest:
        """A request from its text (controllers/modes.py parse_request; RigError naming what is wrong)."""
        return parse_request(text, self.dt, max_profile_s=self.cfg.controller.track_profile_s, where=where)

    def modes(self) -> list[str]:
        """The mode of each operated mount (as requested last)."""
        return [self.loop.ctrls[m].current.mode for m in self.operated]

    def request_mode(self, request, mount: str | int | None = None) -> ModeRequest:
        """An operating mode for one mount (name or index) or all operated ones, at the next period boundary,
        bumpless. request: a ModeRequest or its text. Checked first: a reference the actuator cannot follow
        raises RigError with one line and changes nothing (never a clamp)."""
        req = self.parse(request) if isinstance(request, str) else request
        ops = self.operated
        if not ops:
            raise RigError("mode request: this run has no operating modes (the stand layout has them)")
        if mount is not None:
            m = self.loop.names.index(mount) if isinstance(mount, str) and mount in self.loop.names else mount
            if m not in ops:
                raise RigError(f"mode request: no operated mount {mount!r} (have {', '.join(self.loop.names)})")
            ops = [m]
        for m in ops:
            self.loop.ctrls[m].check(req, self.loop.kernel.states[m])
        for m in ops:
            self.loop.request_mode(m, req)
        return req

    def control(self, word: str, source: str = "control") -> bool:
        """One control word (control file, script, signals, a console): `stop`; on the machine `on` / `off`
        (isolation) and `feedback` / `feedback_feedforward` (the isolation mode); with operating modes a mode
        request (`off`, `hold [POS]`, `track REF`, `isolate`, `setpoint POS`). A word refused or not understood is logged (and recorded as an event) in one line;
        False then."""
        w = word.strip()
        low = w.lower()
        try:
            req = self._check_word(w, bool(self.operated), source)
            if low == "stop":
                self.safe_stop(f"{source}: stop")
            elif isinstance(req, ModeRequest):
                self.request_mode(req)
            elif low in ("on", "isolation on", "off", "isolation off"):
                self.request_isolation(low.endswith("on"))
            else:
                try:
                    self.request_isolation_mode(low)
                except ValueError as e:          # feedback_feedforward without the floor feedforward
                    raise RigError(str(e)) from None
            return True
        except RigError as e:
            text = f"{source}: refused: {str(e).removeprefix(source + ': ')}"
            log.warning("%s", text)
            if self.loop is not None:
                self.loop.tap.event(self.loop._t_s(self.loop.t_ns), text)
            return False

    def _check_word(self, word: str, operated: bool, where: str) -> ModeRequest | None:
        """A control word's meaning on this layout: `stop` and the machine's isolation words (None), or the
        operating modes' request; RigError naming `where` for a word the layout does not take."""
        low = word.strip().lower()
        if low == "stop":
            return None
        if operated:
            return self.parse(word, where)
        if low not in _MACHINE_WORDS:
            raise RigError(f"{where}: unknown control word {word.strip()!r} (expected on, off, feedback, "
                           f"feedback_feedforward or stop)")
        return None

    def safe_stop(self, reason: str = "stop requested") -> None:
        self.loop.stop(reason)

    def start_recording(self, path, **attrs) -> Recorder:
        """Record the loop's rows to `path` from the next period on (a running session)."""
        rec = Recorder(path, self.loop.channels, rate_hz=self.rate_hz, flush_s=self.cfg.recording.flush_s,
                       ring_s=self.cfg.recording.ring_s, chunk_rows=self.cfg.recording.chunk_rows,
                       compression=self.cfg.recording.compression,
                       attrs={"config_source": self.cfg.source, "backend": self.backend, **attrs},
                       wait_when_full=not self.clock.is_real,
                       priority=WRITER_PRIORITY if self.realtime else 0).start()
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
                "isolation": lp.isolation, "isolation_mode": lp.isolation_mode, "fault_reason": lp.lc.fault_reason,
                "harm": lp.harm,
                "iterations": lp.iterations,
                "overruns": lp.overruns, "skipped_periods": lp.skipped, "valve_cmd_V": lp.cmd,
                "stroke_m": list(m.stroke_m) if m is not None else None,
                "accel_mps2": list(m.accel_mps2) if m is not None else None, "timing_us": lp.timing_us(),
                **self._published()}

    def _published(self) -> dict:
        """The controllers' published state of the last period (operating modes: mode, reference, error)."""
        k = self.loop.kernel
        out = {}
        for name in k.published:
            c = k.layout[name]
            out[name] = [float(v) for v in k.row[c:c + k.n]]
        if "mode" in out:
            out["mode"] = [MODES[int(v)] for v in out["mode"]]
        return out


def check_stable(cfg: Config, ctrls, dt: float) -> None:
    """ConfigError (one line) when `rig design`'s analysis calls the isolation loop unstable on the configured
    plant at this period (controllers/analysis.py unstable_loops: closed-loop poles only, about 0.1 s)."""
    bad = unstable_loops(cfg, ctrls, dt)
    if bad:
        raise ConfigError(f"{cfg.source}: [controller]: `rig design` calls this loop unstable on the configured "
                          f"plant at {1 / dt:g} Hz ({'; '.join(bad)}): refused; `rig design` shows the margins, "
                          f"--force runs it anyway")


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
        k = lp.kernel
        if "mode" in k.published:
            what = f"mode={','.join(MODES[int(v)] if v == v else '-' for v in k.row[k.layout['mode']:][:k.n])}"
        else:
            susp = lp.suspended_mounts if lp.isolation else []
            what = "iso=" + (("on " if not susp else f"SUSPENDED({','.join(susp)})") if lp.isolation else "off")
        timing = (f"wake p99={tm['wake_latency_us']['p99']:6.1f}us compute p99={tm['compute_us']['p99']:5.1f}us "
                  f"overruns={lp.overruns}" if lp.clock.is_real else "simulated time (not timed)")
        return f"t={t:7.2f}s {lp.state.name:8s} {what} {timing} stroke_um=[{xs}] cmd_V=[{us}]"

    def run(self) -> None:
        period = 0.25 if self.tty else 1.0
        while not self._halt.wait(period):
            s = self.line()
            sys.stderr.write(("\r" + s + "\x1b[K") if self.tty else (s + "\n"))
            sys.stderr.flush()


_MACHINE_WORDS = ("on", "off", "isolation on", "isolation off") + ISOLATION_MODES[1:]


class _ControlFile(_Helper):
    """Polls a control file every 0.1 s for one control word (Session.control): `stop`; `on` / `off`
    (isolation) on the machine; mode requests with operating modes."""

    def __init__(self, path: str, session: Session) -> None:
        super().__init__("rig-control")
        self.path, self.session = path, session
        self._last = self._stamp()
        if self._last is not None:           # a word left from before the start does not count
            word = self._word()
            if word:
                log.info("%s says %r from before the start: ignored (only changes count)", path, word)

    def _stamp(self) -> tuple[int, int] | None:
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    def _word(self) -> str:
        """The file's word; "" after a warning when it cannot be read as text (the poll goes on)."""
        try:
            return read_text(self.path, "control file").strip()
        except RigError as e:
            log.warning("%s (ignored; the file is still polled)", e)
            return ""

    def run(self) -> None:
        while not self._halt.wait(0.1):
            key = self._stamp()
            if key is None or key == self._last:
                continue
            self._last = key
            word = self._word()
            if word:
                self.session.control(word, f"control file {self.path}")

"""The console's side in the loop's process: it starts the web server, publishes the run, and turns the page's
commands into the session's requests.

What runs here, and what it costs the loop:
- The live ring (rig/console/live.py) bound as the loop's recorder while no recording runs: the compiled
  period copies its row there, as it would into a recording's ring. While a recording runs, the link thread
  copies the recording's new rows into the live ring twenty times a second (a numpy copy; the loop's thread
  never waits for it).
- The link thread: waits on the control socket (no interpreter lock held while waiting); applies each command
  through the session's requests (rig/runtime/session.py: the lifecycle gate's thread-safe requests, applied at the
  next period boundary, the same path as SIGUSR1 and the control file) and logs it; ten times a second sends
  a status message (fault reason, counters, recording, the job's progress, new log records).
- Nothing else: the web server, the JSON, the spectra run in the server's own process (rig/console/server.py),
  kept off the loop's CPU. `serve="thread"` puts the server in this process instead (for the comparison in
  `rig bench loop --console`).

The listening socket is bound here, to 127.0.0.1 only, and handed to the server; the address with its
access token is `Console.url`.
"""
from __future__ import annotations

import collections
import json
import logging
import os
import secrets
import select
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.chirp import check_chirp
from rig.identify import UNITS
from rig.config import MOUNTS
from rig.console.live import LiveRing
from rig.console.protocol import check_command, receive, send
from rig.errors import EXIT_SUSPECT, RigError
from rig.runtime.lifecycle import State
from rig.runtime.recorder import Recorder
from rig.runtime.rt import raise_priority

log = logging.getLogger("rig.console")

HOST = "127.0.0.1"
DEFAULT_PORT = 8765
PORT_TRIES = 10
LIVE_RING_S = 2.0              # the server reads it every 50 ms
TICK_S = 0.02                  # the link's copy period while a recording runs
STATUS_S = 0.1
# SCHED_FIFO of the link thread when the loop runs real-time: a thread of the loop's process that is preempted
# by an ordinary process while it holds the interpreter lock stalls the loop for as long (milliseconds on a
# busy machine); at a real-time priority below the loop's and the drivers', off the loop's CPU, it finishes its
# short work instead
LINK_PRIORITY = 40
# the web server's niceness in a real-time run: ahead of ordinary processes, so that the page keeps its update
# rate and a click its quick answer on a busy machine (its work is a few ms per update, at 20 updates a second)
SERVER_NICE = -10
PAGE_NAMES = {"amplitude": "amplitude_V", "f0/f1": "f0_hz/f1_hz", "duration": "duration_s", "f1": "f1_hz"}
READY_TIMEOUT_S = 120.0        # the web server's start-up (its imports) on a very busy machine


@dataclass
class Job:
    """A chirp identification asked for by the page (rig/console/runner.py runs it between two sessions)."""
    amplitude_V: float
    f0_hz: float
    f1_hz: float
    duration_s: float
    mount: str
    resume_active: bool = True
    phase: str = "waiting"              # waiting, chirp, identify, done, failed
    progress: float = 0.0
    text: str = ""
    recording: str = ""
    started_wall: float = field(default_factory=time.time)


class _Tee:
    """The chirp's recorder (a few columns) and, beside it, the live ring with the whole row: the loop pushes
    each row to both (the recorder's drops and its writer's health are the recorder's)."""

    def __init__(self, recorder, live: LiveRing) -> None:
        self.recorder, self.live = recorder, live

    def push_row(self, row) -> bool:
        self.live.push_row(row)
        return self.recorder.push_row(row)

    def event(self, t_s: float, text: str) -> None:
        self.recorder.event(t_s, text)

    def writer_died(self) -> str | None:
        return self.recorder.writer_died()

    @property
    def dropped_rows(self) -> int:
        return self.recorder.dropped_rows


class _LogTap(logging.Handler):
    """The rig's log records (lifecycle, faults, console commands) for the page; formatted off the emitting
    thread."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: collections.deque = collections.deque(maxlen=500)

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _server_priority(pid: int, loop_cpu: int | None) -> None:
    """The web server process, just started (its imports take seconds on a busy machine): in a real-time run off
    the loop's CPU and ahead of ordinary work by SERVER_NICE; else as it is. Set from here rather than in the
    child before its exec (preexec_fn is unsafe beside threads)."""
    if loop_cpu is None:
        return
    try:
        if hasattr(os, "sched_setaffinity"):
            cpus = os.sched_getaffinity(pid) - {loop_cpu}
            if cpus:
                os.sched_setaffinity(pid, cpus)
        os.setpriority(os.PRIO_PROCESS, pid, SERVER_NICE)
    except OSError:         # not allowed here, or it has gone: ordinary priority, the page answers when it can
        pass


class Console:
    """The operator console of a run. Use as a context manager; `attach(session)` / `detach()` around each
    session it shows (rig run --console runs several when the page asks for a chirp identification).
    log_level: the rig's loggers log at least this while the console runs (its commands are logged at INFO);
    None leaves them as they are (the benchmark)."""

    def __init__(self, cfg, backend: str, *, port: int | None = None, read_only: bool = False,
                 serve: str = "process", config_path: str | None = None,
                 log_level: int | None = logging.INFO, record_dir=None) -> None:
        if serve not in ("process", "thread"):
            raise ValueError(f"serve {serve!r}")
        self.cfg, self.backend = cfg, backend
        # the recordings the page starts, and its chirps': here or below (default: where the run was started)
        self.record_dir = Path(record_dir if record_dir is not None else os.getcwd()).resolve()
        self.read_only = bool(read_only)
        self.serve = serve
        self.config_path = config_path
        self.token = secrets.token_hex(24)
        self._want_port = port
        self.port: int | None = None
        self.session = None
        self.live: LiveRing | None = None
        self.job: Job | None = None
        self.stop_requested = False
        self.chirp_session = None
        self._chirp_live: LiveRing | None = None
        self.ended: str | None = None
        self.last_recording: dict | None = None
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._proc: subprocess.Popen | None = None
        self._server_thread = None
        self._thread: threading.Thread | None = None
        self._sock = None
        self._logtap = _LogTap()
        self._log_level = log_level           # at least this for the rig's loggers (None: leave them)
        self._old_level = logging.NOTSET
        self._copy_from = None          # (recorder, rows already copied) while a recording runs
        self._identify: subprocess.Popen | None = None
        self._identify_err = b""
        self._identify_out = b""
        self.shown_job: Job | None = None      # the latest job, as the page shows it
        self._identify_last = ""

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/?token={self.token}"

    # ---- start and stop ---------------------------------------------------------------------------------
    def __enter__(self) -> "Console":
        listen = self._listen()
        self.port = listen.getsockname()[1]
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock = mine
        try:
            if self.serve == "process":
                cmd = [sys.executable, "-m", "rig.console.server", "--control-fd", str(theirs.fileno()),
                       "--listen-fd", str(listen.fileno())]
                self._proc = subprocess.Popen(cmd, pass_fds=(theirs.fileno(), listen.fileno()),
                                              stdin=subprocess.DEVNULL)
                _server_priority(self._proc.pid, self._loop_cpu())
                theirs.close()
                listen.close()
            else:
                from rig.console.server import serve_in_thread   # lazy: the web libraries only in thread mode
                self._server_thread = serve_in_thread(theirs, listen)
            try:
                send(mine, {"type": "hello", "token": self.token, "read_only": self.read_only,
                            "backend": self.backend, "config": self.cfg.source, "pid": os.getpid(),
                            "mounts_all": list(MOUNTS), "commands_logged": True})
            except OSError:
                self._not_started()
            self._wait_ready()
        except BaseException:
            self._stop_server()
            raise
        rig_log = logging.getLogger("rig")
        rig_log.addHandler(self._logtap)
        self._old_level = rig_log.level
        if self._log_level is not None and rig_log.getEffectiveLevel() > self._log_level:
            rig_log.setLevel(self._log_level)           # commands are logged, whoever set up logging
        self._thread = threading.Thread(target=self._run, name="rig-console-link", daemon=True)
        self._thread.start()
        return self

    def _wait_ready(self) -> None:
        """Until the web server answers (its imports take seconds on a busy machine, and the address printed
        before would keep the first page waiting that long: 13 s at load 16 measured), with the CPU its own: the
        run's set-up waits. Past READY_TIMEOUT_S the run goes on and the page answers when it can."""
        ready, _, _ = select.select([self._sock], [], [], READY_TIMEOUT_S)
        if not ready:
            log.warning("console: the web server has not answered in %g s (a busy machine?); the run goes on and "
                        "the page answers when it can", READY_TIMEOUT_S)
            return
        msg = self._receive()
        if msg is None:
            self._not_started()
        if msg.get("type") != "ready":
            raise RigError(f"console: the web server sent {msg.get('type')!r} before it was ready")

    def _receive(self) -> dict | None:
        """The web server's next message (no descriptors come this way); None when it has gone."""
        try:
            msg, fds = receive(self._sock)
        except OSError:
            return None
        for fd in fds:
            os.close(fd)
        return msg

    def _not_started(self) -> None:
        code = self._proc.wait(5.0) if self._proc is not None else None
        raise RigError("console: the web server did not start" + (f" (exit {code})" if code is not None else ""))

    def _listen(self) -> socket.socket:
        """The listening socket on 127.0.0.1: the given port, or the first free one from DEFAULT_PORT."""
        ports = [self._want_port] if self._want_port is not None else \
            list(range(DEFAULT_PORT, DEFAULT_PORT + PORT_TRIES))
        err = None
        for p in ports:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((HOST, p))
                s.listen(16)
                s.set_inheritable(True)
                return s
            except OSError as e:
                s.close()
                err = e
        what = f"port {ports[0]}" if len(ports) == 1 else f"ports {ports[0]}-{ports[-1]}"
        raise RigError(f"--port: cannot listen on {HOST} {what} ({err.strerror or err}); choose another with "
                       f"--port N (0: any free port)")

    def _loop_cpu(self) -> int | None:
        n = os.cpu_count() or 1
        if n < 2 or not self.cfg.loop.realtime:
            return None
        return n - 1 if self.cfg.loop.cpu < 0 else self.cfg.loop.cpu

    def finish(self, reason: str) -> None:
        """The run is over: the pages are told why."""
        self.ended = reason
        try:
            send(self._sock, {"type": "status", "status": self._status()})
            send(self._sock, {"type": "ended", "reason": reason})
        except OSError:
            pass

    def __exit__(self, *exc) -> None:
        logging.getLogger("rig").removeHandler(self._logtap)
        logging.getLogger("rig").setLevel(self._old_level)
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.session is not None:
            self.detach()
        self.attach_chirp(None)
        if self._identify is not None and self._identify.poll() is None:
            self._identify.kill()
            self._identify.wait()
        self._stop_server()

    def _stop_server(self) -> None:
        if self._sock is not None:
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._sock.close()
            self._sock = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            self._proc = None
        if self._server_thread is not None:
            self._server_thread.join(timeout=5.0)
            self._server_thread = None

    # ---- the session shown ---------------------------------------------------------------------------------
    def attach(self, session) -> None:
        """Show `session` (entered, running or about to run): its rows go to a new live ring."""
        loop = session.loop
        live = LiveRing(len(loop.kernel.row), max(64, int(LIVE_RING_S * loop.rate_hz)))
        with self._lock:
            self.session, self.live = session, live
            session.idle_recorder = live
            if loop.recorder is None:
                self._bind(session, live)
            self._copy_from = None
        self._send_attach(session, live, "run")

    def _send_attach(self, session, live: LiveRing, kind: str) -> None:
        """The server's new feed: the session's row layout, its mounts and limits, and the live ring.
        kind: "run" (an isolation or operated run) or "chirp" (an identification run: no spectra)."""
        loop, cfg = session.loop, session.cfg
        layout = {"channels": [{"name": c.name, "width": c.width, "unit": c.unit, "labels": list(c.labels)}
                               for c in loop.channels],
                  "rate_hz": loop.rate_hz, "mounts": list(loop.names), "backend": session.backend,
                  "kind": kind, "modes": bool(session.operated),      # the mode field only where modes exist
                  "limits": {"valve_limit_V": cfg.safety.valve_limit_V, "stroke_limit_m": cfg.safety.stroke_limit_m,
                             "accel_range_mps2": cfg.safety.accel_range_mps2}}
        send(self._sock, {"type": "attach", "layout": layout}, fds=(live.fd,))

    def detach(self) -> None:
        """Stop showing the session (before it is torn down)."""
        with self._lock:
            session, live = self.session, self.live
            self.session = None
            self._copy_rows()
            self._copy_from = None
            if session is not None:
                session.idle_recorder = None
                if session.loop.recorder is live:
                    self._bind(session, None)
        try:
            send(self._sock, {"type": "detach"})
        except OSError:
            pass
        if live is not None:
            live.close()
        self.live = None

    @staticmethod
    def _bind(session, rec, timeout_s: float = 1.0) -> None:
        """Record into `rec` from the next period on (at once when the loop is not running)."""
        loop = session.loop
        if loop.t0_ns is None or loop.stop_reason is not None:     # not running: no period boundary to wait for
            loop.recorder = rec
            return
        loop.gate.request_recorder(rec)
        end = time.monotonic() + timeout_s
        while loop.recorder is not rec and time.monotonic() < end and loop.stop_reason is None:
            time.sleep(0.002)
        if loop.recorder is not rec:            # the loop ended meanwhile
            loop.recorder = rec

    def attach_chirp(self, session) -> None:
        """The chirp's own session, shown live as a run is (its recording keeps a few columns, so every row
        also goes to a live ring of its own), and reached by a safe stop. None: the chirp is over."""
        if session is None:
            live, self.chirp_session, self._chirp_live = self._chirp_live, None, None
            if live is not None:
                try:
                    send(self._sock, {"type": "detach"})
                except OSError:
                    pass
                live.close()
            return
        loop = session.loop
        live = LiveRing(len(loop.kernel.row), max(64, int(LIVE_RING_S * loop.rate_hz)))
        self._bind(session, _Tee(loop.recorder, live))      # before the chirp starts (at once)
        self.chirp_session, self._chirp_live = session, live
        self._send_attach(session, live, "chirp")

    # ---- the link thread -------------------------------------------------------------------------------------
    def _run(self) -> None:
        next_status = 0.0
        raised = False
        while not self._halt.is_set():
            if not raised and self.session is not None and self.session.realtime:
                raised = True
                cpu = self._loop_cpu()
                if cpu is not None:          # this thread only: off the loop's CPU, where the loop preempts it
                    os.sched_setaffinity(0, (os.sched_getaffinity(0) - {cpu}) or os.sched_getaffinity(0))
                raise_priority(LINK_PRIORITY)
            waits = [self._sock]
            if self._identify is not None:
                waits += [p for p in (self._identify.stdout, self._identify.stderr) if not p.closed]
            try:
                ready, _, _ = select.select(waits, [], [], TICK_S)
            except (OSError, ValueError):
                return
            if self._sock in ready:
                msg = self._receive()
                if msg is None:
                    log.warning("console: the web server has gone; the run goes on")
                    return
                if msg.get("type") == "cmd":
                    self._command(msg)
            if self._identify is not None:
                self._identify_io([p for p in ready if p is not self._sock])
            with self._lock:
                self._copy_rows()
            now = time.monotonic()
            if now >= next_status:
                next_status = now + STATUS_S
                try:
                    send(self._sock, {"type": "status", "status": self._status()})
                except OSError:
                    return

    def _copy_rows(self) -> None:
        """While a recording's ring takes the loop's rows, copy its new ones into the live ring."""
        session, live = self.session, self.live
        if session is None or live is None:
            return
        rec = session.loop.recorder
        if rec is live or rec is None or not hasattr(rec, "ring_rows"):
            self._copy_from = None
            return
        if self._copy_from is None or self._copy_from[0] is not rec:
            self._copy_from = (rec, rec.committed)
            return
        _, done = self._copy_from
        head = rec.committed
        ring = rec.ring_rows()
        cap = len(ring)
        n = min(head - done, cap // 2)
        if n <= 0:
            return
        i = (head - n) % cap
        live.append(ring[i:i + n] if i + n <= cap else np.concatenate([ring[i:], ring[:n - (cap - i)]]))
        self._copy_from = (rec, head)

    def _status(self) -> dict:
        s = self.session
        chirp = self.chirp_session
        run = {"phase": "ended" if self.ended else ("run" if s is not None else ("chirp" if chirp else "between")),
               "backend": self.backend, "read_only": self.read_only, "ended": self.ended}
        lp = s.loop if s is not None else (chirp.loop if chirp is not None else None)
        if lp is not None:
            run.update(state=lp.state.name, isolation=lp.isolation, fault_reason=lp.lc.fault_reason, harm=lp.harm,
                       stop_reason=lp.stop_reason, iterations=lp.iterations, overruns=lp.overruns,
                       skipped_periods=lp.skipped, rate_hz=lp.rate_hz,
                       missed_deadline_fraction=lp.missed_deadline_fraction)
        rec = s.loop.recorder if s is not None else None
        recording = None
        if isinstance(rec, Recorder):
            recording = {"path": str(rec.path), "rows_written": rec.written(), "dropped_rows": rec.dropped_rows,
                         "running": True}
        elif self.last_recording is not None:
            recording = self.last_recording
        job = self.shown_job
        out = {"run": run, "recording": recording, "wall": time.time(),
               "job": None if job is None else {"phase": job.phase, "progress": job.progress, "text": job.text,
                                                "recording": job.recording},
               "log": self._log_records()}
        return out

    def _log_records(self) -> list[dict]:
        out = []
        recs = self._logtap.records
        while recs:
            r = recs.popleft()
            try:
                text = r.getMessage()
            except Exception:       # noqa: BLE001 - a malformed log call must not stop the console
                text = str(r.msg)
            out.append({"wall": r.created, "level": r.levelname, "text": text, "logger": r.name})
        return out

    # ---- commands ------------------------------------------------------------------------------------------
    def _command(self, msg: dict) -> None:
        cid, client = msg.get("id"), msg.get("client", "?")
        checked = check_command(msg)
        if self.read_only:
            ok, text = False, "read-only console: commands are refused"
        elif isinstance(checked, str):
            ok, text = False, checked
        else:
            name, args = checked
            try:
                ok, text = getattr(self, f"_cmd_{name}")(**args)
            except RigError as e:
                ok, text = False, str(e)
            except Exception as e:   # noqa: BLE001 - the page gets the one line; the run goes on
                ok, text = False, f"{e.__class__.__name__}: {e}"
            if ok:
                log.info("console: %s (%s)", text, client)
            else:
                log.warning("console: %s refused (%s): %s", name, client, text)
        try:
            send(self._sock, {"type": "reply", "id": cid, "ok": ok, "text": text})
        except OSError:
            pass

    def _need_run(self):
        if self.session is None:
            raise RigError("no run is going on now" + (" (chirp identification)" if self.chirp_session else ""))
        return self.session

    def _cmd_isolation(self, on: bool):
        s = self._need_run()
        s.request_isolation(on)
        note = "" if s.loop.state is State.ACTIVE else f" (takes effect on activation: {s.loop.state.name})"
        return True, f"isolation {'on' if on else 'off'} requested{note}"

    def _cmd_mode(self, request: str):
        s = self._need_run()
        req = s.request_mode(s.parse(request, "console"))
        note = "" if s.loop.state is State.ACTIVE else f" (takes effect on activation: {s.loop.state.name})"
        return True, f"mode {req} requested{note}"

    def _cmd_activate(self):
        s = self._need_run()
        st = s.loop.state
        if st is State.FAULT:
            return False, f"in FAULT ({s.loop.lc.fault_reason}): reset the fault first"
        if st is State.ACTIVE:
            return True, "already ACTIVE"
        s.request_active(True)
        return True, "activation requested"

    def _cmd_deactivate(self):
        s = self._need_run()
        s.request_active(False)
        return True, "deactivation requested (valves to null)"

    def _cmd_reset_fault(self):
        s = self._need_run()
        if s.loop.state is not State.FAULT:
            return False, f"no fault to reset (state {s.loop.state.name})"
        s.reset_fault()
        return True, "fault reset requested (FAULT -> INACTIVE)"

    def _cmd_safe_stop(self):
        self.stop_requested = True
        stopped = []
        for s in (self.session, self.chirp_session):
            if s is not None:
                s.safe_stop("console: safe stop")
                stopped.append("run" if s is self.session else "chirp")
        return True, f"safe stop requested ({', '.join(stopped) or 'nothing running'})"

    def _cmd_record_start(self, path: str):
        s = self._need_run()
        if isinstance(s.loop.recorder, Recorder):
            return False, f"already recording to {s.loop.recorder.path}: stop it first"
        p = self.recording_path(path)
        s.start_recording(p, command="rig run --console", started_by="console")
        self.last_recording = None
        return True, f"recording to {p}"

    def recording_path(self, name: str) -> Path:
        """A recording the page names, as a new file in the console's recording folder or below it. The token lets
        a person drive the rig, not write wherever the rig's user may: an absolute path elsewhere, `..` or `~`
        out of the folder (or a symbolic link leading out) is refused in one line, as is a file that exists."""
        root = self.record_dir
        p = Path(name)
        if p.suffix.lower() not in (".h5", ".hdf5"):
            raise RigError(f"recording {name!r}: expected a file name ending in .h5")
        full = (root / p).resolve()           # an absolute p stands alone; `..` and links are resolved
        if (len(p.parts) > 1 and p.parts[0].startswith("~")) or not full.is_relative_to(root):   # ~/, ~user/
            raise RigError(f"recording {name!r}: outside the console's recording folder {root} (where the run "
                           f"started): expected a file name there or below it")
        try:
            there = os.path.lexists(root / p) or full.exists()
        except OSError as e:                  # e.g. a name longer than the file system takes
            raise RigError(f"recording {name[:80]!r}: {e.strerror or e}") from None
        if there:
            raise RigError(f"recording {full}: exists (choose another name; nothing is overwritten)")
        if not full.parent.is_dir():
            raise RigError(f"recording {full}: folder {full.parent} does not exist")
        return full

    def _cmd_record_stop(self):
        s = self._need_run()
        rec = s.loop.recorder
        if not isinstance(rec, Recorder):
            return False, "no recording is running"
        with self._lock:
            self._copy_rows()
        s.stop_recording(rec)
        self.last_recording = {"path": str(rec.path), "rows_written": rec.rows_written,
                               "dropped_rows": rec.dropped_rows, "running": False}
        return True, f"recording closed: {rec.path}, {rec.rows_written} rows, {rec.dropped_rows} dropped"

    def _cmd_chirp(self, amplitude_V: float, f0_hz: float, f1_hz: float, duration_s: float, mount: str):
        s = self._need_run()
        if self.job is not None or (self._identify is not None and self._identify.poll() is None):
            return False, "an identification is already running"
        if isinstance(s.loop.recorder, Recorder):
            return False, "a recording is running: stop it first (the chirp ends this run and starts its own)"
        if s.loop.state is State.FAULT:
            return False, f"in FAULT ({s.loop.lc.fault_reason}): reset the fault first"
        if self.backend != "sim" and mount not in MOUNTS:
            return False, f"mount: expected one of {', '.join(MOUNTS)}, got {mount!r}"
        try:                                     # refused before the run is stopped: a typo keeps isolation on
            check_chirp(self.cfg, self.backend, amplitude_V, f0_hz, f1_hz, duration_s, PAGE_NAMES)
        except RigError as e:
            return False, f"chirp: {e}"
        self.job = self.shown_job = Job(amplitude_V, f0_hz, f1_hz, duration_s, mount,
                                        resume_active=s.loop.state is State.ACTIVE, text="stopping the run")
        s.safe_stop("console: chirp identification")
        return True, "chirp identification: the run stops safely, the chirp follows"

    # ---- the chirp job (rig/console/runner.py drives it from the main thread) ---------------------------------
    def take_job(self) -> Job | None:
        return self.job

    def job_progress(self, phase: str, progress: float, text: str) -> None:
        job = self.shown_job
        if job is not None:
            job.phase, job.progress, job.text = phase, max(0.0, min(1.0, progress)), text

    def job_failed(self, text: str) -> None:
        self.job_progress("failed", 0.0, text)
        self._publish_result({"ok": False, "text": text})
        self.job = None

    def start_identify(self, recording: Path) -> None:
        """`rig identify REC --json` in a process of its own (the run goes on meanwhile); the link thread
        follows its progress lines and publishes the result."""
        job = self.job
        job.recording = str(recording)
        self.job_progress("identify", 0.0, "identifying the six actuator parameters")
        cmd = [sys.executable, "-m", "rig.cli", "identify", str(recording), "--json"]
        if self.config_path:
            cmd[4:4] = ["--config", self.config_path]
        cpu = self._loop_cpu()
        self._identify_out, self._identify_err, self._identify_last = b"", b"", ""
        self.job = None

        def off_loop_cpu():
            os.nice(5)
            if cpu is not None:
                os.sched_setaffinity(0, (os.sched_getaffinity(0) - {cpu}) or os.sched_getaffinity(0))
        self._identify = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          stdin=subprocess.DEVNULL, preexec_fn=off_loop_cpu)

    def _identify_io(self, ready) -> None:
        p = self._identify
        for f in ready:
            chunk = os.read(f.fileno(), 65536)
            if f is p.stdout:
                self._identify_out += chunk
            else:
                self._identify_err += chunk
                *lines, rest = self._identify_err.split(b"\n")
                self._identify_err = rest
                for line in lines:
                    self._identify_line(line.decode(errors="replace"))
            if not chunk:
                f.close()
        if p.stdout.closed and p.stderr.closed:
            code = p.wait()
            self._identify = None
            job = self.shown_job
            if code in (0, EXIT_SUSPECT):          # EXIT_SUSPECT: identified, with a warning in its fit
                try:
                    result = json.loads(self._identify_out)
                except ValueError as e:
                    self._identify_result_failed(job, f"identify: unreadable output ({e})")
                    return
                job.phase, job.progress, job.text = "done", 1.0, "identified"
                self._publish_result({"ok": True, "recording": job.recording, "units": UNITS,
                                      "chirp": {"amplitude_V": job.amplitude_V, "f0_hz": job.f0_hz,
                                                "f1_hz": job.f1_hz, "duration_s": job.duration_s,
                                                "mount": job.mount}, **result})
                log.info("console: identified from %s (NRMSE %.4f)", job.recording, result["fit"]["nrmse"])
                if result["fit"].get("warning"):
                    log.warning("console: identify: %s", result["fit"]["warning"])
            else:
                last = self._identify_last or self._identify_err.decode(errors="replace").strip()
                self._identify_result_failed(job, f"identify failed (exit {code})" + (f": {last}" if last else ""))

    def _identify_result_failed(self, job: Job, text: str) -> None:
        job.phase, job.text = "failed", text
        self._publish_result({"ok": False, "text": text, "recording": job.recording})
        log.error("console: %s", text)

    def _identify_line(self, line: str) -> None:
        """`[ 0.28 s]  30 % time-domain output-error refinement` -> the progress bar."""
        if "%" in line and line.startswith("["):
            head, _, stage = line.partition("%")
            try:
                frac = float(head.rsplit("]", 1)[1]) / 100
            except (IndexError, ValueError):
                return
            self.job_progress("identify", frac, stage.strip())
        elif line.strip():
            self._identify_last = line.strip()      # an error line: the failure's text

    def _publish_result(self, result: dict) -> None:
        try:
            send(self._sock, {"type": "result", "result": result})
        except OSError:
            pass

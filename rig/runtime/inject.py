"""Fault rehearsal: `KIND:MOUNT:SIGNAL@T` drives a backend's fault knobs at loop time T (seconds after the
loop's first period), so an operator can drill the rig's reaction before trusting it (`rig run --inject`,
`rig hil --inject`, `rig drill`).

  MOUNT   a mount name (front_left ...) or index (0-3); `*` for a whole device (the Modbus module, the
          serial amplifier) or for faults of no mount
  SIGNAL  accel, stroke, valve; `-` for none

The simulated backend (sim_backend/backend.py `inject`, acting from T to the loop's period):
  nan / range / stuck       MOUNT:accel|stroke   the sensor reads NaN / far out of range / a frozen value
  stale / drop              MOUNT:accel|stroke   time stamps lag 10 ms / the sample is no longer refreshed
  device                    MOUNT:-              the backend reports a device fault
The emulated devices behind the real drivers (hil; sim_backend/emulators, set by a thread at T):
  silence / exception / garbage / stale    *:accel     the Modbus module stops answering / answers with an
                                                       exception / (stale) serves frozen registers
  silence / exception / garbage / stale / fragment   *:stroke   the same for the serial amplifier
  range / nan               MOUNT:stroke         the amplifier flags the channel over range / not present
  silence / garbage / stale / fault / hold           MOUNT:valve   one valve node
Both backends:
  overrun   *:-    every period from T costs 1.2 periods more: the loop falls behind real time (lag rule)
  stall     *:-    one stall of three watchdog limits inside the period at T (watchdog)
  recorder  *:-    the recording's writer process is killed (needs --record)
"""
from __future__ import annotations

import math
import os
import signal
import threading
import time
from dataclasses import dataclass

from rig.cliargs import check_within_run
from rig.config import mount_names
from rig.errors import RigError

COMMON = ("overrun", "stall", "recorder")
SIM = {"nan": ("accel", "stroke"), "range": ("accel", "stroke"), "stuck": ("accel", "stroke"),
       "stale": ("accel", "stroke"), "drop": ("accel", "stroke"), "device": (None,)}
HIL_DEVICE = {"accel": ("silence", "exception", "garbage", "stale"),
              "stroke": ("silence", "exception", "garbage", "stale", "fragment")}
HIL_CHANNEL = {"range": "OR", "nan": "NP"}                     # serial amplifier channel status
HIL_VALVE = ("silence", "garbage", "stale", "fault", "hold")
SIGNALS = ("accel", "stroke", "valve")
OVERRUN_PERIODS = 1.2        # `overrun`: extra cost of every period, in periods
STALL_WATCHDOGS = 3.0        # `stall`: one stall of this many watchdog limits


@dataclass(frozen=True)
class Injection:
    kind: str
    mount: int | None          # None: a whole device, or no mount
    signal: str | None         # None: `-`
    at_s: float
    spec: str

    def __str__(self) -> str:
        return self.spec


def parse(spec: str, n_mounts: int = 4, names: tuple[str, ...] | None = None) -> Injection:
    """One `KIND:MOUNT:SIGNAL@T` (RigError naming what was expected). Whether the backend has the knob is
    checked by `arm`."""
    names = names or mount_names(n_mounts)
    form = "expected KIND:MOUNT:SIGNAL@T, e.g. nan:front_left:accel@2.0"
    head, at, t = spec.partition("@")
    parts = head.split(":")
    if not at or len(parts) != 3:
        raise RigError(f"--inject {spec!r}: {form}")
    kind, mount, sig = (p.strip().lower() for p in parts)
    try:
        at_s = float(t)
    except ValueError:
        raise RigError(f"--inject {spec!r}: T: expected seconds of loop time, got {t!r}") from None
    if not (math.isfinite(at_s) and 0 <= at_s <= 86400):
        raise RigError(f"--inject {spec!r}: T: expected 0 <= T <= 86400 s, got {t!r}")
    known = sorted(set(SIM) | set(COMMON) | set(HIL_VALVE) | {k for v in HIL_DEVICE.values() for k in v})
    if kind not in known:
        raise RigError(f"--inject {spec!r}: KIND: expected one of {', '.join(known)}, got {kind!r}")
    if mount in ("*", "all", "-"):
        m = None
    elif mount.isdigit() and int(mount) < n_mounts:
        m = int(mount)
    elif mount in names:
        m = names.index(mount)
    else:
        raise RigError(f"--inject {spec!r}: MOUNT: expected one of {', '.join(names)}, 0-{n_mounts - 1} or *, "
                       f"got {mount!r}")
    if sig not in SIGNALS + ("-",):
        raise RigError(f"--inject {spec!r}: SIGNAL: expected one of {', '.join(SIGNALS)} or -, got {sig!r}")
    return Injection(kind, m, None if sig == "-" else sig, at_s, spec)


def _need(inj: Injection, what: str, ok: bool, backend: str) -> None:
    if not ok:
        raise RigError(f"--inject {inj.spec!r}: the {backend} backend's {inj.kind} knob needs {what}")


def check(inj: Injection, backend: str, seconds: float | None = None) -> None:
    """RigError when `backend` has no knob for this injection, or T is not inside a run of `seconds` (before
    anything is started)."""
    _check_knob(inj, backend)
    check_within_run(inj.at_s, seconds, f"--inject {inj.spec!r}: T")


def _check_knob(inj: Injection, backend: str) -> None:
    if inj.kind in COMMON:
        return
    if backend == "sim":
        sigs = SIM.get(inj.kind)
        if sigs is None:
            raise RigError(f"--inject {inj.spec!r}: the sim backend has no {inj.kind!r} knob (sim: "
                           f"{', '.join(list(SIM) + list(COMMON))})")
        _need(inj, "a mount", inj.mount is not None, backend)
        _need(inj, f"SIGNAL {' or '.join(s or '-' for s in sigs)}", inj.signal in sigs, backend)
    elif backend == "hil":
        if inj.signal == "valve":
            _need(inj, "a mount", inj.mount is not None and inj.kind in HIL_VALVE, backend)
        elif inj.signal == "stroke" and inj.kind in HIL_CHANNEL:
            _need(inj, "a mount", inj.mount is not None, backend)
        elif inj.signal in HIL_DEVICE and inj.kind in HIL_DEVICE[inj.signal]:
            _need(inj, "MOUNT * (the whole device)", inj.mount is None, backend)
        else:
            raise RigError(f"--inject {inj.spec!r}: the hil backend has no {inj.kind}:{inj.signal or '-'} knob "
                           f"(accel: {', '.join(HIL_DEVICE['accel'])}; stroke: {', '.join(HIL_DEVICE['stroke'])}, "
                           f"range, nan; valve: {', '.join(HIL_VALVE)}; {', '.join(COMMON)})")
    else:
        raise RigError(f"--inject: the {backend} backend has no fault knobs (sim and hil have)")


class Armed:
    """The injections of one session, armed: knobs the simulated backend schedules itself are set at once;
    the others by a thread at their loop time (`applied`: spec -> loop time it acted from, s)."""

    def __init__(self, session, injections: list[Injection]) -> None:
        self.session = session
        self.injections = list(injections)
        self.applied: dict[str, float] = {}
        self._pending: list[Injection] = []
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._extra_ns = 0              # the slow-read proxy's cost per read (hil overrun/stall)
        self._extra_every = False
        self.rows_at_kill: int | None = None      # `recorder`: rows the loop had committed when the writer died

    def __enter__(self) -> "Armed":
        s = self.session
        port, loop = s.port, s.loop
        for inj in self.injections:
            check(inj, s.backend)
            if inj.kind == "recorder" and s.recorder is None:
                raise RigError(f"--inject {inj.spec!r}: needs a recording (--record FILE)")
        wd = s.cfg.safety.watchdog_s
        for inj in self.injections:
            if s.backend == "sim" and inj.kind != "recorder":
                if inj.kind == "overrun":
                    port.inject("overrun", at_s=inj.at_s, extra_s=OVERRUN_PERIODS * loop.dt, every=True)
                elif inj.kind == "stall":
                    port.inject("overrun", at_s=inj.at_s, extra_s=STALL_WATCHDOGS * wd)
                else:
                    port.inject(inj.kind, mount=inj.mount, at_s=inj.at_s, sensor=inj.signal or "accel")
                self.applied[inj.spec] = inj.at_s
            else:
                self._pending.append(inj)
        if any(i.kind in ("overrun", "stall") for i in self._pending):
            loop.slow_down(self.slow)          # the loop's own step before its kernel; the gate keeps the port
        if self._pending:
            self._thread = threading.Thread(target=self._run, name="rig-inject", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(1.0)
        t = self._loop_time()           # the sim's knobs were set ahead: keep those the loop reached
        self.applied = {k: v for k, v in self.applied.items() if t is not None and v <= t + 1e-9}

    def _loop_time(self) -> float | None:
        lp = self.session.loop
        return (lp.t_ns - lp.t0_ns) * 1e-9 if lp.t0_ns is not None and lp.t_ns else None

    def _run(self) -> None:
        todo = sorted(self._pending, key=lambda i: i.at_s)
        while todo and not self._halt.wait(0.001):
            t = self._loop_time()
            while todo and t is not None and t >= todo[0].at_s:
                inj = todo.pop(0)
                self._apply(inj)
                self.applied[inj.spec] = t

    def _apply(self, inj: Injection) -> None:
        s = self.session
        if inj.kind == "recorder":
            self.rows_at_kill = s.recorder.rows_committed
            os.kill(s.recorder.pid, signal.SIGKILL)
        elif inj.kind == "overrun":
            self._extra_ns, self._extra_every = int(OVERRUN_PERIODS * s.loop.period_ns), True
        elif inj.kind == "stall":
            self._extra_ns, self._extra_every = int(STALL_WATCHDOGS * s.cfg.safety.watchdog_s * 1e9), False
        else:                                   # the emulated devices (hil)
            emu = s.port.rig
            if inj.signal == "valve":
                emu.set_valve(inj.mount, inj.kind)
            elif inj.signal == "stroke" and inj.kind in HIL_CHANNEL:
                emu.set_serial_channel(inj.mount, HIL_CHANNEL[inj.kind])
            elif inj.signal == "accel":
                emu.set_modbus(inj.kind)
            else:
                emu.set_serial(inj.kind)


    def slow(self) -> None:
        """The extra time of a drilled overrun or stall, in the loop's period before its kernel. It sleeps
        rather than spins, as the loop would while it waits on a slow device."""
        if self._extra_ns:
            extra = self._extra_ns
            if not self._extra_every:
                self._extra_ns = 0
            time.sleep(extra * 1e-9)

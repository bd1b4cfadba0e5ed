"""Clocks for the loop, injected so tests run in simulated time.

Both clocks speak integer nanoseconds on a monotonic time base:
  now_ns()              current time
  sleep_until(t_ns)     block until t_ns (absolute deadline; returns at once if t_ns is past)
  spend(ns)             consume ns of time as if computing (busy-wait on the real clock; advance on the
                        simulated one): used to inject overruns
"""
from __future__ import annotations

import ctypes
import errno
import time

from rig.runtime.libc import LIBC, Timespec

CLOCK_MONOTONIC = 1
TIMER_ABSTIME = 1


def _load_nanosleep():
    """clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME): an absolute wake-up, no drift from relative sleeps."""
    fn = getattr(LIBC, "clock_nanosleep", None)
    if fn is None:
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(Timespec), ctypes.POINTER(Timespec)]
    fn.restype = ctypes.c_int
    return fn


_NANOSLEEP = _load_nanosleep()


class MonotonicClock:
    """The real clock: time.monotonic_ns and an absolute clock_nanosleep (relative sleep as fallback).

    Hybrid wait (spin_ns > 0): sleep until spin_ns before the deadline, then spin on the clock to it. A
    virtual machine's timer wake-up is late by tens of microseconds and has a long tail; spinning the last
    part trades that CPU time for an on-time start (`rig bench loop --spin-us` shows the effect). spin_ns None: not chosen yet, the Loop sets it from
    [loop] spin_us."""

    is_real = True

    def __init__(self, spin_ns: int | None = None) -> None:
        self._nanosleep = _NANOSLEEP
        self._ts = Timespec()
        self._ts_ref = ctypes.byref(self._ts)
        self.spin_ns = spin_ns

    @staticmethod
    def now_ns() -> int:
        return time.monotonic_ns()

    def sleep_until(self, t_ns: int) -> None:
        spin = self.spin_ns
        if spin:
            now = time.monotonic_ns
            if now() < t_ns - spin:
                self._sleep(t_ns - spin)
            while now() < t_ns:
                pass
            return
        self._sleep(t_ns)

    def _sleep(self, t_ns: int) -> None:
        if self._nanosleep is not None:
            self._ts.tv_sec, self._ts.tv_nsec = divmod(t_ns, 1_000_000_000)
            while True:
                rc = self._nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, self._ts_ref, None)
                if rc != errno.EINTR:      # a signal: the Python handler runs after return; sleep on
                    return
                if time.monotonic_ns() >= t_ns:
                    return
        dt = t_ns - time.monotonic_ns()
        if dt > 0:
            time.sleep(dt * 1e-9)

    @staticmethod
    def spend(ns: int) -> None:
        end = time.monotonic_ns() + ns
        while time.monotonic_ns() < end:
            pass


class SimClock:
    """Simulated time: sleeping jumps to the deadline, computing costs nothing unless `spend` is called."""

    is_real = False

    def __init__(self, t0_ns: int = 0) -> None:
        self.t_ns = int(t0_ns)

    def now_ns(self) -> int:
        return self.t_ns

    def sleep_until(self, t_ns: int) -> None:
        if t_ns > self.t_ns:
            self.t_ns = t_ns

    def spend(self, ns: int) -> None:
        self.t_ns += int(ns)

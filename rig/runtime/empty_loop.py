"""An empty loop beside a run: the host's timing measured in the same run as the work it judges.

A process of its own wakes on absolute deadlines at a rate and a priority, with nothing in its period, and keeps
how late each wake-up was. At a priority above every other process of the run, pinned to one CPU, its
wake-ups more than a period late are the periods in which that CPU was taken from the run (by the kernel or the
hypervisor). `rig hil` runs one on each CPU beside the loop at PROBE_PRIORITY, at a tenth of the loop's rate so
that it takes little of the CPUs it measures (late_share: the loop's periods in a stretch where any of them was
held), and `rig bench stalls` measures the host with it."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time

import numpy as np

from rig.runtime.clock import MonotonicClock
from rig.runtime.rt import raise_priority

# above the loop ([loop] rt_priority, 80) and its watchdog (10 above it): at the loop's own priority an empty loop
# on the loop's CPU waits behind a long period of the loop, and the run's own work would read as the host's
PROBE_PRIORITY = 99


def _wake(first_ns, count, stop, late_ns, period_ns: int, priority: int, cpu: int | None) -> None:
    # forked from the run's process with its handlers: a Ctrl-C to the process group is the run's to act on (it
    # stops this loop), and a SIGTERM ends this one quietly
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    raise_priority(priority)
    clock = MonotonicClock(0)
    t = time.monotonic_ns() + period_ns
    first_ns.value = t
    late = np.frombuffer(late_ns, dtype=np.int64)
    k = 0
    while k < late.size and not stop.value:
        clock.sleep_until(t)
        late[k] = time.monotonic_ns() - t
        k += 1
        count.value = k
        t += period_ns


class EmptyLoop:
    """with EmptyLoop(rate_hz, seconds, priority, cpu) as el: ... ; then el.late_us() and el.late_spans_ns().
    It stops at the block's end or after `seconds`, whichever comes first; cpu None: where the kernel puts it."""

    def __init__(self, rate_hz: float, seconds: float, priority: int = 0, cpu: int | None = None) -> None:
        self.period_ns = int(round(1e9 / rate_hz))
        n = int(seconds * rate_hz) + 1
        self._first, self._count, self._stop = mp.RawValue("q", 0), mp.RawValue("q", 0), mp.RawValue("b", 0)
        self._late = mp.RawArray("q", n)
        self._proc = mp.get_context("fork").Process(
            target=_wake, args=(self._first, self._count, self._stop, self._late, self.period_ns, priority, cpu),
            daemon=True, name="rig-empty-loop")

    def __enter__(self) -> "EmptyLoop":
        self._proc.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.value = 1
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()

    def late_us(self) -> np.ndarray:
        """Each wake-up's lateness after its deadline (us), in order."""
        return np.frombuffer(self._late, dtype=np.int64)[:self._count.value] * 1e-3

    def late_spans_ns(self, late_ns: int | None = None) -> np.ndarray:
        """(deadline, wake-up) of each wake-up more than late_ns (default: its period) after its deadline, on the
        monotonic clock (ns): the stretches its CPU was taken from it."""
        late = np.frombuffer(self._late, dtype=np.int64)[:self._count.value]
        k = np.flatnonzero(late > (self.period_ns if late_ns is None else late_ns))
        t = self._first.value + self.period_ns * k.astype(np.int64)
        return np.stack([t, t + late[k]], axis=1)


def late_share(loops, t0_ns: int, t1_ns: int, period_ns: int) -> float | None:
    """The share of the periods of [t0_ns, t1_ns) (the grid t0_ns + k period_ns) that fall in a stretch where any
    of the empty loops woke more than one such period late; None for an empty window."""
    n = (t1_ns - t0_ns) // period_ns
    if n <= 0:
        return None
    late = np.zeros(n, dtype=bool)
    for el in loops:
        for a, b in el.late_spans_ns(period_ns):
            k0, k1 = max(0, -(-(a - t0_ns) // period_ns)), min(n, -(-(b - t0_ns) // period_ns))
            if k1 > k0:                 # (a stretch before the window has k1 <= 0: a slice would wrap)
                late[k0:k1] = True
    return float(late.mean())

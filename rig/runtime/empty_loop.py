"""An empty loop beside a run: the host's timing measured in the same run as the work it judges.

A process of its own wakes on absolute deadlines at a rate and a priority, with nothing in its period but the fixed
work below, and keeps how late each wake-up was. At a priority above every other process of the run, pinned to one
CPU, its wake-ups more than a period late are the periods in which that CPU was taken from the run (by the kernel
or the hypervisor). `rig hil` runs one on each CPU beside the loop at PROBE_PRIORITY, at a tenth of the loop's rate
so that it takes little of the CPUs it measures (late_share: the loop's periods in a stretch where any of them was
held), and `rig bench stalls` measures the host with it.

A host can also slow a CPU without taking it: the same work takes longer (another guest on the core's other
hardware thread, a lower clock). An empty loop sees no late wake-up then, so each wake-up also times a fixed piece
of compiled arithmetic (FIXED_WORK iterations, about 20-30 us here), whose time depends on nothing but the core's
speed: a full load of the run's own on the other CPU moved it by at most 6 % here. A stretch in which every CPU's
took SLOWED times its median over the run is the host's (slowed_share). A host can also take a CPU for a
hundred microseconds or two at a time, often but not for long: a stretch's median does not move then, and no
wake-up is a period late, but many wake-ups' fixed work takes SLOWED times its fastest or longer (the 10th
percentile over the run): their share is noisy_share. It is a thin sample of a CPU (a short piece of work at a tenth
of the loop's rate), so it is given beside a run's figures and decides nothing (drivers/README.md, a noisy host)."""
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
FIXED_WORK = 12000               # iterations of a dependent multiply-add: the core's speed, not the memory's
SLOWED = 1.25                    # a CPU slowed: its fixed work took this much longer than its median ...
SLOWED_WINDOW_NS = 50_000_000    # ... over 50 ms of wake-ups (their median: an interrupt in one does not count)
QUIET_NOISY = 0.03                # noisy_share on a quiet host, the run's own load beside (drivers/README.md)
_compiled = None


def _fixed_work():
    """The fixed work, compiled on first use (numba imported then: `rig hil` refuses bad input before any heavy
    import) and inherited by the forked loops."""
    global _compiled
    if _compiled is None:
        import numba

        def work(n):
            x = 1.0
            for _ in range(n):            # each step waits for the one before: the core's latency, not its width
                x = x * 1.0000001 + 1e-9
            return x
        _compiled = numba.njit(cache=True)(work)
        _compiled(1)
    return _compiled


def _wake(first_ns, count, stop, late_ns, work_ns, period_ns: int, priority: int, cpu: int | None,
          speed: bool) -> None:
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
    late, work = np.frombuffer(late_ns, dtype=np.int64), np.frombuffer(work_ns, dtype=np.int64)
    fixed_work = _fixed_work() if speed else None
    k = 0
    while k < late.size and not stop.value:
        clock.sleep_until(t)
        woke = time.monotonic_ns()
        late[k] = woke - t
        if fixed_work is not None:
            fixed_work(FIXED_WORK)
            work[k] = time.monotonic_ns() - woke
        k += 1
        count.value = k
        t += period_ns


class EmptyLoop:
    """with EmptyLoop(rate_hz, seconds, priority, cpu) as el: ... ; then el.late_us(), el.late_spans_ns() and, with
    speed=True (the fixed work timed at each wake-up), el.slowed_spans_ns().
    It stops at the block's end or after `seconds`, whichever comes first; cpu None: where the kernel puts it."""

    def __init__(self, rate_hz: float, seconds: float, priority: int = 0, cpu: int | None = None, *,
                 speed: bool = False) -> None:
        self.period_ns = int(round(1e9 / rate_hz))
        self.speed = speed
        if speed:
            _fixed_work()                # compiled (or loaded from numba's cache) here: the forked loop inherits it
        n = int(seconds * rate_hz) + 1
        self._first, self._count, self._stop = mp.RawValue("q", 0), mp.RawValue("q", 0), mp.RawValue("b", 0)
        self._late, self._work = mp.RawArray("q", n), mp.RawArray("q", n)
        self._proc = mp.get_context("fork").Process(
            target=_wake, args=(self._first, self._count, self._stop, self._late, self._work, self.period_ns,
                                priority, cpu, speed),
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

    def work_us(self) -> np.ndarray:
        """Each wake-up's fixed work (us), in order: the CPU's speed."""
        return np.frombuffer(self._work, dtype=np.int64)[:self._count.value] * 1e-3

    def slowed_spans_ns(self, factor: float = SLOWED, window_ns: int = SLOWED_WINDOW_NS) -> np.ndarray:
        """(start, end) of each window_ns stretch whose wake-ups' fixed work took, in their median, factor times
        its median over the whole run or longer, on the monotonic clock (ns): the stretches its CPU ran slowed."""
        work = np.frombuffer(self._work, dtype=np.int64)[:self._count.value]
        per = max(1, int(window_ns // self.period_ns))
        nw = work.size // per
        if nw == 0 or not self.speed:     # (not timed: no stretch is known slowed)
            return np.zeros((0, 2), dtype=np.int64)
        med = np.median(work[:nw * per].reshape(nw, per), axis=1)
        w = np.flatnonzero(med >= factor * np.median(work))
        t = self._first.value + self.period_ns * per * w.astype(np.int64)
        return np.stack([t, t + self.period_ns * per], axis=1)

    def noisy_counts(self, t0_ns: int, t1_ns: int, factor: float = SLOWED) -> tuple[int, int]:
        """(slowed, all) of the wake-ups in [t0_ns, t1_ns) whose fixed work took factor times its fastest over the
        run (the 10th percentile) or longer; (0, 0) untimed."""
        work = np.frombuffer(self._work, dtype=np.int64)[:self._count.value]
        if not self.speed or work.size < 10:
            return 0, 0
        t = self._first.value + self.period_ns * np.arange(work.size, dtype=np.int64)
        w = work[(t >= t0_ns) & (t < t1_ns)]
        return int(np.count_nonzero(w >= factor * np.percentile(work, 10))), int(w.size)


def _periods_in(spans, t0_ns: int, n: int, period_ns: int) -> np.ndarray:
    """Which of the n periods t0_ns + k period_ns fall in one of the (start, end) spans."""
    hit = np.zeros(n, dtype=bool)
    for a, b in spans:
        k0, k1 = max(0, -(-(a - t0_ns) // period_ns)), min(n, -(-(b - t0_ns) // period_ns))
        if k1 > k0:                     # (a stretch before the window has k1 <= 0: a slice would wrap)
            hit[k0:k1] = True
    return hit


def late_share(loops, t0_ns: int, t1_ns: int, period_ns: int) -> float | None:
    """The share of the periods of [t0_ns, t1_ns) (the grid t0_ns + k period_ns) that fall in a stretch where any
    of the empty loops woke more than one such period late; None for an empty window."""
    n = (t1_ns - t0_ns) // period_ns
    if n <= 0:
        return None
    late = np.zeros(n, dtype=bool)
    for el in loops:
        late |= _periods_in(el.late_spans_ns(period_ns), t0_ns, n, period_ns)
    return float(late.mean())


def slowed_share(loops, t0_ns: int, t1_ns: int, period_ns: int) -> float | None:
    """The share of the periods of [t0_ns, t1_ns) that fall in a stretch where every empty loop's CPU ran slowed
    (EmptyLoop.slowed_spans_ns): the host's, since the run's own load does not slow a CPU's arithmetic; None for
    an empty window or without loops."""
    n = (t1_ns - t0_ns) // period_ns
    if n <= 0 or not loops:
        return None
    slowed = np.ones(n, dtype=bool)
    for el in loops:
        slowed &= _periods_in(el.slowed_spans_ns(), t0_ns, n, period_ns)
    return float(slowed.mean())


def noisy_share(loops, t0_ns: int, t1_ns: int, period_ns: int) -> float | None:
    """The share of all the empty loops' wake-ups in [t0_ns, t1_ns) whose fixed work took SLOWED times its fastest
    or longer (EmptyLoop.noisy_counts): the host taking the CPUs in short pieces; None without timed wake-ups there.
    (period_ns: the signature of the other shares.)"""
    slowed = total = 0
    for el in loops:
        a, b = el.noisy_counts(t0_ns, t1_ns)
        slowed, total = slowed + a, total + b
    return slowed / total if total else None

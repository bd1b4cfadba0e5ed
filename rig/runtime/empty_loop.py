"""An empty loop beside a run: the host's timing measured in the same run as the work it judges.

A process of its own wakes on absolute deadlines at a rate and a priority, with nothing in its period, and keeps
how late each wake-up was. Its share of wake-ups more than a period late is what the host (the kernel, the
hypervisor, the machine's other load) did in that window to any process of the run: `rig hil` reports it per
mode beside its own late periods, and `rig bench stalls` measures the host with it."""
from __future__ import annotations

import multiprocessing as mp
import time

import numpy as np

from rig.runtime.clock import MonotonicClock
from rig.runtime.rt import raise_priority


def _wake(first_ns, count, stop, late_ns, period_ns: int, priority: int) -> None:
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
    """with EmptyLoop(rate_hz, seconds, priority) as el: ... ; then el.late_share(t0_ns, t1_ns) and el.late_us().
    It stops at the block's end or after `seconds`, whichever comes first."""

    def __init__(self, rate_hz: float, seconds: float, priority: int = 0) -> None:
        self.period_ns = int(round(1e9 / rate_hz))
        n = int(seconds * rate_hz) + 1
        self._first, self._count, self._stop = mp.RawValue("q", 0), mp.RawValue("q", 0), mp.RawValue("b", 0)
        self._late = mp.RawArray("q", n)
        self._proc = mp.get_context("fork").Process(
            target=_wake, args=(self._first, self._count, self._stop, self._late, self.period_ns, priority),
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

    def late_share(self, t0_ns: int | None = None, t1_ns: int | None = None) -> float | None:
        """The share of the wake-ups whose deadlines fall in [t0_ns, t1_ns) (monotonic clock) that came more
        than a period late; None when there were none."""
        late = np.frombuffer(self._late, dtype=np.int64)[:self._count.value]
        deadline = self._first.value + self.period_ns * np.arange(late.size, dtype=np.int64)
        m = np.ones(late.size, dtype=bool)
        if t0_ns is not None:
            m &= deadline >= t0_ns
        if t1_ns is not None:
            m &= deadline < t1_ns
        return float((late[m] > self.period_ns).mean()) if m.any() else None

"""The request/response thread of a driver, kept off the control period (SCHED_FIFO where allowed)."""
from __future__ import annotations

import time

from rig.runtime.rt import raise_priority


class TriggeredPoller:
    """The request/response loop of a driver-owned thread, kept off the control period.

    The owner provides `_poll_once() -> bool` (True when a new sample arrived), `_stop` and `_trigger`
    (threading.Event), `_thread`, `poll_ns`, `priority`, and the ring `latency_ns` with its fill `n_latency`."""

    def latencies_us(self) -> list[float]:
        n = min(self.n_latency, len(self.latency_ns))
        return [x * 1e-3 for x in self.latency_ns[:n]]

    def _stop_thread(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def trigger(self) -> None:
        """The period started (SYNC sent): fetch the next sample now, so it is in by the next period."""
        self._trigger.set()

    def _run(self) -> None:
        """Poll on each trigger until a new sample arrives (at most ~0.85 poll period), or once per poll
        period when no trigger comes (loop not running: the sample stays fresh, the watchdog fed)."""
        raise_priority(self.priority)
        stop, trig = self._stop, self._trigger
        budget = int(0.85 * self.poll_ns)
        while not stop.is_set():
            triggered = trig.wait(self.poll_ns * 1e-9)
            trig.clear()
            end = time.monotonic_ns() + (budget if triggered else 0)
            while not self._poll_once() and time.monotonic_ns() < end and not stop.is_set():
                time.sleep(5e-5)

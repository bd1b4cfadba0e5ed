"""The loop's clock work: absolute deadlines, the overrun policy, timing statistics and the watchdogs.

- Absolute deadlines in integer ns on an injected clock (`t += period`), so tests run in simulated time.
- Overrun policy: "skip" jumps to the first deadline still ahead and counts the skipped periods; "catch_up"
  runs the late periods back to back. Counters: overruns (cycles that ended after their period), skipped.
  missed_deadline_fraction = (overruns + skipped) / (iterations + skipped).
- The gap check: wake-ups further apart than watchdog_s are a fault. On the real clock a watchdog thread
  (rig/safety.py Watchdog) also nulls the valve if the loop hangs inside a period.
- An optional Port.idle() runs in the slack after a period when at least half a period is left.
"""
from __future__ import annotations

import array
import math

import numpy as np

from rig.lifecycle import State
from rig.safety import Watchdog

_FAULT = State.FAULT


class Scheduler:
    def __init__(self, clock, rate_hz: float, policy: str, watchdog_s: float, keep: int,
                 watchdog_thread: bool) -> None:
        if policy not in ("skip", "catch_up"):
            raise ValueError(f"overrun policy {policy!r}")
        self.clock = clock
        self.rate_hz = float(rate_hz)
        self.period_ns = int(round(1e9 / self.rate_hz))
        self.policy = policy
        self.watchdog_s = watchdog_s
        self.watchdog_ns = int(round(watchdog_s * 1e9))
        self.use_wd_thread = watchdog_thread
        self.wd: Watchdog | None = None
        self.iterations = 0
        self.overruns = 0
        self.skipped = 0
        self.keep = int(keep)
        self.wake_ns = array.array("q", bytes(8 * self.keep))       # ring of the last `keep` periods
        self.compute_ns = array.array("q", bytes(8 * self.keep))
        self.t0_ns: int | None = None

    def start_watchdog(self, on_trip) -> None:
        """Started before the real-time set-up: the thread keeps the normal policy and any CPU."""
        if self.use_wd_thread and self.wd is None:
            self.wd = Watchdog(self.watchdog_s, on_trip).start()

    def stop_watchdog(self) -> None:
        if self.wd is not None:
            self.wd.stop()
            self.wd = None

    def run(self, cycle, gate, *, seconds: float | None, iterations: int | None, activate_after_s: float | None,
            idle=None) -> None:
        """Periods until `seconds` of loop time, `iterations`, or the gate's stop reason. cycle(t, wake
        latency, previous compute) is one period; the gate takes the faults and the activation request."""
        clock, period, keep = self.clock, self.period_ns, self.keep
        skip = self.policy == "skip"
        wake_a, comp_a = self.wake_ns, self.compute_ns
        t = clock.now_ns() + period
        if self.t0_ns is None:
            self.t0_ns = t
        end_t = t + int(round(seconds * 1e9)) if seconds is not None else None
        max_it = self.iterations + iterations if iterations is not None else None
        act_it = (self.iterations + max(1, int(round(activate_after_s * self.rate_hz)))
                  if activate_after_s is not None else -1)
        wd = self.wd
        prev_wake = None
        compute_prev = 0
        idle = idle if clock.is_real else None
        idle_ns = period // 2
        while gate.stop_reason is None:
            if end_t is not None and t >= end_t:
                gate.stop("time")
                break
            if max_it is not None and self.iterations >= max_it:
                gate.stop("iterations")
                break
            clock.sleep_until(t)
            wake = clock.now_ns()
            if prev_wake is not None and wake - prev_wake > self.watchdog_ns and gate.state is not _FAULT:
                gate.t_ns = t
                gate.fault(f"watchdog: {(wake - prev_wake) / 1e6:.3f} ms between periods "
                           f"(limit watchdog_s = {self.watchdog_ns / 1e6:g} ms)")
            if wd is not None:
                wd.beat += 1
                if wd.tripped and gate.state is not _FAULT:
                    gate.fault(wd.tripped)
            prev_wake = wake
            if self.iterations == act_it:
                gate.request_active(True)
            cycle(t, wake - t, compute_prev)
            done = clock.now_ns()
            j = self.iterations % keep
            wake_a[j] = wake - t
            comp_a[j] = compute_prev = done - wake
            self.iterations += 1
            t += period
            if done > t:
                self.overruns += 1
                if skip:
                    missed = (done - t) // period + 1
                    self.skipped += missed
                    t += missed * period
            elif idle is not None and t - done > idle_ns:
                idle()                      # the port's housekeeping, in the slack before the next period

    # ---- figures --------------------------------------------------------------------------------------------
    @property
    def missed_deadline_fraction(self) -> float:
        sched = self.iterations + self.skipped
        return (self.overruns + self.skipped) / sched if sched else 0.0

    def timing_us(self) -> dict:
        """p50/p99/max of wake latency and compute over the kept periods, in microseconds."""
        n = min(self.iterations, self.keep)
        out = {}
        for key, arr in (("wake_latency_us", self.wake_ns), ("compute_us", self.compute_ns)):
            a = np.frombuffer(arr, dtype=np.int64)[:n] * 1e-3
            if n:
                out[key] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                            "max": float(a.max())}
            else:
                out[key] = {"p50": math.nan, "p99": math.nan, "max": math.nan}
        return out

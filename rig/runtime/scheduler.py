"""The loop's clock work: absolute deadlines, the overrun policy, timing statistics and the watchdogs.

- Absolute deadlines in integer ns on an injected clock (`t += period`), so tests run in simulated time.
- Overrun policy: "skip" jumps to the first deadline still ahead and counts the skipped periods; "catch_up"
  runs the late periods back to back. Counters: overruns (cycles that ended after their period), skipped.
  missed_deadline_fraction = (overruns + skipped) / (iterations + skipped).
- The gap check: wake-ups further apart than watchdog_s are a fault. On the real clock a watchdog thread
  (rig/runtime/safety.py Watchdog) also nulls the valve if the loop hangs inside a period.
- The lag rule: a period whose wake-up comes more than lag_limit_s after its deadline is a fault (the loop
  runs behind real time: a controller acting on old data). Checked at every wake-up, so the fault comes in
  the period the limit is crossed.
- The missed-deadline rule: more than missed_limit of the periods scheduled over the last missed_window_s
  missed their deadline -> fault. Counted in MISS_BLOCKS blocks of loop time per window (a few integer
  operations at a block's end, nothing per period beyond a compare), judged after that period's work (rare
  code runs from cold caches: tens of us, kept out of the period's time; the fault comes with the next one).
- The start-up rate check (rate_check): over the first periods (START_MIN_S, 50 to 2000 periods) the
  work of one period (wake-up to the next sleep: read, kernel, write, record and the loop's own bookkeeping)
  is measured; if its median exceeds period_budget of the period the loop cannot hold the rate on this
  machine, and the run is refused (RateRefused, a ConfigError, after a safe stop) with the figures.
- `idle` (the loop's slack work: its 10 Hz watch when due, and an optional Port.idle()) runs in the slack after
  a period when at least half a period is left.
- The stop period: an ACTIVE run stops through one INACTIVE period (valve null written, the period
  recorded), so the recording ends with the null the valve got: the last period of a run of `seconds` or
  `iterations`, or the period after a stop request (a signal, the control file, a console).
"""
from __future__ import annotations

import array
import math
import time

import numpy as np

from rig.errors import ConfigError
from rig.runtime.lifecycle import State
from rig.runtime.safety import Watchdog

_FAULT, _ACTIVE = State.FAULT, State.ACTIVE
MISS_BLOCKS = 10            # blocks per missed-deadline window
START_PERIODS = 50          # the start-up rate check measures at least this many periods ...
START_MIN_S = 0.05          # ... and at least this long, but ...
START_MAX_PERIODS = 2000    # ... at most this many (a loop that cannot keep up would reach the lag limit first)
MAX_CPU_SHARE = 0.9         # the loop thread on the CPU this share of the time over them: it never sleeps
MAX_START_MISSED = 0.95     # this share of their deadlines missed: it never catches up


class RateRefused(ConfigError):
    """The loop cannot hold its rate on this machine (measured at start-up)."""


class Scheduler:
    def __init__(self, clock, rate_hz: float, policy: str, watchdog_s: float, keep: int,
                 watchdog_thread: bool, *, lag_limit_s: float = math.inf, missed_limit: float = 1.0,
                 missed_window_s: float = 1.0, period_budget: float = 1.0, rate_check: bool = False) -> None:
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
        self.watchdog_priority = 0          # SCHED_FIFO of the watchdog thread (the session's, real-time runs)
        self.iterations = 0
        self.overruns = 0
        self.skipped = 0
        self.keep = int(keep)
        self.wake_ns = array.array("q", bytes(8 * self.keep))       # ring of the last `keep` periods
        self.compute_ns = array.array("q", bytes(8 * self.keep))
        self.cpu_ns: array.array | None = None      # measure_cpu(): the loop thread's CPU time per period
        self.t0_ns: int | None = None
        self.lag_limit_s = lag_limit_s
        self.lag_ns = int(round(lag_limit_s * 1e9)) if math.isfinite(lag_limit_s) else 1 << 62
        self.missed_limit = float(missed_limit)
        self.missed_window_s = float(missed_window_s)
        self._block_ns = max(self.period_ns, int(round(missed_window_s * 1e9 / MISS_BLOCKS)))   # loop time
        self._blocks: list[tuple[int, int]] = []      # (missed, scheduled) of the last MISS_BLOCKS blocks
        self.period_budget = float(period_budget)
        self._start_n = (max(START_PERIODS, min(START_MAX_PERIODS, int(math.ceil(START_MIN_S * self.rate_hz))))
                         if rate_check else 0)
        self.busy_ns = array.array("q", bytes(8 * self._start_n))   # the start-up check's periods
        self._start_done = 0
        self.start_figures: dict | None = None

    def measure_cpu(self) -> None:
        """Also record each period's CPU time of the loop thread from its wake-up to the end of its work
        (time.thread_time_ns, about 1 us a call, so benchmarks only; read just before the wake-up time, so the
        compute figure does not hold it): the period's own work without the time the host gave other
        processes in it."""
        self.cpu_ns = array.array("q", bytes(8 * self.keep))

    def start_watchdog(self, on_trip) -> None:
        """Started before the loop thread's real-time set-up: any CPU; SCHED_FIFO watchdog_priority if set."""
        if self.use_wd_thread and self.wd is None:
            self.wd = Watchdog(self.watchdog_s, on_trip, self.watchdog_priority).start()

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
        end_t, max_it, act_it = self._ends(t, seconds, iterations, activate_after_s)
        wd = self.wd
        now_ns, sleep_until, watchdog_ns = clock.now_ns, clock.sleep_until, self.watchdog_ns   # bound once
        prev_wake = None
        compute_prev = 0
        idle = idle if clock.is_real else None
        idle_ns = period // 2
        lag_ns = self.lag_ns
        block_t = t + self._block_ns                       # the end of the current block (loop time)
        block_start = (self.overruns + self.skipped, self.iterations + self.skipped)
        block_end = None                                   # (missed, scheduled) of a block just ended
        cpu_a = self.cpu_ns
        cpu_now = time.thread_time_ns
        final = False                                      # this is the stop period
        while True:
            if gate.stop_reason is not None:
                if final or gate.state is not _ACTIVE:
                    break
                final = True                               # the stop period: valve to null, recorded
            elif end_t is not None and t >= end_t:
                gate.stop("time")
                break
            elif max_it is not None and self.iterations >= max_it:
                gate.stop("iterations")
                break
            elif (end_t is not None and t + period >= end_t) or \
                    (max_it is not None and self.iterations + 1 >= max_it):
                final = True                               # the run's last period is its stop period
            if self._start_done < self._start_n and prev_wake is not None:
                self._start_sample(gate, prev_wake)
            sleep_until(t)
            if cpu_a is not None:
                c0 = cpu_now()                             # (a syscall: outside the compute it measures)
            wake = now_ns()
            if prev_wake is not None and wake - prev_wake > watchdog_ns and gate.state is not _FAULT:
                self._gap_fault(gate, t, wake - prev_wake)
            if wake - t > lag_ns and gate.state is not _FAULT:
                self._lag_fault(gate, t, wake - t)
            if t >= block_t:                             # a block of loop time ended: the missed-deadline rule
                block_t = t + self._block_ns
                now = (self.overruns + self.skipped, self.iterations + self.skipped)
                block_end = (now[0] - block_start[0], now[1] - block_start[1])     # judged after the period
                block_start = now
            if wd is not None:
                wd.beat += 1
                if wd.tripped and gate.state is not _FAULT:
                    gate.fault(wd.tripped)
            prev_wake = wake
            if self.iterations == act_it and not final:
                gate.request_active(True)
            if final:
                gate.request_active(False)
            cycle(t, wake - t, compute_prev)
            done = now_ns()
            j = self.iterations % keep
            if cpu_a is not None:
                cpu_a[j] = cpu_now() - c0
            wake_a[j] = wake - t
            comp_a[j] = compute_prev = done - wake
            if block_end is not None:                    # rare code (cold caches): outside the period's time
                gate.t_ns = t
                self._missed_block(gate, *block_end)
                block_end = None
            self.iterations += 1
            t += period
            if done > t:
                t = self._overran(done, t, skip)
            elif idle is not None and t - done > idle_ns:
                idle()                      # the port's housekeeping, in the slack before the next period

    def _ends(self, t: int, seconds, iterations, activate_after_s) -> tuple:
        """(loop time to stop at or None, iteration to stop at or None, iteration to activate at or -1)."""
        end_t = t + int(round(seconds * 1e9)) if seconds is not None else None
        max_it = self.iterations + iterations if iterations is not None else None
        act_it = (self.iterations + max(1, int(round(activate_after_s * self.rate_hz)))
                  if activate_after_s is not None else -1)
        return end_t, max_it, act_it

    def _start_sample(self, gate, prev_wake: int) -> None:
        """The start-up rate check: the work of the first periods, judged once there are enough."""
        now = self.clock.now_ns()
        self.busy_ns[self._start_done] = now - prev_wake                      # the last period's work
        if self._start_done == 0:
            self._start_at = (time.thread_time_ns(), now, self.overruns + self.skipped,
                              self.iterations + self.skipped)
        self._start_done += 1
        if self._start_done == self._start_n:
            self._check_rate(gate, time.thread_time_ns(), now)

    def _gap_fault(self, gate, t: int, gap_ns: int) -> None:
        """FAULT: the gap since the last wake-up passed the watchdog's limit."""
        gate.t_ns = t
        gate.fault(f"watchdog: {gap_ns / 1e6:.3f} ms between periods "
                   f"(limit watchdog_s = {self.watchdog_ns / 1e6:g} ms)")

    def _lag_fault(self, gate, t: int, lag_ns: int) -> None:
        """FAULT: the loop woke further behind its deadline than lag_limit_s."""
        gate.t_ns = t
        gate.fault(f"loop lag: {lag_ns / 1e6:.1f} ms behind real time (limit lag_limit_s = {self.lag_ns / 1e6:g} ms): "
                   f"the loop cannot keep up")

    def _overran(self, done: int, t: int, skip: bool) -> int:
        """Count an overrun; under the skip policy, skip the periods already past. The next deadline."""
        self.overruns += 1
        if skip:
            missed = (done - t) // self.period_ns + 1
            self.skipped += missed
            t += missed * self.period_ns
        return t

    # ---- the rules off the per-period path ------------------------------------------------------------------
    def _missed_block(self, gate, missed: int, scheduled: int) -> None:
        """A block of periods ended: the missed-deadline fraction over the last window, a fault above the limit."""
        blocks = self._blocks
        blocks.append((missed, scheduled))
        if len(blocks) > MISS_BLOCKS:
            del blocks[0]
        if len(blocks) < MISS_BLOCKS or gate.state is _FAULT:
            return
        m = sum(b[0] for b in blocks)
        n = sum(b[1] for b in blocks)
        if n and m / n > self.missed_limit:
            gate.fault(f"missed deadlines: {100 * m / n:.1f} % of {n} periods over the last "
                       f"{self.missed_window_s:g} s (limit missed_limit = {100 * self.missed_limit:g} %): "
                       f"the loop cannot hold {self.rate_hz:g} Hz (the host is busy or the loop lacks real-time "
                       f"priority: docs/OPERATING.md real-time set-up; --sim-time runs without a clock to keep)")

    def _check_rate(self, gate, cpu_now_ns: int, now_ns: int) -> None:
        """The start-up rate check over its first periods: the median work of a period against period_budget
        of the period; (real clock) the loop thread's CPU share: a loop that never sleeps (its wait spins
        through the whole slack) takes a whole CPU, which Linux's real-time throttling takes back for tens of
        ms every second (sched_rt_runtime_us), and starves the other threads of the process; and whether it
        met any deadline at all (work, wait and wake-up together longer than the period: it only falls
        behind; a stall of the machine is caught up within a few periods). The last only above missed_limit:
        missed_limit = 1 turns the missed-deadline rules off (a loaded machine without real-time priority)."""
        cpu0, wall0, missed0, sched0 = self._start_at
        wall_ns = now_ns - wall0
        missed, sched = self.overruns + self.skipped - missed0, self.iterations + self.skipped - sched0
        a = np.frombuffer(self.busy_ns, dtype=np.int64)
        busy = float(np.median(a))
        c = np.frombuffer(self.compute_ns, dtype=np.int64)[:min(self.iterations, self.keep)]
        compute = float(np.median(c)) if c.size else math.nan
        cpu_share = (cpu_now_ns - cpu0) / wall_ns if self.clock.is_real and wall_ns > 0 else 0.0
        self.start_figures = {"periods": int(a.size), "work_p50_us": busy / 1e3, "compute_p50_us": compute / 1e3,
                              "period_us": self.period_ns / 1e3, "period_budget": self.period_budget,
                              "cpu_share": cpu_share, "missed": missed, "scheduled": sched}
        head = f"loop rate {self.rate_hz:g} Hz: the loop cannot hold this rate here:"
        work = (f"a period's work takes {busy / 1e3:.1f} us (median over the first {a.size} periods; compute "
                f"{compute / 1e3:.1f} us, the rest the loop's own wake-up and bookkeeping) of the "
                f"{self.period_ns / 1e3:g} us period")
        if busy > self.period_budget * self.period_ns:
            text = (f"{head} {work}, above period_budget = {100 * self.period_budget:g} %; at most about "
                    f"{_round_down(1e9 * self.period_budget / busy):g} Hz on this machine")
        elif cpu_share > MAX_CPU_SHARE:
            spin = getattr(self.clock, "spin_ns", 0) or 0
            text = (f"{head} the loop thread was on the CPU {100 * cpu_share:.0f} % of the time over the first "
                    f"{a.size} periods: it never sleeps ({work}; the wait spins the last {spin / 1e3:g} us before "
                    f"each deadline, [loop] spin_us). Lower spin_us below the slack or lower the rate")
        elif sched and missed >= MAX_START_MISSED * sched and missed > self.missed_limit * sched:
            text = (f"{head} it missed {missed} of its first {sched} deadlines, falling further behind each period "
                    f"({work}; the rest is the wait and the wake-up)")
        else:
            return
        gate.stop("refused")
        raise RateRefused(text)

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


def _round_down(hz: float) -> float:
    """hz rounded down to two significant digits (a rate to suggest)."""
    if hz <= 0 or not math.isfinite(hz):
        return 0.0
    e = 10 ** (math.floor(math.log10(hz)) - 1)
    return math.floor(hz / e) * e

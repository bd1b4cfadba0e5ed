"""The empty loop beside a run (rig/runtime/empty_loop.py): a real process on the real clock. Held off its CPU
(here: stopped by a signal, as a hypervisor takes a vCPU), its wake-ups in that stretch come more than a period
late, and late_share counts those periods of a window, once however many loops saw them."""
from __future__ import annotations

import os
import signal
import time

from rig.runtime.empty_loop import EmptyLoop, late_share

RATE = 1000.0
PERIOD_NS = 1_000_000


def _hold(el: EmptyLoop, before_s: float, held_s: float, after_s: float) -> tuple[int, int]:
    """Stop the loop's process for held_s (between before_s and after_s of it running): when it stopped and went
    on (monotonic ns)."""
    time.sleep(before_s)
    t_stop = time.monotonic_ns()
    os.kill(el._proc.pid, signal.SIGSTOP)
    time.sleep(held_s)
    os.kill(el._proc.pid, signal.SIGCONT)
    t_cont = time.monotonic_ns()
    time.sleep(after_s)
    return t_stop, t_cont


def test_a_loop_held_off_its_cpu_marks_the_periods_it_was_held():
    with EmptyLoop(RATE, 5.0) as el, EmptyLoop(RATE, 5.0) as other:
        t_stop, t_cont = _hold(el, 0.2, 0.08, 0.2)
    spans = el.late_spans_ns()
    assert spans.shape[1] == 2 and (spans[:, 1] > spans[:, 0] + PERIOD_NS).all()
    held = (spans[:, 0] >= t_stop - 2 * PERIOD_NS) & (spans[:, 0] < t_cont + PERIOD_NS)
    assert held.sum() >= 40                                 # the 80 ms held, less what the host let slip anyway
    assert held.sum() >= 0.9 * len(spans) - 5               # the late wake-ups are the held stretch
    assert el.late_us().size > 300                          # it ran on after
    t0, t1 = t_stop - 100 * PERIOD_NS, t_cont + 100 * PERIOD_NS
    both = late_share([el, other], t0, t1, PERIOD_NS)
    alone = late_share([el], t0, t1, PERIOD_NS)
    assert 0.2 <= alone <= both <= 1.0                      # about 80 of the window's 280 periods
    slow = [EmptyLoop(RATE / 10, 1.0)]                      # never started: no wake-ups, no late periods
    assert late_share(slow, t0, t1, PERIOD_NS) == 0.0
    assert late_share([el], t1, t1, PERIOD_NS) is None      # an empty window


def test_a_slow_loop_marks_every_period_of_a_faster_grid_it_was_held_through():
    run_period = PERIOD_NS // 2                             # the run at 2 kHz, the empty loop at 100 Hz
    with EmptyLoop(100.0, 5.0) as el:
        t_stop, t_cont = _hold(el, 0.1, 0.1, 0.1)
    share = late_share([el], t_stop - 100 * run_period, t_cont + 100 * run_period, run_period)
    held = (t_cont - t_stop) / run_period                   # about 200 periods of the 2 kHz grid
    assert (held - 40) / (held + 200) <= share <= (held + 40) / (held + 200)
    assert late_share([el], t_cont + 20 * run_period, t_cont + 120 * run_period, run_period) <= 0.2   # after it


def _spin_at(priority: int, cpu: int, seconds: float) -> None:
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass
    os._exit(0)


def _fifo_allowed() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except PermissionError:
        return False
    return True


def test_the_probe_runs_above_a_loop_that_holds_its_cpu():
    """rig hil's empty loops (PROBE_PRIORITY) wake on time beside a task at the loop's priority that keeps their
    CPU for 60 ms; one at the loop's own priority waits behind it, and would count the run's own work as the
    host's."""
    import multiprocessing as mp

    import pytest

    from rig.config import config_from_dict
    from rig.runtime.empty_loop import PROBE_PRIORITY
    loop_priority = config_from_dict({}).loop.rt_priority
    if not _fifo_allowed():
        pytest.skip("SCHED_FIFO not allowed here")
    cpu = max(os.sched_getaffinity(0))
    with EmptyLoop(RATE, 3.0, PROBE_PRIORITY, cpu) as probe, EmptyLoop(RATE, 3.0, loop_priority, cpu) as level:
        time.sleep(0.3)
        hog = mp.get_context("fork").Process(target=_spin_at, args=(loop_priority, cpu, 0.06))
        t0 = time.monotonic_ns()
        hog.start()
        hog.join(10)
        t1 = time.monotonic_ns()
        time.sleep(0.1)
    def held(el):
        s = el.late_spans_ns()
        return int(((s[:, 0] >= t0 - PERIOD_NS) & (s[:, 0] < t1)).sum())
    assert held(level) >= 20                     # the 60 ms behind the hog, less the fork's start
    assert held(probe) <= 2


def test_a_stretch_is_the_hosts_slowing_only_where_every_cpu_ran_slowed():
    """Each wake-up times a fixed piece of compiled arithmetic (the CPU's speed); a 50 ms stretch whose median took
    SLOWED times the run's is a slowed CPU. A host's slowdown cannot be made here, so it is written into the two
    loops' record after their run: slowed_share counts a stretch only where every loop's CPU ran slowed."""
    import numpy as np

    from rig.runtime.empty_loop import PROBE_PRIORITY, slowed_share
    cpus = sorted(os.sched_getaffinity(0))
    with EmptyLoop(200.0, 2.0, PROBE_PRIORITY, cpus[0], speed=True) as a, \
            EmptyLoop(200.0, 2.0, PROBE_PRIORITY, cpus[-1], speed=True) as b:
        time.sleep(2.2)
    for el in (a, b):         # (how often the host slows this machine's CPUs is its own: drivers/README.md)
        w = el.work_us()
        assert w.size >= 350 and (w > 0).all()

    for el in (a, b):         # each at its median throughout (what the host did meanwhile left out) ...
        work = np.frombuffer(el._work, dtype=np.int64)[:el._count.value]
        work[:] = int(np.median(work))

    def slow(el, t_from, t_to):   # ... and twice that in one stretch
        work = np.frombuffer(el._work, dtype=np.int64)[:el._count.value]
        t = el._first.value + el.period_ns * np.arange(work.size)
        work[(t >= t_from) & (t < t_to)] *= 2

    t_from = a._first.value + 600_000_000
    t_to = t_from + 300_000_000
    w0, w1, grid = t_from - 300_000_000, t_to + 300_000_000, 500_000      # 900 ms of a 2 kHz run's periods
    slow(a, t_from, t_to)
    assert slowed_share([a, b], w0, w1, grid) == 0.0                       # one CPU slowed: not the host
    slow(b, t_from, t_to)
    assert 0.2 <= slowed_share([a, b], w0, w1, grid) <= 0.45               # a third of the window, to 50 ms
    assert slowed_share([], w0, w1, grid) is None and slowed_share([a, b], w1, w1, grid) is None


def test_a_noisy_host_is_the_share_of_wake_ups_slowed_against_the_fastest():
    """A host that takes a CPU for a hundred microseconds or two at a time, in one wake-up of ten, moves no
    stretch's median and holds no wake-up a period: noisy_share counts the wake-ups whose fixed work took SLOWED
    times its fastest (the run's 10th percentile), over every loop. Written into real loops' record, as above."""
    import numpy as np

    from rig.runtime.empty_loop import PROBE_PRIORITY, QUIET_NOISY, noisy_share, slowed_share
    cpus = sorted(os.sched_getaffinity(0))
    with EmptyLoop(200.0, 2.0, PROBE_PRIORITY, cpus[0], speed=True) as a, \
            EmptyLoop(200.0, 2.0, PROBE_PRIORITY, cpus[-1], speed=True) as b:
        time.sleep(2.2)
    w0, w1, grid = a._first.value, a._first.value + 1_500_000_000, 500_000
    for el in (a, b):
        work = np.frombuffer(el._work, dtype=np.int64)[:el._count.value]
        work[:] = 30_000                                     # 30 us throughout ...
        assert noisy_share([el], w0, w1, grid) == 0.0
        work[::5] = 180_000                                  # ... but every fifth wake-up 150 us longer
    share = noisy_share([a, b], w0, w1, grid)
    assert 0.18 <= share <= 0.22 and share > QUIET_NOISY
    assert slowed_share([a, b], w0, w1, grid) == 0.0        # what the stretches' medians do not see
    assert noisy_share([], w0, w1, grid) is None and noisy_share([a, b], w1 + 10**9, w1 + 10**9, grid) is None


def test_a_loop_without_the_timed_work_knows_no_slowed_stretch():
    """`rig bench stalls` runs its empty loops up to 20 kHz with nothing in their period: the fixed work is rig hil's
    (speed=True), and a loop without it says nothing of its CPU's speed rather than 'slowed throughout'."""
    from rig.runtime.empty_loop import slowed_share
    with EmptyLoop(RATE, 1.0) as a, EmptyLoop(RATE, 1.0) as b:
        time.sleep(0.6)
    assert a.late_us().size > 300 and (a.work_us() == 0).all()
    assert len(a.slowed_spans_ns()) == 0
    t0 = a._first.value
    assert slowed_share([a, b], t0, t0 + 400 * PERIOD_NS, PERIOD_NS) == 0.0

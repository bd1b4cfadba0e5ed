"""The real clock's hybrid wait ([loop] spin_us): it never returns before the deadline, past deadlines return
at once, and the loop gives a real clock the configured spin unless the caller chose one. (Ordering checks,
not timing: how much the spin buys is measured by `rig bench loop --spin-us`.)"""
from __future__ import annotations

import time

from rig.runtime.clock import MonotonicClock, SimClock
from rig.config import config_from_dict
from rig.runtime.loop import Loop
from sim_backend.backend import SimBackend
from tests.rig.support import CentringP, TinyPlant

DT = 1.0 / 5000.0


def test_hybrid_wait_returns_at_or_after_each_deadline():
    for spin_ns in (0, 50_000, 10_000_000):                  # none, part of the wait, longer than the wait
        clk = MonotonicClock(spin_ns)
        for _ in range(20):
            t = time.monotonic_ns() + 200_000
            clk.sleep_until(t)
            assert time.monotonic_ns() >= t
        clk.sleep_until(time.monotonic_ns() - 1_000_000)     # a past deadline: returns at once


def _loop(clock, spin_us=None):
    cfg = config_from_dict({"loop": {"spin_us": spin_us}} if spin_us is not None else {})
    port = SimBackend(TinyPlant(4, DT), DT, clock=clock)
    return Loop(cfg, port, [CentringP(dt=DT) for _ in range(4)], clock=clock, rate_hz=1 / DT,
                watchdog_thread=False)


def test_loop_sets_the_configured_spin_on_a_real_clock_only_if_unset():
    assert _loop(MonotonicClock(), 60.0).clock.spin_ns == 60_000
    assert _loop(MonotonicClock()).clock.spin_ns == round(config_from_dict({}).loop.spin_us * 1e3)
    assert _loop(MonotonicClock(5_000), 60.0).clock.spin_ns == 5_000      # the caller's choice stays
    assert not hasattr(_loop(SimClock(), 60.0).clock, "spin_ns")         # simulated time never spins


_NO_CHILD = """
import sys
started = []
sys.addaudithook(lambda ev, args: started.append(ev) if ev in ("subprocess.Popen", "os.posix_spawn", "os.exec",
                                                                 "os.fork") else None)
from rig.runtime.clock import MonotonicClock
from rig.runtime.rt import enter_realtime, leave_realtime
for _ in range(3):
    clk = MonotonicClock(0)
    clk.sleep_until(clk.now_ns() + 100_000)
st = enter_realtime(priority=0, cpu=None, lock_memory=True, freeze_gc=False)
leave_realtime(st)
print(",".join(started) or "none")
"""


def test_making_clocks_and_entering_real_time_start_no_process():
    """The C library is the process's own: looking it up by ctypes.util.find_library ran `ldconfig -p` in a child
    each time a clock was made, and that fork and exec held the real-time tasks of every CPU at a run's start."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-c", _NO_CHILD], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "none"

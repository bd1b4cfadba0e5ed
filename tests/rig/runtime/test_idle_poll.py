"""Idle CPUs kept polling (rig/runtime/idle_poll.py): when pollers start, that each is a SCHED_IDLE process on a
CPU of its own that really spins, and that they end with stop() and with the real-time state that started them."""
from __future__ import annotations

import os
import time

import pytest

from rig.runtime import idle_poll
from rig.runtime.rt import enter_realtime, leave_realtime


def test_auto_starts_pollers_only_where_no_cpuidle_driver_honours_pm_qos(tmp_path):
    none, haltpoll = tmp_path / "none", tmp_path / "haltpoll"
    none.write_text("none\n")
    haltpoll.write_text("haltpoll\n")
    assert idle_poll.halts_regardless(str(none))
    assert not idle_poll.halts_regardless(str(haltpoll))
    assert idle_poll.halts_regardless(str(tmp_path / "missing"))       # no cpuidle at all: the idle task halts
    assert idle_poll.wanted("auto", str(none)) and not idle_poll.wanted("auto", str(haltpoll))
    assert idle_poll.wanted("on", str(haltpoll)) and not idle_poll.wanted("off", str(none))


def _cpu_ns(pid: int) -> int:
    with open(f"/proc/{pid}/schedstat") as f:
        return int(f.read().split()[0])


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux only")
def test_pollers_are_idle_class_one_per_cpu_spin_and_end():
    p = idle_poll.IdlePollers().start()
    try:
        if p.note:
            pytest.skip(p.note)
        cpus = sorted(os.sched_getaffinity(0))
        assert len(p.procs) == len(cpus)
        assert [os.sched_getaffinity(q.pid) for q in p.procs] == [{c} for c in cpus]
        assert all(os.sched_getscheduler(q.pid) == os.SCHED_IDLE for q in p.procs)
        before = [_cpu_ns(q.pid) for q in p.procs]
        time.sleep(0.5)
        spent = [_cpu_ns(q.pid) - b for q, b in zip(p.procs, before)]
        assert max(spent) > 0.05e9, spent               # at least one spins (the other may yield to this test)
        procs = list(p.procs)
    finally:
        p.stop()
    assert not p.procs and all(q.poll() is not None for q in procs)


def test_the_realtime_state_starts_and_ends_them():
    st = enter_realtime(priority=0, cpu=None, lock_memory=False, freeze_gc=False, idle_poll="on")
    try:
        if st.notes:
            pytest.skip("; ".join(st.notes))
        assert st.idle_pollers == len(os.sched_getaffinity(0))
        assert f"idle_poll={st.idle_pollers} CPUs" in st.summary()
        procs = list(st._pollers.procs)
    finally:
        leave_realtime(st)
    assert st.idle_pollers == 0 and all(q.poll() is not None for q in procs)
    off = enter_realtime(priority=0, cpu=None, lock_memory=False, freeze_gc=False, idle_poll="off")
    leave_realtime(off)
    assert off.idle_pollers == 0

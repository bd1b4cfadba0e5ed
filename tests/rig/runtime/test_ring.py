"""The producer's rule of a shared row ring (rig/runtime/ring.py), as the compiled period and Recorder.push run it, and
a period that faults after the compiled call: its row corrected before it is published."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.isolation import make_isolation_controllers
from rig.runtime import ring as rr
from rig.runtime.clock import SimClock
from rig.config import Config
from rig.runtime.loop import Loop
from rig.runtime.recorder import Recorder, read_recording
from sim_backend.backend import make_sim_port
from tests.rig.support import ReadWritePort

DT = 2e-4


@settings(max_examples=80, deadline=None)
@given(cap=st.integers(1, 9), ops=st.lists(st.sampled_from(["period", "read", "end"]), max_size=120))
def test_the_reader_gets_every_row_not_dropped_once_in_order(cap, ops):
    """The period's order (publish the row before, claim, write) against a reader taking what is published:
    each row reaches the reader once and in order, or is dropped and counted; a claimed row is never seen
    before it is published."""
    hdr = np.zeros(len(rr.HEADER), dtype=np.int64)
    ring = np.full(cap, -1.0)
    made = kept = 0
    seen: list[float] = []
    for op in ops:
        if op == "period":
            rr.publish(hdr)
            r = rr.claim(hdr, cap)
            if r >= 0:
                ring[r] = made
                kept += 1
            made += 1
        elif op == "read":                               # the writer: every published row, then the tail
            seen += [ring[k % cap] for k in range(hdr[rr.TAIL], hdr[rr.HEAD])]
            hdr[rr.TAIL] = hdr[rr.HEAD]
        else:                                            # the run ends: the last row published
            rr.publish(hdr)
        assert 0 <= rr.room(hdr, cap) <= cap
        assert hdr[rr.HEAD] - hdr[rr.TAIL] <= cap
    rr.publish(hdr)
    seen += [ring[k % cap] for k in range(hdr[rr.TAIL], hdr[rr.HEAD])]
    assert seen == sorted(set(seen)) and len(seen) == kept
    assert hdr[rr.DROPPED] == made - kept


def test_a_ring_that_never_fills_overwrites_and_counts_nothing():
    hdr = np.zeros(len(rr.HEADER), dtype=np.int64)
    hdr[rr.TAIL] = rr.NEVER_FULL
    rows = []
    for _ in range(10):
        rr.publish(hdr)
        rows.append(rr.claim(hdr, 4))
    assert rows == [0, 1, 2, 3, 0, 1, 2, 3, 0, 1] and hdr[rr.DROPPED] == 0
    assert rr.pending_row(hdr, 4) == 1 and rr.room(hdr, 4) == 4
    rr.publish(hdr)
    assert rr.pending_row(hdr, 4) == -1 and hdr[rr.HEAD] == 10


def test_a_port_write_that_fails_is_recorded_with_its_fault_and_no_command(tmp_path):
    """The compiled period writes the row before the port write; the write fails: the row in the ring, not yet
    published, is corrected (fault flag, lifecycle FAULT, null commands) and every period is in the file."""
    cfg = Config()
    clock = SimClock()
    port = ReadWritePort(make_sim_port(cfg, DT, clock=clock))       # the loop calls its write
    loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clock, rate_hz=1 / DT, watchdog_thread=False)
    write, calls = port.write, [0]

    def failing_write(t_ns, commands):
        calls[0] += 1
        if calls[0] == 400:
            raise OSError("valve amplifier gone")
        write(t_ns, commands)
    port.write = failing_write
    path = tmp_path / "write_fault.h5"
    rec = Recorder(path, loop.channels, rate_hz=1 / DT).start()
    loop.recorder = rec
    assert loop.run(iterations=1000, activate_after_s=0.02) == "fault"
    rec.close()
    r = read_recording(path)
    k = int(np.argmax(r["fault"] == 1.0))
    assert len(r["time_s"]) == loop.iterations and k > 0
    assert r["lifecycle_state"][k] == 3 and r["lifecycle_state"][k - 1] == 2 and r["fault"][k - 1] == 0
    assert np.all(r["valve_cmd_V"][k] == 0.0) and np.abs(r["valve_cmd_V"][k - 1]).max() > 0.0
    assert any("port write failed" in text for _, text in r["events"])

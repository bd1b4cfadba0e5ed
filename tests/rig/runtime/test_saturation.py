"""Saturation recovery in the running loop (simulated time): a scheduling gap (skip policy, sim backend's
overrun knob, a latest-value sensor) leaves the isolation controllers' double integration with a velocity error that drives the
valves to the clamp for seconds; without recovery the safety check faults (saturation_s). With the
controllers' recovery ([controller] sat_reset_s) isolation is suspended bumplessly, the valves leave the
clamp, and isolation resumes by itself: no FAULT, back in the linear range, isolating again."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import config_from_dict
from rig.runtime.lifecycle import State
from rig.runtime.loop import Loop
from sim_backend.backend import make_sim_port

RATE = 5000.0
DT = 1.0 / RATE
STALL_S = 0.006              # 30 skipped periods, well below the 50 ms watchdog
AT_S = 0.8                   # (how long the valves stay at the clamp depends on the floor motion at the gap)


def run_stall(controller: dict, seconds: float, sample_driven: bool = False, stall_s: float = STALL_S,
              at_s: float = AT_S):
    cfg = config_from_dict({"loop": {"overrun_policy": "skip"}, "controller": controller})
    clk = SimClock()
    # sample_driven=False: a latest-value sensor, the gap's samples are lost (a sample-driven port replays them)
    port = make_sim_port(cfg, DT, clock=clk, sample_driven=sample_driven)
    ctrls = make_isolation_controllers(cfg, DT)
    loop = Loop(cfg, port, ctrls, clock=clk, rate_hz=RATE, stop_on_fault=False)
    loop.configure()
    loop.activate()
    port.inject("overrun", at_s=at_s, extra_s=stall_s)
    plant = port.plant
    rows = []

    i_cmd = loop.kernel.layout["valve_cmd_V"]

    class Rows:                           # the loop's recorder interface; keeps what the test looks at
        def push_row(self, row):
            rows.append((*row[i_cmd:i_cmd + 4], plant.table_m, sum(plant.floor_m) / 4,
                         *(float(c.suspended(s)) for c, s in zip(ctrls, loop.states))))

        def event(self, t_s, text):
            pass

    loop.recorder = Rows()
    loop.run(seconds=seconds)
    r = np.array(rows)
    cmd, table, floor, suspended = r[:, 0:4], r[:, 4], r[:, 5], r[:, 6:10]
    return loop, cmd, table, floor, suspended


def test_without_recovery_the_gap_latches_the_clamp_and_faults():
    loop, cmd, _, _, suspended = run_stall({"sat_reset_s": 0.0}, 3.0)
    assert loop.skipped == round(STALL_S / DT)
    assert loop.state is State.FAULT and not suspended.any()
    assert "clamp" in loop.lc.fault_reason


def test_recovery_returns_to_isolation_without_fault(caplog):
    with caplog.at_level(logging.INFO, logger="rig.loop"):
        loop, cmd, table, floor, suspended = run_stall({}, 15.0)
    assert loop.skipped == round(STALL_S / DT)
    assert loop.lc.fault_reason is None and loop.stop_reason == "time"
    assert np.max(np.abs(cmd[int(0.5 * RATE):int(2.0 * RATE)])) == pytest.approx(10.0)   # it did saturate
    last = slice(int(13.0 * RATE), None)        # the blend (0.1 Hz) forgets in ~10 s
    assert np.max(np.abs(cmd[last])) < 0.9 * 10.0                       # back in the linear range
    assert suspended.max() == 1.0 and not suspended[last].any()        # suspended, then isolating again
    assert np.std(table[last]) < 0.6 * np.std(floor[last])              # passive ~1.0, isolating 0.25-0.45
    sus = [r.message for r in caplog.records if "isolation suspended" in r.message]
    res = [r.message for r in caplog.records if "isolation resumed" in r.message]
    assert sus and len(sus) == len(res)                  # each suspension logged once, and its resumption


@pytest.mark.parametrize("stall_s, at_s", [(0.006, 0.8), (0.01, 0.5)])
def test_a_sample_driven_port_makes_the_gap_harmless(stall_s, at_s):
    """The default sim backend hands over every conversion of the gap (as the FIFO accelerometer module does
    through the drivers): the controllers integrate them exactly, and the valves never reach the clamp."""
    loop, cmd, table, floor, suspended = run_stall({"sat_reset_s": 0.0}, 3.0, True, stall_s, at_s)
    assert loop.skipped == round(stall_s / DT)
    assert loop.lc.fault_reason is None
    assert np.max(np.abs(cmd)) < 0.9 * 10.0
    late = slice(int(1.5 * RATE), None)
    assert np.std(table[late]) < 0.6 * np.std(floor[late])

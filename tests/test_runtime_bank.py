"""The loop with the compiled controller bank (controllers/bank.py) behaves and records exactly like the loop
stepping the same IsolationControllers one by one in Python: same commands, same HDF5 rows (the bank writes
measurement, raw commands and states into the recording row itself), through INACTIVE warm-up, activation,
isolation switching, skipped periods (replayed) and a FAULT. Simulated time, real Recorder (HDF5)."""
from __future__ import annotations

import numpy as np
import pytest

from controllers.bank import IsolationBank
from controllers.isolation import make_isolation_controllers
from rig.clock import SimClock
from rig.config import config_from_dict
from rig.lifecycle import State
from rig.loop import Loop, loop_channels
from rig.recorder import Recorder, read_recording
from sim_backend.backend import make_sim_port

RATE = 5000.0
DT = 1.0 / RATE


def run(tmp_path, use_bank: bool, record: bool = True):
    # the loop's own skip-policy counters are kept by loop_run_periods (Loop.run does the same)
    cfg = config_from_dict({"loop": {"overrun_policy": "skip"}})
    clk = SimClock()
    port = make_sim_port(cfg, DT, clock=clk)
    loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clk, rate_hz=RATE, stop_on_fault=False,
                use_bank=use_bank)
    assert (loop.bank is not None) == use_bank
    rec = None
    if record:
        rec = Recorder(tmp_path / f"bank_{use_bank}.h5", loop_channels(loop.n, loop.state_len, loop.names),
                       rate_hz=RATE).start()
        loop.recorder = rec
    port.inject("overrun", at_s=0.05, extra_s=0.0009)        # 4 skipped periods, replayed
    port.inject("nan", at_s=0.35, mount=1, sensor="stroke")  # FAULT: controllers no longer stepped
    loop.configure()
    cmds = []
    for what, n in (("inactive", 100), ("activate", 600), ("iso_off", 400), ("iso_on", 800)):
        if what == "activate":
            loop.request_active(True)
        elif what == "iso_off":
            loop.request_isolation(False)
        elif what == "iso_on":
            loop.request_isolation(True)
        loop_run_periods(loop, clk, n, cmds)
    if rec is not None:
        rec.close()
    return loop, np.array(cmds)


def loop_run_periods(loop, clk, n, cmds):
    """Periods on the simulated clock with the skip policy (as Loop.run), keeping the written commands."""
    P = loop.period_ns
    t = getattr(loop, "_test_t", P)
    for _ in range(n):
        clk.sleep_until(t)
        loop.cycle(t)
        cmds.append(list(loop.cmd))
        t += P
        if clk.now_ns() > t:
            missed = (clk.now_ns() - t) // P + 1
            loop.skipped += missed
            t += missed * P
    loop._test_t = t


def test_bank_loop_equals_python_loop_and_records_the_same_rows(tmp_path):
    lb, cb = run(tmp_path, True)
    lp, cp = run(tmp_path, False)
    assert isinstance(lb.bank, IsolationBank) and lp.bank is None
    assert lb.skipped == lp.skipped == 4
    assert lb.state is lp.state is State.FAULT and lb.lc.fault_reason == lp.lc.fault_reason
    assert np.abs(cb).max() > 0.1                            # it actuated
    np.testing.assert_allclose(cb, cp, rtol=1e-12, atol=1e-12)
    rb = read_recording(tmp_path / "bank_True.h5")
    rp = read_recording(tmp_path / "bank_False.h5")
    assert len(rb["time_s"]) == len(rp["time_s"]) == 1900
    for name in ("time_s", "accel_mps2", "stroke_m", "valve_cmd_V", "valve_cmd_raw_V", "controller_state",
                 "lifecycle_state", "isolation_on", "fault", "skipped_periods", "cmd_limited"):
        np.testing.assert_allclose(rb[name], rp[name], rtol=1e-12, atol=1e-15, err_msg=name)
    # the FAULT rows still carry that period's measurement (NaN stroke of mount 1)
    k = int(np.argmax(rb["fault"] > 0))
    assert np.isnan(rb["stroke_m"][k, 1]) and rb["lifecycle_state"][k] == float(State.FAULT)


def test_loop_takes_a_bank_and_steps_other_controllers_in_python(tmp_path):
    from tests.test_runtime_support import CentringP
    cfg = config_from_dict({})
    clk = SimClock()
    port = make_sim_port(cfg, DT, clock=clk)
    bank = IsolationBank(make_isolation_controllers(cfg, DT))
    loop = Loop(cfg, port, bank, clock=clk, rate_hz=RATE)
    assert loop.bank is bank and len(loop.ctrls) == 4 and loop.states.shape == (4, bank.state_len)
    other = Loop(cfg, make_sim_port(cfg, DT, clock=SimClock()), [CentringP() for _ in range(4)],
                 clock=SimClock(), rate_hz=RATE)
    assert other.bank is None

"""The loop's recording equals the plain-Python reference recomputed from it: the recorded measurement of each
period through the reference isolation law (tests/controllers/reference.py) and command limiter
(tests/rig/reference.py), with the activation, isolation switching and skipped periods (replayed,
interpolated) the recording shows, gives the recorded raw commands, written commands and controller states,
bit for bit; through INACTIVE warm-up, activation, isolation off and on, 4 skipped periods and a FAULT.
Simulated time, the real Recorder (HDF5)."""
from __future__ import annotations

import numpy as np

from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import config_from_dict
from rig.runtime.lifecycle import State
from rig.runtime.loop import Loop
from rig.runtime.recorder import Recorder, read_recording
from sim_backend.backend import make_sim_port
from tests.controllers.reference import isolation_step
from tests.rig.reference import RefCommandLimiter

RATE = 5000.0
DT = 1.0 / RATE


def _run(path):
    cfg = config_from_dict({"loop": {"overrun_policy": "skip"}})
    clk = SimClock()
    port = make_sim_port(cfg, DT, clock=clk, sample_driven=False)      # skipped periods: the loop replays them
    loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clk, rate_hz=RATE, stop_on_fault=False)
    rec = Recorder(path, loop.channels, rate_hz=RATE).start()
    loop.recorder = rec
    port.inject("overrun", at_s=0.05, extra_s=0.0009)        # 4 skipped periods, replayed
    port.inject("nan", at_s=0.35, mount=1, sensor="stroke")  # FAULT: controllers no longer stepped
    loop.configure()
    for what, n in (("inactive", 100), ("activate", 600), ("iso_off", 400), ("iso_on", 800)):
        if what == "activate":
            loop.request_active(True)
        elif what == "iso_off":
            loop.request_isolation(False)
        elif what == "iso_on":
            loop.request_isolation(True)
        _periods(loop, clk, n)
    rec.close()
    return cfg, loop, read_recording(path)


def _periods(loop, clk, n):
    """Periods on the simulated clock with the skip policy (as Loop.run)."""
    P = loop.period_ns
    t = getattr(loop, "_test_t", P)
    for _ in range(n):
        clk.sleep_until(t)
        loop.cycle(t)
        t += P
        if clk.now_ns() > t:
            missed = (clk.now_ns() - t) // P + 1
            loop.skipped += missed
            t += missed * P
    loop._test_t = t


def test_loop_records_what_the_reference_computes(tmp_path):
    cfg, loop, r = _run(tmp_path / "run.h5")
    assert loop.skipped == 4 and loop.state is State.FAULT
    n = len(r["time_s"])
    assert n == 1900 and np.abs(r["valve_cmd_V"]).max() > 0.1             # it actuated
    ctrls = make_isolation_controllers(cfg, DT)
    states = [c.set_enabled(c.initial_state(), False) for c in ctrls]
    lim = RefCommandLimiter(cfg, 4, DT)
    acc, xs, raw_rec = r["accel_mps2"], r["stroke_m"], r["valve_cmd_raw_V"]
    life, iso, skipped = r["lifecycle_state"], r["isolation_on"], r["skipped_periods"]
    raw = [0.0] * 4
    checked = 0
    for k in range(n):
        if life[k] == State.FAULT:
            assert np.all(r["valve_cmd_V"][k] == 0.0)
            assert raw_rec[k].tolist() == raw                               # not stepped: the commands hold
            continue
        if k and life[k] == State.ACTIVE and life[k - 1] == State.INACTIVE:
            states = [c.set_enabled(s, bool(iso[k])) for c, s in zip(ctrls, states)]
            lim.reset()
        elif k and life[k] == State.ACTIVE and iso[k] != iso[k - 1]:
            states = [c.set_enabled(s, bool(iso[k])) for c, s in zip(ctrls, states)]
        miss = int(skipped[k] - skipped[k - 1]) if k else 0
        for j in range(miss):                                               # replayed, interpolated
            f = (j + 1) / (miss + 1)
            for i, c in enumerate(ctrls):
                isolation_step(c, states[i], (acc[k - 1, i] + f * (acc[k, i] - acc[k - 1, i]),
                                              xs[k - 1, i] + f * (xs[k, i] - xs[k - 1, i])), DT)
        for i, c in enumerate(ctrls):
            raw[i], states[i] = isolation_step(c, states[i], (float(acc[k, i]), float(xs[k, i])), DT)
        cmd = [0.0] * 4
        if life[k] == State.ACTIVE:
            assert lim.limit(raw, cmd) is None
        assert raw_rec[k].tolist() == raw, k
        assert r["valve_cmd_V"][k].tolist() == cmd, k
        assert r["controller_state"][k].tolist() == [x for s in states for x in s], k
        checked += 1
    assert checked == int(np.argmax(life == State.FAULT))                   # every period up to the fault
    assert r["lifecycle_state"][100] == State.ACTIVE and (np.diff(iso) != 0).sum() == 2 and skipped[-1] == 4
    k = int(np.argmax(r["fault"] > 0))                                      # the FAULT row: its measurement
    assert np.isnan(r["stroke_m"][k, 1]) and life[k] == float(State.FAULT)

"""The floor feedforward in the runtime: the kernel's fourth per-mount input and its feedforward path computed
as the plain reference computes them (controller + feedforward, with replayed and older conversions), the
floor accelerometers checked like the other sensors, the modes off / feedback / feedback_feedforward switched
through the gate's requests without a jump and recorded, a loop that cannot have the feedforward refused at
construction, and the result on the simulated rig over the same floor: the feedforward adds what the linear
design predicts, also with the plant's actuators 10 % off the model."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.signal

from controllers.feedforward import make_feedforward_filters
from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import MOUNTS, Config, config_from_dict
from rig.errors import ConfigError, RigError
from rig.runtime.kernel import MODE_ACTIVE, PeriodKernel
from rig.runtime.lifecycle import State
from rig.port import Measurements
from rig.runtime.recorder import read_recording
from rig.runtime.safety import CHECK_FLOOR
from rig.runtime.session import Session
from tests.controllers.reference import feedforward_step, isolation_step

DT = 1.0 / 5000
FLOOR = Config().replace(sensors=dataclasses.replace(Config().sensors, floor_accel=True))


def _kernel(cfg=FLOOR):
    ctrls = make_isolation_controllers(cfg, DT)
    ffs = make_feedforward_filters(cfg, DT)
    return PeriodKernel(cfg, ctrls, MOUNTS, DT, 50, ffs), ctrls, ffs


def test_kernel_runs_controller_plus_feedforward_like_the_reference():
    """Raw command = isolation law + feedforward law per mount, bit for bit with the references, through
    periods with older conversions (mount then floor values each) and replayed skipped periods (interpolated
    floor too); the row records the floor input, the feedforward's part and its switch."""
    k, ctrls, ffs = _kernel()
    k.set_enabled(True)
    k.set_feedforward(True)
    states = [c.set_enabled(c.set_enabled(c.initial_state(), False), True) for c in ctrls]
    fst = [f.set_enabled(f.initial_state(on=False), True).tolist() for f in ffs]
    lay, row = k.layout, k.row
    rr, rf, rg = lay["valve_cmd_raw_V"], lay["ff_cmd_V"], lay["floor_accel_mps2"]
    rng = np.random.default_rng(5)
    prev = None

    def ref_step(i, a, x, g):
        u, states[i] = isolation_step(ctrls[i], states[i], (a, x), DT)
        return u + feedforward_step(ffs[i], fst[i], g)
    for p in range(300):
        a = (1e-3 * rng.standard_normal(4)).tolist()
        x = (1e-7 * rng.standard_normal(4)).tolist()
        g = (2e-3 * rng.standard_normal(4)).tolist()
        older, miss = (), 0
        if p % 37 == 5:                                          # a sample-driven port hands over two more
            older = tuple(tuple((1e-3 * rng.standard_normal(8)).tolist()) for _ in range(2))
        elif p % 41 == 7:
            miss = 3                                             # three skipped periods, replayed
        m = Measurements(p * 200_000, a, x, [p * 200_000] * 4, floor_accel_mps2=g, accel_older=older,
                         new_samples=(1 + len(older)) if older else None)
        code = k.period(m, p * 200_000, p * DT, 0.0, 0.0, MODE_ACTIVE, miss)
        assert code in (0, 500)                                 # (a random walk may reach the clamp: latched)
        for j in range(miss):
            f = (j + 1) / (miss + 1)
            for i in range(4):
                ref_step(i, prev[0][i] + f * (a[i] - prev[0][i]), prev[1][i] + f * (x[i] - prev[1][i]),
                         prev[2][i] + f * (g[i] - prev[2][i]))
        for j, o in enumerate(older):                         # the stroke interpolated across them
            f = (j + 1) / (len(older) + 1)
            for i in range(4):
                ref_step(i, o[i], prev[1][i] + f * (x[i] - prev[1][i]), o[4 + i])
        ff = [feedforward_step(ffs[i], fst[i], g[i]) for i in range(4)]
        raw = []
        for i in range(4):
            u, states[i] = isolation_step(ctrls[i], states[i], (a[i], x[i]), DT)
            raw.append(u + ff[i])
        assert row[rr:rr + 4].tolist() == raw, p
        assert row[rf:rf + 4].tolist() == ff, p
        assert row[rg:rg + 4].tolist() == g and row[lay["feedforward_on"]] == 1.0
        assert [s.tolist() for s in k.ff_states] == fst
        prev = (a, x, g)
    assert max(abs(v) for v in row[rf:rf + 4]) > 0.0


def test_a_bad_floor_accelerometer_faults_naming_it():
    with Session(FLOOR, "sim", clock=SimClock()) as s:
        s.port.inject("nan", mount=2, sensor="floor", at_s=0.01)
        s.loop.activate()
        for p in range(100):
            s.loop.cycle(p * s.loop.period_ns)
        assert s.loop.state is State.FAULT
        assert s.loop.lc.fault_reason == ("rear_left: floor accelerometer implausible: nan m/s^2 (NaN or outside "
                                          "+-5 m/s^2, [sensors] floor_range_mps2)")
    k, _, _ = _kernel()
    m = Measurements(0, [0.0] * 4, [0.0] * 4, [0] * 4, floor_accel_mps2=[0.0, 6.0, 0.0, 0.0])
    assert k.period(m, 0, 0.0, 0.0, 0.0, MODE_ACTIVE, 0) == CHECK_FLOOR + 1


def test_modes_switch_through_the_gate_without_a_jump_and_are_recorded(tmp_path):
    """off -> feedback -> feedback_feedforward -> feedback -> off, requested from the gate: the feedforward's
    command fades in and out (no step larger than the fade allows), the recording has the switch, the floor
    input, the feedforward's part and the isolation mode events."""
    path = tmp_path / "modes.h5"
    with Session(FLOOR, "sim", clock=SimClock(), isolation=False, record=path) as s:
        lp = s.loop
        lp.activate()
        p = 0
        for mode in ("off", "feedback", "feedback_feedforward", "feedback", "off"):
            s.request_isolation_mode(mode)
            for _ in range(2500):
                lp.cycle(p * lp.period_ns)
                p += 1
            assert lp.isolation_mode == mode and s.snapshot()["isolation_mode"] == mode
    r = read_recording(path)
    on, ff = r["feedforward_on"], r["ff_cmd_V"]
    assert on[:5000].max() == 0 and on[5000:7500].min() == 1 and on[7500:].max() == 0
    assert np.all(ff[:5000] == 0.0) and np.abs(ff[5000:7500]).max() > 0.05
    fade = make_feedforward_filters(FLOOR, DT)[0].fade
    steady, rate = np.abs(ff[6500:7500]).max(), np.abs(np.diff(ff[6500:7500], axis=0)).max()
    jump = 3 * (1 - fade) * steady                     # what the gain's change of one period can add at most
    assert np.abs(np.diff(ff[4990:5020], axis=0)).max() < jump                # fades in from 0
    assert np.abs(np.diff(ff[7490:7520], axis=0)).max() < rate + jump         # and out: no step
    assert np.abs(ff[-1]).max() < 1e-4 * steady                              # e^-10 after 10 fade_s
    assert np.abs(r["floor_accel_mps2"]).max() > 1e-3
    events = [text for _, text in r["events"]]
    assert [e for e in events if e.startswith("isolation mode")] == [
        "isolation mode feedback", "isolation mode feedback_feedforward", "isolation mode feedback",
        "isolation mode off"]


def test_feedforward_needs_floor_accelerometers():
    with pytest.raises(ConfigError, match="sensors.floor_accel = true"):
        Session(Config(), "sim", clock=SimClock(), feedforward=True)
    with Session(Config(), "sim", clock=SimClock()) as s:
        assert "floor_accel_mps2" not in s.loop.kernel.layout          # the loop as without the feedforward
        with pytest.raises(ValueError, match="no floor feedforward"):
            s.request_isolation_mode("feedback_feedforward")
        with pytest.raises(ValueError, match="expected one of off, feedback, feedback_feedforward"):
            s.request_isolation_mode("on")


def test_isolation_mode_and_operating_modes_are_separate_requests():
    """The machine's isolation mode (request_isolation_mode, control words feedback / feedback_feedforward) and
    a stand's operating modes (request_mode): each refused where it does not apply, neither taken for the other."""
    with Session(FLOOR, "sim", clock=SimClock(), isolation=False) as s:
        lp = s.loop
        lp.activate()
        assert s.control("feedback_feedforward", "test")
        lp.cycle(0)
        assert lp.isolation_mode == "feedback_feedforward" and lp.kernel.feedforward_enabled()
        with pytest.raises(RigError, match="no operating modes"):
            s.request_mode("hold")
        assert not s.control("hold 5um", "test")                    # refused, in one line
    stand = config_from_dict({"layout": {"plant": "stand"}})
    with Session(stand, "sim", clock=SimClock()) as s:
        assert s.loop.kernel.nf == 0
        with pytest.raises(ValueError, match="no floor feedforward"):
            s.request_isolation_mode("feedback_feedforward")
        assert not s.control("feedback_feedforward", "test")        # a stand reads it as a mode request: refused


def test_sensors_config_errors_are_one_line():
    for bad, words in (({"floor_channels": [4, 5, 6]}, "sensors.floor_channels: expected a list of 4"),
                       ({"floor_channels": [4, 5, 5, 7]}, "sensors.floor_channels: expected 4 distinct"),
                       ({"floor_channels": [2, 5, 6, 7]}, r"expected >= 4, got 2 in \[2, 5, 6, 7\]"),
                       ({"floor_channels": [4, 5, 6, 7.0]}, "expected a list of integers"),
                       ({"floor_range_mps2": 8.0}, "sensors.floor_range_mps2: expected <= 10 V"),
                       ({"floor_noise_mps2_per_rthz": -1.0}, "expected >= 0")):
        with pytest.raises(ConfigError, match=words):
            config_from_dict({"sensors": bad})
    with pytest.raises(ConfigError, match="plant_error.K_Q: expected >= 0.5"):
        config_from_dict({"plant_error": {"K_Q": 0.0}})


def _table_1_100hz(cfg, mode, n):
    with Session(cfg, "sim", clock=SimClock(), isolation=mode != "off",
                 feedforward=mode == "feedback_feedforward") as s:
        s.loop.activate()
        x = np.empty(n)
        for p in range(n):
            s.loop.cycle(p * s.loop.period_ns)
            x[p] = s.port.plant.table_m
        assert s.loop.state is State.ACTIVE and s.loop.limiter.clamped == 0
    sos = scipy.signal.butter(4, (1.0, 100.0), btype="bandpass", fs=1 / DT, output="sos")
    return float(np.std(scipy.signal.sosfiltfilt(sos, x[5000:])))


@pytest.mark.slow
def test_feedforward_on_the_simulated_rig_with_the_actuators_off_the_model():
    """Three runs over the same floor, the plant's actuators in the worst +-10 % corner for the feedforward:
    feedback >= 12 dB and feedback + feedforward >= 20 dB on the table in 1-100 Hz (the issue's targets), and
    within 2 dB of the linear prediction for that plant."""
    from controllers.analysis import worst_model_error
    fac, predicted = worst_model_error(FLOOR, DT, make_isolation_controllers(FLOOR, DT),
                                       make_feedforward_filters(FLOOR, DT))
    assert all(abs(x - 1) == pytest.approx(0.1) for x in fac.values())
    cfg = FLOOR.replace(plant_error=dataclasses.replace(FLOOR.plant_error, **fac))
    n = int(4.0 / DT)
    off, fb, both = (_table_1_100hz(cfg, m, n) for m in ("off", "feedback", "feedback_feedforward"))
    fb_db, both_db = 20 * math.log10(off / fb), 20 * math.log10(off / both)
    assert fb_db >= 12.0 and both_db >= 20.0, (fb_db, both_db)
    assert both_db == pytest.approx(predicted, abs=2.0)


def test_floor_accelerometers_without_the_feedforward():
    """A port with floor accelerometers under controllers that take no feedforward (another kind): the loop
    runs as without them (the floor values are not handed to the kernel), also over older conversions."""
    from tests.rig.support import CentringP
    with Session(FLOOR, "sim", clock=SimClock(), controllers=[CentringP() for _ in range(4)]) as s:
        assert s.port.floor_sensors and s.loop.kernel.nf == 0
        s.loop.activate()
        p = 0
        for _ in range(200):
            s.loop.cycle(p * s.loop.period_ns)
            p += 3 if p % 50 == 0 else 1                   # skipped periods: older conversions handed over
        assert s.loop.state is State.ACTIVE


def test_record_floor_records_the_floor_with_any_controllers_and_leaves_their_commands_alone(tmp_path):
    """`rig commission`'s open-loop playback with the floor accelerometers recorded (record_floor): the floor in
    the recording as the port read it, the commands the playback's own to the bit (the feedforward's filters run
    switched off, and cannot be switched on); the same run without it records no floor (nothing else changes)."""
    from controllers.playback import SignalPlayback
    sig = list(np.sin(np.arange(400) * 0.05))

    def run(path, **kw):
        ctrls = [SignalPlayback(sig, DT, name=m) for m in MOUNTS]
        with Session(FLOOR, "sim", clock=SimClock(), controllers=ctrls, record=path, **kw) as s:
            s.run(iterations=600, activate_after_s=0.02)
            if kw:
                with pytest.raises(ValueError, match="feedforward runs with isolation controllers only"):
                    s.request_isolation_mode("feedback_feedforward")
                assert not s.control("feedback_feedforward", "test")          # refused in one line
        return read_recording(path)

    with_floor, without = run(tmp_path / "floor.h5", record_floor=True), run(tmp_path / "plain.h5")
    assert "floor_accel_mps2" not in without
    floor = np.asarray(with_floor["floor_accel_mps2"])
    assert floor.shape == (600, 4) and np.all(floor.std(axis=0) > 0)          # each mount's floor, moving
    assert np.array_equal(with_floor["valve_cmd_V"], without["valve_cmd_V"])    # the playback's commands alone
    assert np.abs(with_floor["valve_cmd_V"]).max() > 0.5 and not np.any(with_floor["ff_cmd_V"])
    with pytest.raises(ConfigError, match="recording the floor needs floor accelerometers"):
        Session(Config(), "sim", clock=SimClock(), record_floor=True)

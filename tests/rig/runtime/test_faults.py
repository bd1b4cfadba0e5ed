"""Each fault knob of the simulated backend -> FAULT within one period of becoming detectable, valve at
null via safe_state, the reason logged once. Simulated time (SimClock), the real SimBackend and Loop."""
from __future__ import annotations

import logging
import math

import pytest

from rig.runtime.clock import SimClock
from rig.config import Config, config_from_dict
from rig.runtime.lifecycle import State
from controllers.playback import SignalPlayback
from rig.runtime.loop import Loop
from sim_backend.backend import SimBackend
from tests.rig.support import CentringP, TinyPlant

RATE = 5000.0
DT = 1.0 / RATE
K0 = 500                     # the knob acts from period 500 (0.1 s)


def run_with(knob: dict, cfg: Config | None = None, periods: int = 1200):
    cfg = cfg or Config()
    clk = SimClock(t0_ns=123_456_789)
    port = SimBackend(TinyPlant(4, DT), DT, clock=clk)
    loop = Loop(cfg, port, [CentringP(2e5) for _ in range(4)], clock=clk, rate_hz=RATE, stop_on_fault=False)
    loop.configure()
    loop.activate()
    port.inject(at_s=K0 * DT, **knob)
    loop.run(iterations=periods)
    k_fault = None if loop.fault_t_ns is None else (loop.fault_t_ns - loop.t0_ns) // loop.period_ns
    return loop, port, k_fault


def _expected_stale_period(cfg: Config) -> int:
    # a dropped sample keeps the time stamp of period K0-1: age at K0+j is (j+1) periods
    stale_ns = round(cfg.safety.stale_s * 1e9)
    j = 0
    while (j + 1) * round(DT * 1e9) <= stale_ns:
        j += 1
    return K0 + j


CASES = [
    ("nan accel", {"kind": "nan", "mount": 2, "sensor": "accel"}, lambda c: K0, "rear_left: accelerometer"),
    ("nan stroke", {"kind": "nan", "mount": 1, "sensor": "stroke"}, lambda c: K0, "front_right: displacement"),
    ("out of range", {"kind": "range", "mount": 0, "sensor": "accel", "value": 1e3}, lambda c: K0, "implausible"),
    ("stroke limit", {"kind": "range", "mount": 3, "sensor": "stroke", "value": 0.95e-3}, lambda c: K0,
     "stroke limit"),
    ("stale", {"kind": "stale", "mount": 1, "age_s": 0.01}, lambda c: K0, "stale sample"),
    ("dropped", {"kind": "drop", "mount": 0}, _expected_stale_period, "stale sample"),
    ("stuck", {"kind": "stuck", "mount": 2, "sensor": "accel"}, lambda c: K0 + c.safety.stuck_samples,
     "accelerometer stuck"),
    ("device", {"kind": "device", "mount": 3}, lambda c: K0, "device fault"),
    # a stall of 3 watchdog limits inside period K0: caught at the first wake after it
    ("overrun", {"kind": "overrun", "extra_s": 0.15}, lambda c: K0 + 1 + math.ceil(0.15 / DT),
     "between periods (limit watchdog_s = 50 ms)"),
]


@pytest.mark.parametrize("name,knob,expect,words", CASES, ids=[c[0] for c in CASES])
def test_fault_knob_faults_within_one_period(name, knob, expect, words, caplog):
    cfg = config_from_dict({"loop": {"overrun_policy": "skip"}})   # period indices count skipped deadlines
    with caplog.at_level(logging.INFO):
        loop, port, k_fault = run_with(knob, cfg)
    assert loop.state is State.FAULT
    assert k_fault is not None and k_fault == expect(cfg), (k_fault, expect(cfg))
    assert words in loop.lc.fault_reason
    # valve at null: safe_state called once, nothing written after it
    assert port.safe_calls >= 1 and port.last_written == [0.0] * 4
    assert loop.cmd == [0.0] * 4
    # the reason logged exactly once although the condition persisted for hundreds of periods
    faults = [r for r in caplog.records if r.levelno >= logging.ERROR and "FAULT" in r.getMessage()]
    assert len(faults) == 1 and words in faults[0].getMessage()


def test_no_fault_without_knobs_and_before_the_knob():
    loop, port, k = run_with({"kind": "nan", "mount": 0}, periods=K0)   # stops just before the knob
    assert loop.state is State.INACTIVE and k is None and loop.lc.fault_reason is None
    assert port.safe_calls == 1                                          # only the stop's own safe state


def test_short_overrun_counts_and_skip_policy_jumps_ahead():
    # 0.7 ms stall: below the watchdog, so no fault; the late period is counted, 3 deadlines are skipped
    cfg = config_from_dict({"loop": {"overrun_policy": "skip"}})
    loop, port, k = run_with({"kind": "overrun", "extra_s": 0.0007}, cfg=cfg, periods=1000)
    assert k is None and loop.lc.fault_reason is None
    assert loop.overruns == 1 and loop.skipped == 3
    assert loop.iterations == 1000
    assert loop.missed_deadline_fraction == pytest.approx(4 / 1003)


def test_skipped_periods_still_pass_through_the_controllers():
    # the controllers' filters integrate over time: a skipped period must still be a step for them. A playback
    # controller counts its steps in its `sample` state (an empty table: it writes null all along)
    cfg = config_from_dict({"loop": {"overrun_policy": "skip"}})
    clk = SimClock(t0_ns=123_456_789)
    port = SimBackend(TinyPlant(4, DT), DT, clock=clk)
    ctrls = [SignalPlayback([], DT) for _ in range(4)]
    loop = Loop(cfg, port, ctrls, clock=clk, rate_hz=RATE, stop_on_fault=False)
    loop.configure()
    loop.activate()
    port.inject(at_s=K0 * DT, kind="overrun", extra_s=0.0007)
    loop.run(iterations=1000)
    assert loop.skipped == 3
    # every ACTIVE period and skipped one is a step; the last period is the stop's, INACTIVE (playback holds)
    assert all(int(st[0]) == loop.iterations - 1 + loop.skipped for st in loop.states)


def test_catch_up_policy_runs_late_periods_back_to_back():
    cfg = config_from_dict({"loop": {"overrun_policy": "catch_up"}})
    loop, port, k = run_with({"kind": "overrun", "extra_s": 0.0007}, cfg, periods=1000)
    assert k is None and loop.skipped == 0
    # a 3.5-period stall in period 500: it and the late periods 501, 502 end past their deadlines; 503,
    # run back to back too, ends at 503.5 periods, inside its own period
    assert loop.overruns == 3
    assert port._k == 999                    # the plant took exactly one step per period: nothing skipped


def test_nan_controller_output_faults():
    clk = SimClock()
    port = SimBackend(TinyPlant(4, DT), DT, clock=clk)
    ctrls = [CentringP(), CentringP(), CentringP(math.nan), CentringP()]     # mount 2's law gives NaN
    loop = Loop(Config(), port, ctrls, clock=clk, rate_hz=RATE)
    loop.configure()
    loop.activate()
    reason = loop.run(iterations=10)
    assert reason == "fault" and "controller 2: valve command is NaN" in loop.lc.fault_reason
    assert port.last_written == [0.0] * 4 and port.writes == 0


def test_watchdog_thread_nulls_valve_when_the_loop_hangs():
    """Real clock: a port read that blocks for 0.3 s; the watchdog thread calls safe_state meanwhile."""
    import threading
    import time

    from rig.runtime.clock import MonotonicClock

    cfg = config_from_dict({"safety": {"watchdog_s": 0.05}})
    clk = MonotonicClock()
    port = SimBackend(TinyPlant(4, 1e-3), 1e-3, clock=clk)
    ctrls = [CentringP(dt=1e-3) for _ in range(4)]
    hang = threading.Event()
    seen = {}

    def slow_update(t_ns, _orig=port.update):
        if hang.is_set():
            hang.clear()
            calls = port.safe_calls
            time.sleep(0.3)
            seen["safe_calls_during_hang"] = port.safe_calls - calls
        return _orig(t_ns)

    port.update = slow_update
    loop = Loop(cfg, port, ctrls, clock=clk, rate_hz=1000.0)
    loop.configure()
    loop.activate()
    threading.Timer(0.1, hang.set).start()
    reason = loop.run(seconds=1.0)
    assert seen["safe_calls_during_hang"] == 1          # the valve went to null while the loop hung
    assert reason == "fault" and "(limit watchdog_s = 50 ms)" in loop.lc.fault_reason


@pytest.mark.parametrize("sensor, unit", [("accel", "m/s^2"), ("stroke", "mm")])
def test_a_stuck_sensors_value_is_given_with_four_significant_digits_and_its_unit(sensor, unit):
    """`stuck at -0.009416967953903963 m/s^2` was a float's repr: the text says -0.009417 m/s^2."""
    import re
    loop, _, _ = run_with({"kind": "stuck", "mount": 2, "sensor": sensor}, config_from_dict({}))
    m = re.search(r"stuck at (\S+) (\S+) for \d+ samples$", loop.lc.fault_reason)
    assert m and m.group(2) == unit, loop.lc.fault_reason
    mantissa = m.group(1).lstrip("-").split("e")[0].replace(".", "").lstrip("0")
    assert 1 <= len(mantissa) <= 4, loop.lc.fault_reason
    float(m.group(1))                                   # a number, not a repr of something else

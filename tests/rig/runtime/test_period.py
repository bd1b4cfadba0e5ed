"""The period kernel's rules (rig/runtime/safety.py check_sensors and limit_commands, compiled) decide exactly as the
plain-Python references (tests/rig/reference.py) for any sequence: the same fault text on the same period,
the same counters; and the loop records every period, with its faults, also when the ring is full."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import Config, SafetyConfig
from rig.runtime.loop import Loop
from rig.port import Measurements
from rig.runtime.safety import CommandLimiter, SensorCheck, check_sensors, limit_commands
from sim_backend.backend import make_sim_port
from tests.rig.reference import RefCommandLimiter, RefSensorCheck
from tests.rig.support import ReadWritePort
P = 200_000
CFG = Config(safety=SafetyConfig(stuck_samples=3, saturation_s=3 * P * 1e-9))
STALE_PERIODS = round(CFG.safety.stale_s * 1e9) // P
# mostly plausible mounts with values from a small set (so repeats, i.e. stuck counting, are common), now and
# then an implausible one: out of range, NaN, inf, or a time stamp at and beyond the staleness limit
OK_A, OK_X = st.sampled_from([0.0, 1e-3, -2e-3]), st.sampled_from([0.0, 1e-6, 3e-6])
GOOD = st.tuples(OK_A, OK_X, st.sampled_from([0] * 8 + [1]))
BAD = st.one_of(st.tuples(st.sampled_from([1e3, -1e3, math.nan, math.inf]), OK_X, st.just(0)),
                st.tuples(OK_A, st.sampled_from([1.0, math.nan, -math.inf]), st.just(0)),
                st.tuples(OK_A, OK_X, st.sampled_from([STALE_PERIODS, STALE_PERIODS + 1])))
PERIOD = st.lists(st.one_of(*[GOOD] * 100, BAD), min_size=4, max_size=4)
COMMAND = st.sampled_from([0.0, 0.5, -0.5, 1.9, 2.0, 9.99, 10.0, 12.0, -10.0, -30.0, math.nan, 0.5])


HELD = [[(0.0, 0.0, 0)] * 4] + [[(0.0, 0.0, 1)] * 4] * 3 + [[(1e-3, 1e-6, 0)] * 4] * 16   # a held sample repeats


@pytest.mark.slow
@settings(max_examples=400, deadline=None)
@given(st.lists(PERIOD, min_size=20, max_size=60))
@example(HELD)
def test_compiled_check_decides_like_the_reference(periods):
    ref, chk = RefSensorCheck(CFG, 4), SensorCheck(CFG, 4)
    state, lim = chk.initial_state(), np.array(chk.limits() + (0.0, 0.0, 0.0))
    for k, period in enumerate(periods):
        t = (k + 20_000) * P
        m = Measurements(t, [p[0] for p in period], [p[1] for p in period], [t - p[2] * P for p in period])
        want = ref.check(m, t)
        code = check_sensors(state, lim, np.array(m.accel_mps2), np.array(m.stroke_m),
                             np.array(m.sample_t_ns, dtype=float), np.array(m.sample_t_ns, dtype=float), float(t))
        got = chk.reason(code, state, m.accel_mps2, m.stroke_m, m.sample_t_ns, t) if code else None
        assert got == want, (k, period)
        if want is not None:
            break
        assert state[3].tolist() == ref._same_a and state[4].tolist() == ref._same_x


@pytest.mark.slow
@settings(max_examples=400, deadline=None)
@given(st.lists(st.lists(COMMAND, min_size=4, max_size=4), min_size=1, max_size=30),
       st.lists(st.integers(0, 29), max_size=3))
def test_compiled_limiter_decides_like_the_reference(raws, resets):
    dt = 1e-3
    cfg = Config(safety=SafetyConfig(slew_V_per_s=2e3, saturation_s=3e-3))   # 2 V per period, 3 at the clamp
    ref = RefCommandLimiter(cfg, 4, dt)
    lim_b = CommandLimiter(cfg, 4, dt)
    last, flags = np.zeros(4), np.zeros(3)
    lim_b.view(last, flags)
    lim = np.array((0.0,) * 4 + lim_b.limits())
    for k, raw in enumerate(raws):
        if k in resets:
            ref.reset()
            last[:] = 0.0
            flags[0] = 0.0
        out_r, out_k = [0.0] * 4, np.zeros(4)
        want = ref.limit(raw, out_r)
        code = limit_commands(last, flags, lim, np.array(raw), out_k)
        assert (lim_b.reason(code) if code else None) == want, (k, raw)
        if want is not None:
            break
        assert out_k.tolist() == out_r
        assert (lim_b.last, lim_b.sat_run, lim_b.clamped, lim_b.limited) == (ref.last, ref.sat_run, ref.clamped,
                                                                            ref.limited)


DT = 2e-4


def _sim_loop(knobs=()):
    """A four-mount loop on the simulated rig in simulated time."""
    cfg = Config()
    clock = SimClock()
    port = make_sim_port(cfg, DT, clock=clock)
    for knob in knobs:
        port.inject(**knob)
    loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clock, rate_hz=1 / DT, watchdog_thread=False)
    return loop, port


def _run(inject=None):
    loop, port = _sim_loop([inject] if inject else ())
    written = []
    port.commit = lambda t: written.extend([port.last_written] * (port.writes - len(written)))
    port.written = written
    loop = Loop(loop.cfg, port, loop.ctrls, clock=loop.clock, rate_hz=1 / DT, watchdog_thread=False)
    loop.run(iterations=3000, activate_after_s=0.02)
    return loop, port


def test_loop_writes_every_period_and_the_stop_null():
    lk, pk = _run()
    assert lk.iterations == 3000 and lk.lc.fault_reason is None
    wk = np.array(pk.written)
    assert wk.shape == (3001, 4)                               # every period wrote, and the stop's null
    assert np.all(wk[:100] == 0.0) and np.all(wk[-1] == 0.0)   # INACTIVE, then the safe stop
    assert np.abs(wk).max() > 1e-3                             # the controllers were really acting


@pytest.mark.parametrize("knob, words, after", [
    (dict(kind="nan", mount=1, at_s=0.3), "front_right: accelerometer implausible", 0),
    (dict(kind="stuck", mount=3, sensor="stroke", at_s=0.3), "rear_right: displacement transducer stuck", 250),
    (dict(kind="stale", mount=2, at_s=0.3, age_s=0.01), "rear_left: stale sample", 0)])
def test_loop_faults_on_the_period_the_rule_sees(knob, words, after):
    loop, port = _run(knob)
    assert words in loop.lc.fault_reason
    assert (loop.fault_t_ns - loop.t0_ns) // loop.period_ns == round(0.3 / DT) + after
    assert port.last_written == [0.0] * 4 and port.safe_calls >= 1


def _recorded(tmp_path, inject=(), ring_s=2.0):
    from rig.runtime.recorder import Recorder, read_recording
    loop, port = _sim_loop(inject)
    path = tmp_path / "run.h5"
    rec = Recorder(path, loop.channels, rate_hz=1 / DT, ring_s=ring_s).start()
    loop.recorder = rec
    loop.run(iterations=2500, activate_after_s=0.1)
    rec.close()
    return read_recording(path)


def test_kernel_records_every_period_with_its_fault(tmp_path):
    """Rows written into the ring by the kernel: INACTIVE (null), the activation, ACTIVE, and the fault period
    (recorded by the loop itself, with the fault flag and null commands)."""
    knobs = (dict(kind="range", mount=0, sensor="stroke", at_s=0.4),
             dict(kind="overrun", extra_s=3e-5, every=True))         # 30 us of compute in every read
    rk = _recorded(tmp_path, knobs)
    assert len(rk["time_s"]) == 2001                                  # 0.4 s, then the fault stops the run
    assert np.allclose(rk["time_s"], np.arange(2001) * DT, rtol=0, atol=1e-12)
    state = rk["lifecycle_state"]
    assert state[0] == 1 and state[600] == 2 and state[-1] == 3          # INACTIVE, ACTIVE, FAULT
    assert np.all(rk["valve_cmd_V"][:400] == 0.0) and np.abs(rk["valve_cmd_V"][600:-1]).max() > 1e-3
    assert np.all(rk["valve_cmd_V"][-1] == 0.0) and rk["fault"][-1] == 1 and rk["fault"][-2] == 0
    assert rk["stroke_m"][-1, 0] == 1e3                                # the fault period's own measurement
    assert [e[1] for e in rk["events"]][-1].startswith("FAULT: front_left: displacement transducer implausible")
    assert np.all(rk["compute_prev_us"][1:] >= 30.0) and np.all(rk["wake_latency_us"] == 0.0)


def test_full_ring_drops_rows_and_counts_each_once(tmp_path):
    """The writer stopped (SIGSTOP) so nothing drains: the ring fills, later rows are dropped and counted once
    each, and the rows kept are the first ones."""
    import signal

    from rig.runtime.recorder import Recorder, read_recording
    loop, port = _sim_loop()
    path = tmp_path / "full.h5"
    rec = Recorder(path, loop.channels, rate_hz=1 / DT, ring_s=0.0).start()     # the smallest ring: 4096 rows
    cap = rec._cap
    rec._proc.send_signal(signal.SIGSTOP)
    try:
        loop.recorder = rec
        loop.run(iterations=cap + 300, activate_after_s=0.01)
    finally:
        rec._proc.send_signal(signal.SIGCONT)
    dropped = rec.dropped_rows
    rec.close()
    r = read_recording(path)
    assert len(r["time_s"]) == cap and dropped == 300 and r["attrs"].get("dropped_rows") == 300
    assert abs(r["time_s"][-1] - (cap - 1) * DT) < 1e-9


def test_a_malformed_measurement_faults():
    """A driver bug (a sensor value None) is a fault in that period with the valves at null, never a dead
    loop: the kernel's entry takes the values as floats, so the None is a TypeError at the call."""
    sim = _sim_loop()[1]
    port = ReadWritePort(sim)                     # a port that only reads: its values reach the kernel as given
    read = sim.read

    def bad_read(t_ns):
        m = read(t_ns)
        if t_ns - sim._t0_ns >= int(0.05e9):
            m.accel_mps2 = [m.accel_mps2[0], m.accel_mps2[1], None, m.accel_mps2[3]]
        return m
    port.read = bad_read
    loop = Loop(Config(), port, make_isolation_controllers(Config(), DT), clock=sim.clock, rate_hz=1 / DT,
                watchdog_thread=False)
    assert loop.run(iterations=2000, activate_after_s=0.01) == "fault"
    assert "malformed measurement" in loop.lc.fault_reason and "TypeError" in loop.lc.fault_reason
    assert sim.last_written == [0.0] * 4
    assert abs(loop.fault_t_ns - sim._t0_ns - int(0.05e9)) < int(DT * 1e9)


def test_kernel_writes_the_ring_after_a_first_period_recorded_by_the_loop(tmp_path):
    """The first recorded period is a fault period (the loop records it itself); after the fault is reset the
    kernel must still write its rows into the ring directly, and every period is in the file."""
    from rig.runtime.recorder import Recorder, read_recording
    loop, port = _sim_loop([dict(kind="device", at_s=0.0)])
    loop.stop_on_fault = False
    path = tmp_path / "first_fault.h5"
    rec = Recorder(path, loop.channels, rate_hz=1 / DT).start()
    loop.recorder = rec
    loop.run(iterations=5)
    assert loop.lc.fault_reason and "device fault" in loop.lc.fault_reason
    port.clear_faults()
    loop.reset_fault()
    loop.stop_reason = None
    by_python = []
    close = loop.tap.close
    loop.tap.close = lambda written: (by_python.append(written), close(written))
    loop.run(iterations=500, activate_after_s=0.01)
    assert loop.tap.ring is rec.ring_rows()            # the ring is bound for the kernel
    assert by_python == [] and rec.committed == 505    # the kernel recorded each period; the last published
    rec.close()
    r = read_recording(path)
    assert len(r["time_s"]) == 505 and r["fault"][:5].tolist() == [1.0] * 5 and r["lifecycle_state"][-2] == 2
    assert r["lifecycle_state"][-1] == 1 and np.all(r["valve_cmd_V"][-1] == 0.0)     # the stop period

"""The compiled period (rig/period.py) must decide exactly as the Python stages it stands for: KernelCheck as
SensorCheck and KernelLimiter as CommandLimiter (same fault texts on the same period, same counters), for any
sequence; and a loop run on the compiled path as one on the stage-by-stage path."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from controllers.isolation import make_isolation_controllers
from rig.clock import SimClock
from rig.config import Config, SafetyConfig
from rig.loop import Loop
from rig.period import KernelCheck, KernelLimiter
from rig.port import Measurements
from rig.safety import CommandLimiter, SensorCheck
from sim_backend.backend import make_sim_port

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


@settings(max_examples=400, deadline=None)
@given(st.lists(PERIOD, min_size=20, max_size=60))
@example(HELD)
def test_kernel_check_decides_like_sensor_check(periods):
    ref, ker = SensorCheck(CFG, 4), KernelCheck(CFG, 4)
    for k, period in enumerate(periods):
        t = (k + 20_000) * P
        m = Measurements(t, [p[0] for p in period], [p[1] for p in period], [t - p[2] * P for p in period])
        want, got = ref.check(m, t), ker.check(m, t)
        assert got == want, (k, period)
        if want is not None:
            break
        n = 4
        assert ker.sv[3 * n:4 * n].tolist() == ref._same_a and ker.sv[4 * n:5 * n].tolist() == ref._same_x


@settings(max_examples=400, deadline=None)
@given(st.lists(st.lists(COMMAND, min_size=4, max_size=4), min_size=1, max_size=30),
       st.lists(st.integers(0, 29), max_size=3))
def test_kernel_limiter_decides_like_command_limiter(raws, resets):
    dt = 1e-3
    cfg = Config(safety=SafetyConfig(slew_V_per_s=2e3, saturation_s=3e-3))   # 2 V per period, 3 at the clamp
    ref, ker = CommandLimiter(cfg, 4, dt), KernelLimiter(cfg, 4, dt)
    for k, raw in enumerate(raws):
        if k in resets:
            ref.reset()
            ker.reset()
        out_r, out_k = [0.0] * 4, [0.0] * 4
        want, got = ref.limit(raw, out_r), ker.limit(raw, out_k)
        assert got == want, (k, raw)
        if want is not None:
            break
        assert out_k == out_r
        assert (ker.last, ker.sat_run, ker.clamped, ker.limited) == (ref.last, ref.sat_run, ref.clamped,
                                                                    ref.limited)


DT = 2e-4


def _sim_loop(compiled: bool, knobs=()):
    """A four-mount loop on the simulated rig in simulated time: compiled period or stage by stage."""
    cfg = Config()
    clock = SimClock()
    port = make_sim_port(cfg, DT, clock=clock)
    for knob in knobs:
        port.inject(**knob)
    loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clock, rate_hz=1 / DT,
                watchdog_thread=False, use_bank=compiled)
    assert (loop._kern is not None) == compiled
    return loop, port


def _run(compiled: bool, inject=None):
    loop, port = _sim_loop(compiled, [inject] if inject else ())
    written = []
    write = port.write
    port.write = lambda t, c: (written.append(list(c.valve_cmd_V)), write(t, c))
    port.written = written
    loop.run(iterations=3000, activate_after_s=0.02)
    return loop, port


def test_compiled_loop_runs_like_the_stages():
    (lk, pk), (ls, ps) = _run(True), _run(False)
    assert lk.iterations == ls.iterations and lk.lc.fault_reason is None and ls.lc.fault_reason is None
    # the bank equals the Python controllers to ~1e-12 (tests/test_controllers_bank.py): the same run
    wk, ws = np.array(pk.written), np.array(ps.written)
    assert wk.shape == ws.shape == (3001, 4)                   # every period wrote, and the stop's null
    assert np.allclose(wk, ws, rtol=1e-6, atol=1e-9 * np.abs(ws).max())
    assert np.abs(wk).max() > 1e-3                             # the controllers were really acting
    assert lk.limiter.clamped == ls.limiter.clamped


def test_compiled_loop_faults_like_the_stages():
    for knob, words in ((dict(kind="nan", mount=1, at_s=0.3), "front_right: accelerometer implausible"),
                        (dict(kind="stuck", mount=3, sensor="stroke", at_s=0.3),
                         "rear_right: displacement transducer stuck"),
                        (dict(kind="stale", mount=2, at_s=0.3, age_s=0.01), "rear_left: stale sample")):
        (lk, pk), (ls, ps) = _run(True, knob), _run(False, knob)
        assert lk.lc.fault_reason == ls.lc.fault_reason and words in lk.lc.fault_reason
        assert lk.fault_t_ns == ls.fault_t_ns
        assert pk.last_written == [0.0] * 4 and pk.safe_calls >= 1


def _recorded(tmp_path, compiled: bool, inject=(), ring_s=2.0):
    from rig.loop import loop_channels
    from rig.recorder import Recorder, read_recording
    loop, port = _sim_loop(compiled, inject)
    path = tmp_path / f"{'compiled' if compiled else 'stages'}.h5"
    rec = Recorder(path, loop_channels(loop.n, loop.state_len, loop.names), rate_hz=1 / DT, ring_s=ring_s).start()
    loop.recorder = rec
    loop.run(iterations=2500, activate_after_s=0.1)
    rec.close()
    return read_recording(path)


def test_compiled_period_records_like_the_stages(tmp_path):
    """Rows written into the ring by the compiled period equal the stage-by-stage rows: INACTIVE (null), the
    activation, ACTIVE, and the fault period and after it (recorded by the loop itself)."""
    knobs = (dict(kind="range", mount=0, sensor="stroke", at_s=0.4),
             dict(kind="overrun", extra_s=3e-5, every=True))         # 30 us of compute in every read
    rk, rs = _recorded(tmp_path, True, knobs), _recorded(tmp_path, False, knobs)
    n = len(rs["time_s"])
    assert n == len(rk["time_s"]) == 2001                       # 0.4 s, then the fault stops the run
    for name in ("time_s", "lifecycle_state", "isolation_on", "fault", "overruns", "skipped_periods",
                 "cmd_limited", "wake_latency_us", "compute_prev_us"):
        assert np.array_equal(rk[name], rs[name]), name
    for name in ("accel_mps2", "stroke_m", "valve_cmd_V", "valve_cmd_raw_V", "controller_state"):
        assert np.allclose(rk[name], rs[name], rtol=1e-6, atol=1e-12 + 1e-9 * np.abs(rs[name]).max()), name
    state = rk["lifecycle_state"]
    assert state[0] == 1 and state[600] == 2 and state[-1] == 3          # INACTIVE, ACTIVE, FAULT
    assert np.all(rk["valve_cmd_V"][:400] == 0.0) and np.abs(rk["valve_cmd_V"][600:-1]).max() > 1e-3
    assert np.all(rk["valve_cmd_V"][-1] == 0.0) and rk["fault"][-1] == 1 and rk["fault"][-2] == 0
    assert [e[1] for e in rk["events"]] == [e[1] for e in rs["events"]]
    assert np.all(rk["compute_prev_us"][1:] >= 30.0) and np.all(rk["wake_latency_us"] == 0.0)


def test_full_ring_drops_rows_and_counts_each_once(tmp_path):
    """The writer stopped (SIGSTOP) so nothing drains: the ring fills, later rows are dropped and counted once
    each, on the compiled path as on the stage path, and the rows kept are the first ones."""
    import signal

    from rig.loop import loop_channels
    from rig.recorder import Recorder, read_recording
    out = {}
    for compiled in (True, False):
        loop, port = _sim_loop(compiled)
        path = tmp_path / f"full{compiled}.h5"
        rec = Recorder(path, loop_channels(loop.n, loop.state_len, loop.names), rate_hz=1 / DT,
                       ring_s=0.0).start()                        # the smallest ring: 4096 rows
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
        out[compiled] = (dropped, len(r["time_s"]), r["time_s"][-1], r["attrs"].get("dropped_rows"))
    assert out[True] == out[False]
    dropped, rows, t_last, attr = out[True]
    assert rows == cap and dropped == 300 and attr == 300
    assert abs(t_last - (cap - 1) * DT) < 1e-9


@pytest.mark.parametrize("compiled", [True, False])
def test_a_malformed_measurement_faults_on_either_path(compiled):
    """A driver bug (a sensor value None) is a fault in that period with the valves at null, never a dead
    loop. The compiled period is called through its native entry point (no numba type dispatch), where the
    None is a TypeError inside the call."""
    from rig.period import _period4
    loop, port = _sim_loop(compiled)
    if compiled:
        assert loop._kern.call is not _period4 and callable(loop._kern.call)
    read = port.read

    def bad_read(t_ns):
        m = read(t_ns)
        if t_ns - port._t0_ns >= int(0.05e9):
            m.accel_mps2 = [m.accel_mps2[0], m.accel_mps2[1], None, m.accel_mps2[3]]
        return m
    port.read = bad_read
    assert loop.run(iterations=2000, activate_after_s=0.01) == "fault"
    assert "TypeError" in loop.lc.fault_reason and port.last_written == [0.0] * 4
    assert abs(loop.fault_t_ns - port._t0_ns - int(0.05e9)) < int(DT * 1e9)


def test_compiled_period_writes_the_ring_after_a_first_period_recorded_by_the_loop(tmp_path):
    """The first recorded period is a fault period (the loop records it itself); after the fault is reset the
    compiled period must still write its rows into the ring directly, and every period is in the file."""
    from rig.loop import loop_channels
    from rig.recorder import Recorder, read_recording
    loop, port = _sim_loop(True, [dict(kind="device", at_s=0.0)])
    loop.stop_on_fault = False
    path = tmp_path / "first_fault.h5"
    rec = Recorder(path, loop_channels(loop.n, loop.state_len, loop.names), rate_hz=1 / DT).start()
    loop.recorder = rec
    loop.run(iterations=5)
    assert loop.lc.fault_reason and "device fault" in loop.lc.fault_reason
    port.clear_faults()
    loop.reset_fault()
    loop.stop_reason = None
    loop.run(iterations=500, activate_after_s=0.01)
    assert loop._kring is not None                     # the ring is bound for the compiled period
    rec.close()
    r = read_recording(path)
    assert len(r["time_s"]) == 505 and r["fault"][:5].tolist() == [1.0] * 5 and r["lifecycle_state"][-1] == 2

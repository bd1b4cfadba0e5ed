"""The compiled period (rig/period.py) must decide exactly as the Python stages it stands for: KernelCheck as
SensorCheck and KernelLimiter as CommandLimiter (same fault texts on the same period, same counters), for any
sequence; and a loop run on the compiled path as one on the stage-by-stage path."""
from __future__ import annotations

import math

import numpy as np
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


def _run(compiled: bool, inject=None):
    cfg = Config()
    dt = 2e-4
    clock = SimClock()
    port = make_sim_port(cfg, dt, clock=clock)
    if inject:
        port.inject(**inject)
    written = []
    write = port.write
    port.write = lambda t, c: (written.append(list(c.valve_cmd_V)), write(t, c))
    port.written = written
    loop = Loop(cfg, port, make_isolation_controllers(cfg, dt), clock=clock, rate_hz=1 / dt,
                watchdog_thread=False, use_bank=compiled)
    assert (loop._kern is not None) == compiled
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

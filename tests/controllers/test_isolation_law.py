"""The compiled isolation law (controllers/isolation.py isolation_step) equals the plain-Python reference
(tests/controllers/reference.py) sample for sample, over a run with isolation switching, clamp and slew, and
the saturation recovery (suspend and resume); and so does the period kernel (rig/runtime/kernel.py) that runs it for
any number of mounts, with its replay of skipped periods."""
from __future__ import annotations

import numpy as np
import pytest

from controllers.isolation import make_isolation_controllers
from controllers.playback import SignalPlayback
from rig.config import Config, SafetyConfig, config_from_dict, mount_names
from rig.errors import ConfigError
from rig.runtime.kernel import MODE_INACTIVE, PeriodKernel
from rig.port import Measurements
from tests.controllers.reference import isolation_step as reference_step

DT = 1.0 / 5000.0
WIDE = Config(safety=SafetyConfig(accel_range_mps2=1e3, stale_s=1.0))   # the shocks below stay plausible


def _inputs(n: int, seed: int = 5, mounts: int = 4):
    """Floor-like motion plus shocks: some drive the outputs to the clamp long enough to suspend isolation."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    acc = 1e-3 * rng.standard_normal((n, mounts)) + 2e-2 * np.sin(2 * np.pi * 7.0 * k * DT)[:, None]
    xs = 1e-7 * rng.standard_normal((n, mounts))
    for k0, mount, amp in ((1500, 0, 40.0), (1500, 2, -25.0), (5200, 1, 60.0), (9000, 3, -80.0)):
        if mount < mounts:
            acc[k0:k0 + 40, mount] += amp                  # 8 ms shocks
    return acc, xs


def test_compiled_law_equals_the_reference_sample_for_sample():
    cfg = config_from_dict({"controller": {"gain_trim": [1.0, 0.9, 1.1, 1.0], "sat_resume_s": 0.05}})
    ctrls = make_isolation_controllers(cfg, DT)
    n = 14000
    acc, xs = _inputs(n)
    sp = [c.set_enabled(c.initial_state(), False) for c in ctrls]           # reference states (lists)
    sc = [np.array(s) for s in sp]                                         # compiled states (arrays)
    switch = {300: True, 7000: False, 7600: True}
    up, uc = np.empty((n, 4)), np.empty((n, 4))
    susp = np.zeros((n, 4), dtype=bool)
    for k in range(n):
        if k in switch:
            sp = [c.set_enabled(s, switch[k]) for c, s in zip(ctrls, sp)]
            sc = [np.array(c.set_enabled(s.tolist(), switch[k])) for c, s in zip(ctrls, sc)]
        for i, c in enumerate(ctrls):
            up[k, i], sp[i] = reference_step(c, sp[i], (float(acc[k, i]), float(xs[k, i])), DT)
            uc[k, i], sc[i] = c.step(sc[i], (float(acc[k, i]), float(xs[k, i])), DT)
        susp[k] = [c.suspended(s) for c, s in zip(ctrls, sp)]
    # the run covered what it should: isolation on and off, the clamp, suspension and resumption
    lim = ctrls[0].p.limit_V
    assert np.any(np.abs(up) == lim)
    assert susp.any(axis=0).sum() >= 3                                   # three mounts suspended...
    assert np.any(susp[:-1] & ~susp[1:])                                 # ...and resumed
    assert np.abs(up[: 300]).max() < 0.1 < np.abs(up[300:1500]).max()    # centring only, then isolating
    assert np.array_equal(uc, up)                                        # the same operations, bit for bit
    assert all(np.array_equal(c, np.array(p)) for c, p in zip(sc, sp))


def _kernel(ctrls, cfg=WIDE):
    k = PeriodKernel(cfg, ctrls, mount_names(len(ctrls)), DT, max_held_steps=5)
    k.set_enabled(True)
    return k


def _period(k, t, acc, xs, miss=0):
    m = Measurements(t, list(acc), list(xs), [t] * len(acc))
    assert k.period(m, t, 0.0, 0.0, 0.0, MODE_INACTIVE, miss) == 0


def test_kernel_replay_equals_interpolated_reference_steps():
    ctrls = make_isolation_controllers(Config(), DT)
    k = _kernel(ctrls)
    sp = [c.set_enabled(c.initial_state(), True) for c in ctrls]
    prev = ([0.01, -0.02, 0.03, 0.0], [1e-6, 0.0, -2e-6, 3e-6])
    now = ([0.02, 0.01, -0.01, 0.05], [2e-6, 1e-6, -1e-6, 0.0])
    miss = 7                                                   # of which the last max_held_steps = 5 replayed
    for i, c in enumerate(ctrls):
        reference_step(c, sp[i], (prev[0][i], prev[1][i]), DT)
        for j in range(miss - 5, miss):
            f = (j + 1) / (miss + 1)
            reference_step(c, sp[i], (prev[0][i] + f * (now[0][i] - prev[0][i]),
                                      prev[1][i] + f * (now[1][i] - prev[1][i])), DT)
        reference_step(c, sp[i], (now[0][i], now[1][i]), DT)
    _period(k, 10**9, *prev)
    _period(k, 10**9 + 8 * 200_000, *now, miss=miss)
    for s, p in zip(k.states, sp):
        assert s.tolist() == p


@pytest.mark.parametrize("mounts", [1, 3, 8])
def test_kernel_of_any_mount_count_runs_the_law_of_each_mount(mounts):
    cfg = WIDE.replace(controller=config_from_dict({"controller": {"gain_trim": [1.0] * 4}}).controller)
    ctrls = [c for c in make_isolation_controllers(cfg, DT) for _ in range(2)][:mounts]
    k = _kernel(ctrls)
    acc, xs = _inputs(3000, seed=9, mounts=mounts)
    sp = [c.set_enabled(c.initial_state(), True) for c in ctrls]
    for n in range(3000):
        _period(k, 10**9 + n * 200_000, acc[n], xs[n])
        ref = [reference_step(c, sp[i], (float(acc[n, i]), float(xs[n, i])), DT)[0] for i, c in enumerate(ctrls)]
        assert k.raw_commands() == ref
    assert [s.tolist() for s in k.states] == sp


def test_kernel_runs_different_kinds_side_by_side():
    iso = make_isolation_controllers(Config(), DT)[0]
    play = SignalPlayback([0.5, -0.25, 0.125], DT)
    k = _kernel([iso, play])
    sp = iso.set_enabled(iso.initial_state(), True)
    out = []
    for n in range(5):
        _period(k, 10**9 + n * 200_000, [0.01 * n, 0.0], [1e-6, 0.0])
        out.append(k.raw_commands())
        assert out[-1][0] == reference_step(iso, sp, (0.01 * n, 1e-6), DT)[0]
    assert [u[1] for u in out] == [0.5, -0.25, 0.125, 0.0, 0.0]


def test_kernel_refuses_what_it_cannot_run():
    cs = make_isolation_controllers(Config(), DT)
    with pytest.raises(ConfigError, match="dt"):
        PeriodKernel(Config(), cs, mount_names(4), 1e-3, 5)
    with pytest.raises(ConfigError, match="not a controller kind"):
        PeriodKernel(Config(), cs[:3] + [object()], mount_names(4), DT, 5)
    with pytest.raises(ConfigError, match="1 to 8"):
        PeriodKernel(Config(), cs * 3, mount_names(12), DT, 5)

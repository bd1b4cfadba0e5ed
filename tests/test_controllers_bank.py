"""The compiled bank of isolation controllers equals the Python IsolationController.step sample for sample,
over a run with isolation switching, clamp and slew, and the saturation recovery (suspend and resume)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.bank import IsolationBank, make_bank
from controllers.isolation import IsolationController, make_isolation_controllers, params_from_config
from rig.config import Config, config_from_dict

DT = 1.0 / 5000.0


def _inputs(n: int, seed: int = 5):
    """Floor-like motion plus shocks: some drive the outputs to the clamp long enough to suspend isolation."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    acc = 1e-3 * rng.standard_normal((n, 4)) + 2e-2 * np.sin(2 * np.pi * 7.0 * k * DT)[:, None]
    xs = 1e-7 * rng.standard_normal((n, 4))
    for k0, mount, amp in ((1500, 0, 40.0), (1500, 2, -25.0), (5200, 1, 60.0), (9000, 3, -80.0)):
        acc[k0:k0 + 40, mount] += amp                      # 8 ms shocks
    return acc, xs


def test_bank_equals_python_controllers_sample_for_sample():
    cfg = config_from_dict({"controller": {"gain_trim": [1.0, 0.9, 1.1, 1.0], "sat_resume_s": 0.05}})
    py = make_isolation_controllers(cfg, DT)
    bank = IsolationBank(make_isolation_controllers(cfg, DT))
    n = 14000
    acc, xs = _inputs(n)
    sp = [c.set_enabled(c.initial_state(), False) for c in py]
    sb = bank.set_enabled(bank.initial_state(), False)
    assert sb.shape == (4, len(sp[0])) and np.array_equal(sb, np.array(sp))
    switch = {300: True, 7000: False, 7600: True}
    up = np.empty((n, 4))
    ub = np.empty((n, 4))
    susp = np.zeros((n, 4), dtype=bool)
    for k in range(n):
        if k in switch:
            sp = [c.set_enabled(s, switch[k]) for c, s in zip(py, sp)]
            sb = bank.set_enabled(sb, switch[k])
        a, x = acc[k].tolist(), xs[k].tolist()
        for i, c in enumerate(py):
            up[k, i], sp[i] = c.step(sp[i], (a[i], x[i]), DT)
        cmds, sb = bank.step(sb, (a, x), DT)
        ub[k] = cmds
        susp[k] = [c.suspended(s) for c, s in zip(py, sp)]
        assert isinstance(cmds[0], float)
    # the run covered what it should: isolation on and off, the clamp, suspension and resumption
    lim = py[0].p.limit_V
    assert np.any(np.abs(up) == lim)
    assert susp.any(axis=0).sum() >= 3                                   # three mounts suspended...
    assert np.any(susp[:-1] & ~susp[1:])                                 # ...and resumed
    assert np.abs(up[: 300]).max() < 0.1 < np.abs(up[300:1500]).max()    # centring only, then isolating
    np.testing.assert_allclose(ub, up, rtol=1e-12, atol=1e-12 * lim)
    np.testing.assert_allclose(sb, np.array(sp), rtol=1e-12, atol=1e-18)
    assert bank.enabled(sb) == all(c.enabled(s) for c, s in zip(py, sp))


def test_bank_replay_equals_interpolated_python_steps():
    py = make_isolation_controllers(Config(), DT)
    bank = IsolationBank(make_isolation_controllers(Config(), DT))
    sp = [c.set_enabled(c.initial_state(), True) for c in py]
    sb = bank.set_enabled(bank.initial_state(), True)
    prev = ([0.01, -0.02, 0.03, 0.0], [1e-6, 0.0, -2e-6, 3e-6])
    now = ([0.02, 0.01, -0.01, 0.05], [2e-6, 1e-6, -1e-6, 0.0])
    miss, max_steps = 7, 5
    for j in range(miss - max_steps, miss):
        f = (j + 1) / (miss + 1)
        for i, c in enumerate(py):
            _, sp[i] = c.step(sp[i], (prev[0][i] + f * (now[0][i] - prev[0][i]),
                                      prev[1][i] + f * (now[1][i] - prev[1][i])), DT)
    bank.replay(sb, prev, now, miss, max_steps)
    np.testing.assert_allclose(sb, np.array(sp), rtol=1e-12, atol=1e-18)


def test_bank_refuses_what_it_cannot_run():
    cs = make_isolation_controllers(Config(), DT)
    with pytest.raises(ValueError, match="dt"):
        IsolationBank(cs).step(IsolationBank(cs).initial_state(), ([0.0] * 4, [0.0] * 4), 1e-3)
    mixed = cs[:3] + [IsolationController(params_from_config(Config(), 3).with_(notch_hz=0.0), DT)]
    assert make_bank(mixed) is None                                      # different structure
    assert make_bank([object()] * 4) is None                             # not isolation controllers


def test_bank_of_other_sizes_uses_the_array_path_and_agrees():
    py = make_isolation_controllers(Config(), DT)[:3]
    bank = IsolationBank(make_isolation_controllers(Config(), DT)[:3])
    acc, xs = _inputs(3000, seed=9)
    sp = [c.set_enabled(c.initial_state(), True) for c in py]
    sb = bank.set_enabled(bank.initial_state(), True)
    for k in range(3000):
        u = [0.0] * 3
        for i, c in enumerate(py):
            u[i], sp[i] = c.step(sp[i], (float(acc[k, i]), float(xs[k, i])), DT)
        ub, sb = bank.step(sb, (acc[k, :3].tolist(), xs[k, :3].tolist()), DT)
        np.testing.assert_allclose(ub, u, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sb, np.array(sp), rtol=1e-12, atol=1e-18)

"""The stand layout's plant: the actuator on its stand with the floor moving under it (base_motion), stepped
exactly when linear and by RK4 otherwise (the two agree), its linear model (stand_state_space) against the
time-domain plant, and a bank of stands."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_backend.actuator import Effects, StandBank, StandPlant, stand_state_space
from sim_backend.linear import actuator_params, g_eha_frf
from sim_backend.rig_plant import FloorMotion

FS = 5000.0
P = actuator_params()
RK4 = Effects(friction_force_n=1e-9)         # a negligible nonlinear effect: the RK4 path, the same physics


def _drive(plant, n, floor=None, seed=0):
    rng = np.random.default_rng(seed)
    u = np.convolve(rng.standard_normal(n), np.ones(20) / 20, mode="same") * 2.0
    out = []
    for k in range(n):
        g = None if floor is None else floor[k]
        plant.step(float(u[k]), g)
        out.append((plant.x_abs_m, plant.accel_now_mps2 if g is not None else plant.accel_mps2))
    return np.array(out)


def _floor(n, seed=3):
    fl = FloorMotion(1 / FS, rms_m=3e-6, seed=seed, n_mounts=1).next_block(n + 1)
    return [np.array([fl[k, 0], fl[k, 1], fl[k + 1, 0], fl[k + 1, 1]]) for k in range(n)]


@pytest.mark.parametrize("base", [0.0, 60.0])
def test_exact_and_rk4_steps_agree_with_the_floor_moving(base):
    fx = Effects(base_frequency_hz=base)
    exact, rk4 = StandPlant(P, fx, FS), StandPlant(P, dataclasses.replace(RK4, base_frequency_hz=base), FS)
    assert exact.linear and not rk4.linear
    fl = _floor(3000)
    a, b = _drive(exact, 3000, fl), _drive(rk4, 3000, fl)
    scale = np.abs(b).max(axis=0)
    assert np.abs(a - b).max(axis=0)[0] < 1e-4 * scale[0]
    assert np.abs(a - b).max(axis=0)[1] < 1e-3 * scale[1]


def test_the_linear_model_is_the_time_domain_plant():
    """stand_state_space from valve to transducer is Eq. 10 (g_eha, the full Eq. 8 actuator)."""
    A, B, C, D = stand_state_space(P)
    w = 2 * np.pi * np.array([1.0, 10.0, 80.0, 500.0])
    H = [C[0] @ np.linalg.solve(1j * wk * np.eye(len(A)) - A, B[:, 0]) for wk in w]
    assert np.allclose(H, g_eha_frf(P, w), rtol=1e-9)


def test_with_the_valve_null_the_load_rides_the_floor():
    """The actuator is stiff (K_L + K_h ~ 1e10 N/m under 56 kg): at null the load follows the floor and the
    transducer, reading against the floor, barely moves."""
    n = 5000
    floor = FloorMotion(1 / FS, rms_m=3e-6, seed=2, n_mounts=2)
    bank = StandBank([StandPlant(P, Effects(), FS), StandPlant(P, Effects(), FS)], floor)
    assert bank.exact
    x, xs, fm = [], [], []
    for _ in range(n):
        bank.step([0.0, 0.0])
        x.append(bank.table_m)
        xs.append(bank.stroke_m)
        fm.append(bank.floor_m)
    x, xs, fm = np.array(x)[500:], np.array(xs)[500:], np.array(fm)[500:]
    assert (np.std(fm, axis=0) > 1e-6).all()                         # the floor does move (1 s of it)
    assert np.abs(x - fm).max() < 1e-3 * np.abs(fm).max()
    assert np.abs(xs).max() < 1e-3 * np.abs(fm).max()


def test_the_bank_exact_path_equals_its_stands_stepped_one_by_one():
    n = 2000
    fx = Effects(position_noise_m=0.0, accel_noise_mps2=0.0)
    fl = lambda: FloorMotion(1 / FS, rms_m=2e-6, seed=5, n_mounts=3)          # noqa: E731
    exact = StandBank([StandPlant(P, fx, FS) for _ in range(3)], fl())
    slow = StandBank([StandPlant(P, dataclasses.replace(fx, friction_force_n=1e-9), FS) for _ in range(3)], fl())
    assert exact.exact and not slow.exact
    u = 0.5 * np.sin(np.arange(n)[:, None] * np.array([0.01, 0.02, 0.03]))
    ea, sa = [], []
    for k in range(n):
        exact.step(u[k])
        slow.step(u[k])
        ea.append(exact.stroke_m + exact.accel_mps2)
        sa.append(slow.stroke_m + slow.accel_mps2)
    ea, sa = np.array(ea), np.array(sa)
    assert np.abs(ea[:, :3] - sa[:, :3]).max() < 1e-4 * np.abs(sa[:, :3]).max()
    assert np.abs(ea[:, 3:] - sa[:, 3:]).max() < 1e-3 * np.abs(sa[:, 3:]).max()


@pytest.mark.parametrize("n", [1, 8])
def test_floor_motion_for_any_mount_count(n):
    g = FloorMotion(1 / FS, rms_m=1e-6, seed=1, n_mounts=n).next_block(4000)
    assert g.shape == (4000, 3 * n)          # x_g, v_g, a_g per mount
    assert np.std(g[1000:, :n], axis=0) == pytest.approx([1e-6] * n, rel=0.6)

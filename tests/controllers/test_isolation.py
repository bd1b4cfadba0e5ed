"""Isolation controller and tracking PID: the step functions against their own transfer functions, limits,
anti-windup, bumpless switching, and the runtime interface."""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal

from controllers.isolation import (_C, _V, IsolationController, make_isolation_controllers,  # noqa: F401
                                  params_from_config)
from controllers.tracking import (PIDParams, TrackingPID, bandwidth_hz, pid_from_config, tracking_response)
from rig.config import MOUNTS, Config, config_from_dict
from sim_backend.linear import ActuatorParams

DT = 1.0 / 5000.0


@pytest.fixture(scope="module")
def ctrl():
    return make_isolation_controllers(Config(), DT)[0]


def test_runtime_interface_four_mounts():
    cs = make_isolation_controllers(Config(), DT)
    assert len(cs) == len(MOUNTS) == 4
    for c in cs:
        s = c.initial_state()
        assert all(isinstance(v, float) for v in s)
        u, s2 = c.step(s, (0.0, 0.0), DT)
        assert isinstance(u, float) and u == 0.0
        assert c.set_enabled(s2, False) is s2 and not c.enabled(s2)


def test_step_equals_its_discrete_transfer_function(ctrl):
    """One code path: the float step and the state space the analysis uses give the same output."""
    rng = np.random.default_rng(3)
    n = 3000
    a = 1e-5 * rng.standard_normal(n)          # small: no clamp, no slew
    x = 1e-7 * rng.standard_normal(n)
    s = ctrl.initial_state()
    u = np.empty(n)
    for k in range(n):
        u[k], s = ctrl.step(s, (float(a[k]), float(x[k])), DT)
    assert np.max(np.abs(u)) < 0.5 * ctrl.p.limit_V
    A, B, C, D = ctrl.ss()
    _, y, _ = scipy.signal.dlsim((A, B, C, D, DT), np.column_stack([a, x]))
    np.testing.assert_allclose(u, y[:, 0], rtol=1e-9, atol=1e-12 * np.max(np.abs(u)) + 1e-15)
    # and the frequency response equals the state space's
    w = 2 * np.pi * np.array([0.3, 3.0, 30.0, 300.0])
    Ka, Ks = ctrl.frf(w)
    z = np.exp(1j * w * DT)
    H = np.array([C @ np.linalg.solve(zz * np.eye(A.shape[0]) - A, B) + D for zz in z])[:, 0, :]
    np.testing.assert_allclose(Ka, H[:, 0], rtol=1e-4)       # (zI - A) near z = 1 costs digits
    np.testing.assert_allclose(Ks, H[:, 1], rtol=1e-4)


def test_accelerometer_offset_does_not_run_away(ctrl):
    """A constant accelerometer offset (open loop, no plant): the double integration is band-limited, so the
    blended signal returns to zero and the PI output settles to a constant instead of ramping."""
    s = ctrl.initial_state()
    us = []
    for k in range(int(120 / DT)):
        u, s = ctrl.step(s, (1e-12, 0.0), DT)
        us.append(u)
    us = np.array(us)
    assert 0 < np.max(np.abs(us)) < ctrl.p.limit_V           # it responded, in the linear range
    late = us[int(100 / DT):]
    assert np.ptp(late) < 0.05 * np.max(np.abs(us))          # settling to a constant, not ramping
    o = ctrl._o
    assert abs(s[o + _V]) * ctrl.kp < 1e-3 * np.max(np.abs(us))   # the blended signal is back near zero


def test_clamp_and_slew(ctrl):
    s = ctrl.initial_state()
    prev = 0.0
    lim, slew = ctrl.p.limit_V, ctrl.p.slew_V_per_s * DT
    for k in range(2000):
        a = 50.0 * math.sin(2 * math.pi * 80 * k * DT)
        u, s = ctrl.step(s, (a, 0.0), DT)
        assert abs(u) <= lim + 1e-12
        assert abs(u - prev) <= slew + 1e-9
        prev = u


def test_centring_anti_windup():
    """Stroke held far off centre while the output is clamped: the centring integral stops growing, so the
    command leaves the limit as soon as the stroke returns, instead of after a long unwinding."""
    cfg = Config()
    c = make_isolation_controllers(cfg, DT)[0]
    s = c.set_enabled(c.initial_state(), False)      # centring only
    for _ in range(int(20 / DT)):
        u, s = c.step(s, (0.0, 5e-3), DT)             # 5 mm: saturates quickly
    assert u == pytest.approx(-c.p.limit_V)
    o = c._o
    integral = s[o + _C]
    # the integral stays at the value that just saturates the output (limit / k_c), not 20 s of growth
    assert abs(integral) < 1.01 * c.p.limit_V          # (volts)
    u, s = c.step(s, (0.0, -1e-6), DT)
    for _ in range(int(0.01 / DT)):
        u, s = c.step(s, (0.0, -1e-6), DT)
    assert abs(u) < c.p.limit_V                       # off the limit within 10 ms


def _run_sine(c, s, n, k0, amp=1e-4, f=30.0):
    out = []
    for k in range(k0, k0 + n):
        u, s = c.step(s, (amp * math.cos(2 * math.pi * f * k * DT), 0.0), DT)   # starts at rest
        out.append(u)
    return out, s


def test_bumpless_enable_disable(ctrl):
    """Switching isolation on or off under motion never jumps more than the normal per-period change."""
    warm = int(20 / DT)                       # let the 0.1 Hz band-limiting transients die out
    s = ctrl.set_enabled(ctrl.initial_state(), False)
    u_off, s = _run_sine(ctrl, s, warm, 0)
    normal = np.max(np.abs(np.diff(_run_sine(ctrl, ctrl.initial_state(), warm, 0)[0][-2500:])))
    s = ctrl.set_enabled(s, True)
    u_on, s = _run_sine(ctrl, s, 2500, warm)
    assert abs(u_on[0] - u_off[-1]) <= 1.5 * normal
    assert np.max(np.abs(np.diff(u_on))) <= 1.5 * normal
    s = ctrl.set_enabled(s, False)
    u_off2, s = _run_sine(ctrl, s, 5000, warm + 2500)
    assert abs(u_off2[0] - u_on[-1]) <= 1.5 * normal
    assert abs(u_off2[-1]) < 1e-3 * np.max(np.abs(u_on))      # the held offset fades away
    assert np.max(np.abs(u_on[-500:])) > 10 * np.max(np.abs(u_off2[-500:]))


def test_dt_mismatch_is_refused(ctrl):
    with pytest.raises(ValueError, match="dt"):
        ctrl.step(ctrl.initial_state(), (0.0, 0.0), 1e-3)


def test_gain_trim_from_config():
    cfg = config_from_dict({"controller": {"gain_trim": [1.0, 2.0, 1.0, 0.5]}})
    cs = make_isolation_controllers(cfg, DT)
    base = params_from_config(Config(), 0).kp_V_per_m
    assert [c.kp / base for c in cs] == pytest.approx([1.0, 2.0, 1.0, 0.5])


def test_tracking_pid_bandwidth_about_95_hz():
    """Paper Fig. 4: the actuator alone tracks its reference with ~95 Hz bandwidth (-3 dB)."""
    cfg = Config()
    pid = TrackingPID(pid_from_config(cfg), DT)
    f = np.linspace(1.0, 500.0, 5000)
    T = tracking_response(ActuatorParams.from_config(cfg), pid, f)
    assert 90.0 <= bandwidth_hz(f, T) <= 100.0
    assert np.max(20 * np.log10(np.abs(T))) < 3.0


def test_tracking_pid_time_domain_on_stand():
    """The PID on the stepped stand plant (Eqs. 1-7) with one period of delay: a 20 um step settles."""
    from sim_backend.actuator import Effects, StandPlant
    cfg = Config()
    p = ActuatorParams.from_config(cfg)
    plant = StandPlant(p, Effects(), 1.0 / DT)
    pid = TrackingPID(pid_from_config(cfg), DT)
    s = pid.initial_state()
    u_prev = 0.0
    xs = []
    for k in range(int(0.1 / DT)):
        pos, _ = plant.step(u_prev)
        u_prev, s = pid.step(s, (20e-6, float(pos)), DT)
        xs.append(float(pos))
    xs = np.array(xs)
    assert abs(xs[-200:].mean() - 20e-6) < 0.2e-6
    assert xs.max() < 1.2 * 20e-6


def test_saturation_recovery_suspends_and_resumes_isolation_bumplessly():
    """A velocity error in the double integration (an 8 ms acceleration pulse the plant never made: what a
    scheduling gap leaves behind) drives the isolating output to the clamp. After sat_reset_s at the clamp
    isolation is suspended (centring alone, the output leaves the clamp through the fading offset, within
    the slew limit); once the estimate's mean output has stayed in range for sat_resume_s it resumes, still
    enabled, without a jump. With sat_reset_s = 0 the output stays at the clamp."""
    cfg = Config()
    p = params_from_config(cfg, 0)
    lim, slew = p.limit_V, p.slew_V_per_s * DT

    def run(params, seconds):
        c = IsolationController(params, DT)
        s = c.set_enabled(c.initial_state(), True)
        us, sus = [], []
        for k in range(int(seconds / DT)):
            a = 2.0 if 100 <= k < 140 else 0.0
            u, s = c.step(s, (a, 0.0), DT)
            us.append(u)
            sus.append(c.suspended(s))
        return c, s, np.array(us), np.array(sus)

    _, _, u_off, sus_off = run(p.with_(sat_reset_s=0.0), 3.0)
    assert not sus_off.any() and np.mean(np.abs(u_off[int(0.5 / DT):]) == lim) > 0.9    # latched at the clamp
    c, s, u, sus = run(p, 60.0)
    assert c.sat_n == round(p.sat_reset_s / DT)
    k_sus = int(np.argmax(sus))
    assert k_sus > 0 and np.all(np.abs(u[k_sus - c.sat_n + 1:k_sus + 1]) == lim)   # after sat_reset_s
    assert np.max(np.abs(np.diff(u))) <= slew + 1e-9                            # never a jump
    assert np.abs(u[k_sus + int(0.5 / DT)]) < 0.1 * lim                        # off the clamp, fading
    k_res = k_sus + int(np.argmin(sus[k_sus:]))
    assert k_res > k_sus and not sus[-1] and c.enabled(s)                       # resumed by itself
    assert abs(u[k_res]) < 0.5 * lim            # resumed off the clamp (open loop: the PI then integrates
                                                # what is left; the closed loop is tests/test_runtime_saturation.py)

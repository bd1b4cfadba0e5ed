"""Floor feedforward (controllers/feedforward.py): it is the inverse of the actuator model within its band,
the discrete filter is the continuous design, the step function runs the frf (in Python and compiled by numba),
it switches without a jump, and in the simulated rig (RigPlant stepping, one period of delay) it cancels floor
motion as the frequency-domain analysis predicts."""
from __future__ import annotations

import math

import numpy as np
import pytest

from controllers.analysis import DiscreteRig, attenuation_db, siso
from controllers.discrete import sections_step, tustin_section
from controllers.feedforward import (FeedforwardFilter, feedforward_params_from_config, feedforward_step,
                                     make_feedforward_filters)
from controllers.isolation import make_isolation_controllers
from rig.config import Config
from sim_backend.linear import ActuatorParams, g_eha_frf
from sim_backend.rig_plant import I_TABLE, RigPlant

CFG = Config()
DT = 1.0 / CFG.loop.rate_hz


@pytest.fixture(scope="module")
def ff():
    return FeedforwardFilter(feedforward_params_from_config(CFG), DT)


def test_tustin_closed_form_equals_python_control():
    """controllers/discrete.tustin_section writes out the map python-control's sample_system applies."""
    import control
    rng = np.random.default_rng(3)
    for _ in range(40):
        w = 2 * math.pi * 10 ** rng.uniform(-1, 3)
        for num, den in (([1 / w, 1.0], [1 / (4 * w), 1.0]), ([w * w], [1.0, 1.4 * w, w * w]),
                         ([1.0, 0.2 * w, w * w], [1.0, w, w * w]), ([1.0, 0.0], [1.0, 1.8 * w, w * w])):
            for pw in (None, 200.0):
                kw = {"prewarp_frequency": 2 * math.pi * pw} if pw else {}
                d = control.sample_system(control.tf(num, den), DT, method="tustin", **kw)
                b = np.asarray(d.num[0][0], float)
                a = np.asarray(d.den[0][0], float)
                b = np.concatenate([np.zeros(len(a) - len(b)), b]) / a[0]
                a = a / a[0]
                ref = np.concatenate([b, np.zeros(3 - len(b)), a[1:], np.zeros(3 - len(a))])
                assert np.allclose(tustin_section(num, den, DT, pw), ref, rtol=1e-9, atol=1e-12)


def test_it_inverts_the_actuator_model_in_band(ff):
    """u_ff / a_g times the model's x_p / u (Eq. 10), times the floor's acceleration per metre (-w^2) and the
    1.5 periods of delay, is -1 within 2-100 Hz: the stroke cancels the floor to 20 dB or better."""
    f = np.geomspace(2.0, 100.0, 200)
    w = 2 * np.pi * f
    loop = ff.frf(w) * g_eha_frf(ActuatorParams.from_config(CFG), w) * (-(w ** 2)) * np.exp(-1.5j * w * DT)
    assert np.max(np.abs(1 + loop)) < 0.1


def test_discrete_filter_is_the_continuous_design(ff):
    f = np.geomspace(0.5, 100.0, 120)
    w = 2 * np.pi * f
    g = ff.tf()
    cont = np.array([complex(g(1j * x)) for x in w])
    assert np.max(np.abs(ff.frf(w) / cont - 1)) < 0.01


def test_step_runs_the_frf_in_python_and_compiled(ff):
    """A sine of floor acceleration through step() (the compiled law): steady-state amplitude and phase as
    frf(); the law's Python source run by the interpreter gives the same samples."""
    f0 = 23.0
    n = int(3.0 / DT)
    t = np.arange(n) * DT
    a = np.sin(2 * np.pi * f0 * t) * 0.5 * (1 - np.cos(np.pi * np.minimum(t, 1.0)))   # fades in over 1 s
    s = ff.initial_state(on=True)
    y = np.array([ff.step(s, x, DT)[0] for x in a])
    s2 = ff.initial_state(on=True)
    y2 = np.array([feedforward_step.py_func(ff.coef, ff.fade, s2, x) for x in a])
    assert np.allclose(y, y2, rtol=1e-12, atol=1e-15)
    k = t > 2.0
    A = np.column_stack([np.sin(2 * np.pi * f0 * t[k]), np.cos(2 * np.pi * f0 * t[k]), np.ones(k.sum()), t[k]])
    c = np.linalg.lstsq(A, y[k], rcond=None)[0]
    H = ff.frf(np.array([2 * np.pi * f0]))[0]
    assert complex(c[0], c[1]) == pytest.approx(H, rel=2e-3)


def test_cascade_step_is_scipys_sosfilt():
    """The compiled cascade step of the laws (controllers/discrete.sections_step) is transposed direct form II,
    as scipy.signal.sosfilt runs it."""
    import numba
    import scipy.signal
    secs = [tustin_section([1.0, 30.0], [1.0, 300.0], DT, 100.0), tustin_section([1e4], [1.0, 140.0, 1e4], DT)]
    coef = np.ravel(np.array(secs))

    @numba.njit
    def step(st, x):
        return sections_step(st, coef, 0, 0, 2, x)[0]
    x = np.sin(np.arange(400) * 0.1) + 0.3 * np.cos(np.arange(400) * 0.77)
    st = np.zeros(4)
    y = np.array([step(st, v) for v in x])
    sos = np.array([[b0, b1, b2, 1.0, a1, a2] for b0, b1, b2, a1, a2 in secs])
    assert np.allclose(y, scipy.signal.sosfilt(sos, x), rtol=1e-12, atol=1e-14)


def test_switching_fades_without_a_jump(ff):
    """Off: nothing out while the filters run warm; on: the DC block starts from the command it meets (the output
    starts at 0), and the output is that of a filter switched on at once times a gain that rises monotonically, by
    at most dt / fade_s per period (no jump), towards 1."""
    a = np.sin(2 * np.pi * 10.0 * np.arange(int(1.0 / DT)) * DT)
    now = FeedforwardFilter(ff.p.with_(fade_s=1e-9), DT)
    ref, sw = now.initial_state(on=False), ff.initial_state(on=False)
    y_ref, y_sw = [], []
    for k, x in enumerate(a):
        if k == 2000:
            ff.set_enabled(sw, True)
            now.set_enabled(ref, True)
        y_ref.append(now.step(ref, x, DT)[0])
        y_sw.append(ff.step(sw, x, DT)[0])
    y_ref, y_sw = np.array(y_ref), np.array(y_sw)
    assert np.all(y_sw[:2000] == 0.0) and ff.enabled(sw)
    assert y_ref[2000] == 0.0 and abs(y_ref[2001]) < 0.01 * np.abs(y_ref[2000:]).max()
    live = np.abs(y_ref[2000:]) > 1e-3 * np.abs(y_ref).max()
    g = y_sw[2000:][live] / y_ref[2000:][live]
    assert np.all(np.diff(g) >= -1e-12) and np.all(np.diff(g) <= DT / ff.p.fade_s * 1.01)
    assert g[0] < 0.05 and g[-1] > 0.99
    with pytest.raises(ValueError):
        ff.step(sw, 0.0, 2 * DT)


def _switched_on(ff, a, k_on, dc_block=True):
    """The command for floor acceleration a, switched on at sample k_on; without the DC block: the cascade before
    it (the design before the block), faded in the same way."""
    import scipy.signal
    if dc_block:
        st = ff.initial_state(on=False)
        out = np.empty(len(a))
        for k, x in enumerate(a):
            if k == k_on:
                ff.set_enabled(st, True)
            out[k] = ff.step(st, x, DT)[0]
        return out
    sos = np.array([[b0, b1, b2, 1.0, a1, a2] for b0, b1, b2, a1, a2 in ff.sections[:-1]])
    n = np.arange(len(a)) - k_on
    return scipy.signal.sosfilt(sos, a) * np.where(n >= 0, 1 - ff.fade ** (n + 1), 0.0)


def _slow_V(u, k_on):
    """The command's slow part after switch-on: its largest 0.5 s mean."""
    w = int(0.5 / DT)
    return np.max(np.abs(np.convolve(u[k_on:], np.ones(w) / w, mode="valid")))


@pytest.mark.parametrize("seed", [1, 3])
def test_an_accelerometer_offset_does_not_hold_the_valve(ff, seed):
    """A floor accelerometer 2e-5 m/s^2 off (what a calibration left on one mount: the double integration's DC
    gain 1 / w_hp^2 made it 51 um of stroke and the valve's clamp) on a floor already moving when the filters
    start, switched on 6 s later: the command's slow part stays within a volt or two, where the design without
    the DC block holds it about 10 V off null (x the path's gain)."""
    from sim_backend.rig_plant import FloorMotion
    fm = FloorMotion(DT, band_hz=(1.0, 50.0), rms_m=CFG.vibration.rms_m, seed=seed)
    fm.next_block(int(4.0 / DT))                    # the floor has been moving for 4 s
    a = fm.next_block(int(12.0 / DT))[:, 8] + 2e-5
    k_on = int(6.0 / DT)
    new, old = _slow_V(_switched_on(ff, a, k_on), k_on), _slow_V(_switched_on(ff, a, k_on, False), k_on)
    assert old > 8.0 and new < 0.25 * old, (new, old)


def test_the_start_transient_is_no_larger_than_without_the_block(ff):
    """The floor already moving when the filters start reads to the double integration as an initial velocity
    (a transient of its slow modes). The DC block starts at switch-on, so it adds no slow mode of its own from the
    loop's start: switched on 6 s in, over floors moving 2, 4 and 8 s before the start, the command's largest slow
    part is no larger than without the block, and typically the same (a first-order high-pass run from the start
    held it volts larger and stopped `rig hil` at the valve clamp)."""
    from sim_backend.rig_plant import FloorMotion
    k_on = int(6.0 / DT)
    new, old = [], []
    for seed in (1, 2, 3, 5):
        for before_s in (2.0, 4.0, 8.0):
            fm = FloorMotion(DT, band_hz=(1.0, 50.0), rms_m=CFG.vibration.rms_m, seed=seed)
            fm.next_block(int(before_s / DT))
            a = fm.next_block(int(10.0 / DT))[:, 8]
            new.append(_slow_V(_switched_on(ff, a, k_on), k_on))
            old.append(_slow_V(_switched_on(ff, a, k_on, False), k_on))
    new, old = np.array(new), np.array(old)
    assert new.max() <= 1.05 * old.max() and np.median(new / old) < 1.1, (new, old)


def test_bad_roll_off_order():
    with pytest.raises(ValueError, match="lowpass_order"):
        FeedforwardFilter(feedforward_params_from_config(CFG).with_(lowpass_order=4), DT)


class SineFloor:
    """x_g = env(t) amp sin(w t) at the masked mounts (FloorMotion's next_block API), fading in over ramp_s
    (env = (1 - cos(pi t / ramp_s)) / 2) so that the floor starts from rest, and its exact acceleration (what an
    ideal floor accelerometer reads)."""

    def __init__(self, f_hz, amp_m, mask, ramp_s=1.0):
        self.w, self.amp, self.mask, self.T = 2 * math.pi * f_hz, amp_m, np.asarray(mask, dtype=float), ramp_s
        self.k = 0

    def _env(self, t):
        c = np.pi / self.T
        on = t < self.T
        e = np.where(on, 0.5 * (1 - np.cos(c * t)), 1.0)
        de = np.where(on, 0.5 * c * np.sin(c * t), 0.0)
        dde = np.where(on, 0.5 * c * c * np.cos(c * t), 0.0)
        return e, de, dde

    def next_block(self, n):
        t = (self.k + np.arange(n)) * DT
        self.k += n
        e, de, _ = self._env(t)
        s, c = np.sin(self.w * t), np.cos(self.w * t)
        x = self.amp * (e * s)[:, None] * self.mask
        v = self.amp * (de * s + e * self.w * c)[:, None] * self.mask
        return np.ascontiguousarray(np.hstack([x, v]))

    def accel(self, k):
        t = np.array([k * DT])
        e, de, dde = self._env(t)
        s, c = math.sin(self.w * t[0]), math.cos(self.w * t[0])
        return self.amp * float(dde[0] * s + 2 * de[0] * self.w * c - e[0] * self.w ** 2 * s) * self.mask


def _table_amplitude(f_hz, fb, ff, settle_s=2.5, measure_s=1.0):
    floor = SineFloor(f_hz, 1e-6, [1, 0, 0, 0])
    plant = RigPlant(CFG, DT, floor=floor, accel_noise_mps2=0.0, stroke_noise_m=0.0)
    st = fb.initial_state() if fb is not None else None
    fs = ff.initial_state(on=True) if ff is not None else None
    n0, n1 = int(settle_s / DT), int(round(round(measure_s * f_hz) / f_hz / DT))
    table = np.empty(n1)
    u_apply = 0.0
    for k in range(n0 + n1):
        u = 0.0
        if fb is not None:
            u, st = fb.step(st, (plant.accel_mps2[0], plant.stroke_m[0]), DT)
        if ff is not None:
            u += ff.step(fs, floor.accel(k)[0], DT)[0]
        plant.step([u_apply, 0.0, 0.0, 0.0])              # computed at t_k, acts from t_k+1
        u_apply = u
        j = k - n0 + 1
        if 0 <= j < n1:
            table[j] = plant.table_m
    t = np.arange(n1) * DT
    A = np.column_stack([np.cos(2 * np.pi * f_hz * t), np.sin(2 * np.pi * f_hz * t), np.ones_like(t), t])
    c = np.linalg.lstsq(A, table, rcond=None)[0]
    return math.hypot(c[0], c[1])


@pytest.mark.parametrize("f_hz", [7.0, 41.0])
def test_time_domain_feedforward_matches_analysis(f_hz):
    """Front-left: feedback + feedforward in lockstep with the plant attenuates as siso(..., ff) predicts,
    and the feedforward adds more than 10 dB to the feedback alone."""
    fb = make_isolation_controllers(CFG, DT)[0]
    ff = make_feedforward_filters(CFG, DT)[0]
    passive = _table_amplitude(f_hz, None, None)
    both = _table_amplitude(f_hz, fb, ff)
    rig = DiscreteRig(CFG, DT, np.array([f_hz]))
    o = I_TABLE + 1
    r_fb, r_both = siso(rig, fb, 0), siso(rig, fb, 0, ff=ff)
    pred_both = float(attenuation_db(r_both["tr_passive"][:, o], r_both["tr_controlled"][:, o])[0])
    pred_fb = float(attenuation_db(r_fb["tr_passive"][:, o], r_fb["tr_controlled"][:, o])[0])
    assert 20 * math.log10(passive / both) == pytest.approx(pred_both, abs=1.0)
    assert pred_both > pred_fb + 10.0

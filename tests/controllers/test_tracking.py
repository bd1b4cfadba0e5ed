"""The tracking controller (paper Fig. 4 PID with the reference generated in the law and fed forward): the
compiled law against the plain reference, the design figures of the configured gains, reference requests
(grammar, profile files, checks that refuse instead of clamping) and bumpless reference changes."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers import tracking as T
from controllers.reference import load_profile, parse_reference
from controllers.tracking import (bandwidth_hz, loop_margins, preview_periods, track_step, tracking_from_config,
                                  tracking_response)
from rig.config import Config, config_from_dict
from rig.errors import RigError
from sim_backend.linear import ActuatorParams
from tests.controllers.reference import track_step as reference_step

DT = 1.0 / 5000.0
CFG = Config()
ACT = ActuatorParams.from_config(CFG)


def _ctrl(**controller):
    cfg = config_from_dict({"controller": controller}) if controller else CFG
    return tracking_from_config(cfg, DT)


def test_configured_pid_meets_fig4_and_the_margins():
    """Paper Fig. 4: bandwidth >= ~95 Hz (-3 dB), flat (within 1 dB) below it; GM >= 6 dB, PM >= 45 deg on the
    discrete loop (ZOH, one period of delay)."""
    c = _ctrl()
    f = np.geomspace(0.5, 2499.0, 6000)
    T_ = tracking_response(ACT, c, f)
    db = 20 * np.log10(np.abs(T_))
    assert bandwidth_hz(f, T_) >= 95.0
    assert db.max() < 1.0 and db[f < 65].min() > -1.0
    gm, pm = loop_margins(ACT, c, f)
    assert gm >= 6.0 and pm >= 45.0


def test_preview_covers_the_valve_and_the_loop_delay():
    """About 2 zeta / w_nv (2.5 ms) plus 1.5 periods: 13-16 periods at 5 kHz, 3-5 at 500 Hz (two periods)."""
    assert 13 <= preview_periods(ACT, DT, 1) <= 16
    assert 3 <= preview_periods(ACT, 2e-3, 2) <= 5
    assert preview_periods(ACT, DT, 3) > preview_periods(ACT, DT, 1)


def _run(c, requests, n, x_of_k):
    """The compiled law and the plain reference side by side; requests: {period: Reference}."""
    sc = np.array(c.take_over(c.initial_state(), 0.0, 0.0))
    sp = list(sc)
    cf = c.coefficients()
    uc, up = np.empty(n), np.empty(n)
    for k in range(n):
        if k in requests:
            sc = np.array(c.apply(sc.tolist(), requests[k], cf))
            sp = c.apply(sp, requests[k], cf)
        x = x_of_k(k, uc[k - 1] if k else 0.0)
        uc[k] = track_step(sc, cf, x)
        up[k] = reference_step(c, sp, x, cf)
    return uc, up, sc, sp


def test_compiled_law_equals_the_reference_through_every_kind_of_reference(tmp_path):
    prof = tmp_path / "p.csv"
    t = np.arange(0, 0.2, 0.001)
    prof.write_text("time_s,position_m\n" + "\n".join(f"{a:.4f},{3e-6 + 2e-6 * math.sin(40 * a):.6e}" for a in t))
    c = _ctrl()
    reqs = {10: parse_reference("setpoint:x=4um", DT), 700: parse_reference("sine:amp=3um,freq=20,seconds=0.1", DT),
            1500: parse_reference("step:amp=-2um", DT),
            2000: parse_reference("chirp:amp=0.5um,f0=5,f1=60,duration=0.2", DT),
            2600: parse_reference(f"csv:{prof}", DT), 3200: parse_reference("sine:amp=2um,freq=7", DT),
            3500: parse_reference("hold", DT)}
    rng = np.random.default_rng(1)
    noise = 2e-8 * rng.standard_normal(4200)
    state = {"x": 0.0}

    def plant(k, u):             # a first-order actuator (the DC gain and lag of Table 1), one period late
        a = math.exp(-ACT.lag_corner * DT)
        state["x"] = a * state["x"] + (1 - a) * ACT.dc_gain_m_per_V * u
        return state["x"] + noise[k]
    uc, up, sc, sp = _run(c, reqs, 4200, plant)
    assert np.array_equal(uc, up)                          # the same operations, bit for bit
    assert np.array_equal(sc, np.array(sp))
    assert np.abs(uc).max() > 1.0                          # it did drive the valve


@settings(max_examples=25, deadline=None)
@given(amp=st.floats(0.1e-6, 5e-6), freq=st.floats(0.5, 40.0), x0=st.floats(-10e-6, 10e-6),
       at=st.integers(1, 400), delay=st.integers(0, 3))
def test_compiled_law_equals_the_reference_property(amp, freq, x0, at, delay):
    c = _ctrl(track_delay_periods=delay)
    ref = parse_reference(f"sine:amp={amp!r}m,freq={freq!r},offset={x0!r}m", DT)
    uc, up, _, _ = _run(c, {at: ref}, 600, lambda k, u: 1e-7 * math.sin(0.01 * k))
    assert np.array_equal(uc, up)


def test_reference_never_jumps_when_requests_change_mid_waveform():
    """A new reference starts from the current lead value and rate: the reference the loop closes on moves by
    at most its rate limit per period, even when a sine is cut at its fastest point."""
    c = _ctrl()
    reqs = {0: parse_reference("sine:amp=10um,freq=5", DT)}
    reqs.update({k: parse_reference(t, DT) for k, t in ((2750, "hold"), (3100, "sine:amp=5um,freq=9,offset=2um"),
                                                        (3600, "setpoint:x=-3um"), (3650, "step:amp=1um"))})
    cf = c.coefficients()
    s = np.array(c.take_over(c.initial_state(), 0.0, 0.0))
    r = []
    for k in range(5000):
        if k in reqs:
            s = np.array(c.apply(s.tolist(), reqs[k], cf))
        track_step(s, cf, s[T._R])                          # a perfect plant: the error stays zero
        r.append(s[T._R])
    v = np.diff(r) / DT
    assert np.abs(v).max() <= c.ref.rate_m_per_s * 1.0001
    assert np.abs(np.diff(v)).max() / DT <= 2 * c.ref.accel_m_per_s2 + 2 * math.pi * 9 * 5e-6 * 2 * math.pi * 9 * 1.1


@pytest.mark.parametrize("text,match", [
    ("setpoint:x=30um", r"outside what the actuator can hold: \+-24\.1 um"),
    ("setpoint:x=-1.2mm", "outside the stroke limit"),
    ("sine:amp=10um,freq=20", "above the reference rate limit"),
    ("sine:amp=20um,freq=3,offset=10um", "needs .* V at the valve"),
    ("step:amp=30um", "outside what the actuator can hold"),
])
def test_references_the_actuator_cannot_follow_are_refused_in_one_line(text, match):
    c = _ctrl()
    with pytest.raises(RigError, match=match) as e:
        c.check(parse_reference(text, DT), c.take_over(c.initial_state(), 0.0, 0.0))
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("text", ["setpoint:x=24um", "sine:amp=10um,freq=5", "hold", "step:amp=2um",
                                  "chirp:amp=0.7um,f0=0.5,f1=100,duration=20", "sine:amp=1um,freq=70"])
def test_references_within_reach_are_accepted(text):
    c = _ctrl()
    c.check(parse_reference(text, DT), c.take_over(c.initial_state(), 0.0, 0.0))


def test_hold_range_is_the_leakage_static_range():
    """DC gain 2.68 um/V (PHYSICS_NOTES): +-26.8 um at the 10 V clamp, 90 % of it by default."""
    assert _ctrl().hold_range_m() == pytest.approx(0.9 * 10 * 2.680e-6, rel=2e-3)
    assert _ctrl(track_headroom=1.0).hold_range_m() == pytest.approx(26.8e-6, rel=2e-3)


@pytest.mark.parametrize("text,match", [
    ("wobble:amp=1um", "unknown kind 'wobble'"), ("sine:amp=1um", "missing freq"),
    ("sine:amp=1um,freq=-2", "must be > 0"), ("sine:amp=lots,freq=2", "is not a number"),
    ("sine:amp=1um,freq=2,phase=3", "unknown key 'phase'"), ("chirp:amp=1um,f0=10,f1=5,duration=2", "f0 < f1"),
    ("csv:", "expected csv:FILE"), ("csv:/nonexistent/p.csv", "profile file not found"),
    ("sine:amp=10um,freq=5,freq=6", "freq given twice")])
def test_reference_text_errors_name_what_is_wrong(text, match):
    with pytest.raises(RigError, match=match):
        parse_reference(text, DT)


def test_reference_units():
    assert parse_reference("setpoint:x=5um", DT).target_m == pytest.approx(5e-6)
    assert parse_reference("setpoint:0.005mm", DT).target_m == pytest.approx(5e-6)
    assert parse_reference("setpoint:x=-250nm", DT).target_m == pytest.approx(-2.5e-7)
    r = parse_reference("sine:amp=2um,freq=5Hz,seconds=0.3", DT)
    assert (r.amp_m, r.f0_hz, r.span_s) == (2e-6, 5.0, pytest.approx(0.4))        # whole cycles


def test_profile_file_errors_name_the_file_and_row(tmp_path):
    p = tmp_path / "prof.csv"
    p.write_text("time_s,position_m\n0,0\n0.1,1e-6\n0.1,2e-6\n")
    with pytest.raises(RigError, match=r"prof\.csv: time_s not increasing at row 3"):
        load_profile(p, DT)
    p.write_text("t,x\n0,0\n")
    with pytest.raises(RigError, match="expected columns time_s and position_m"):
        load_profile(p, DT)
    p.write_text("position_m,time_s\n0,0\n1e-6,0.01\n")
    prof = load_profile(p, DT)
    assert len(prof) == 51 and prof[-1] == pytest.approx(1e-6) and prof[25] == pytest.approx(0.5e-6)
    with pytest.raises(RigError, match="longer than controller.track_profile_s"):
        load_profile(p, DT, max_s=0.005)


@settings(max_examples=50, deadline=None)
@given(t=st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=2, max_size=20),
       x=st.lists(st.floats(-1e-3, 1e-3, allow_nan=False), min_size=2, max_size=20))
def test_profile_loader_takes_or_refuses_in_one_line(tmp_path_factory, t, x):
    p = tmp_path_factory.mktemp("prof") / "p.csv"
    n = min(len(t), len(x))
    p.write_text("time_s,position_m\n" + "\n".join(f"{a!r},{b!r}" for a, b in zip(t[:n], x[:n])))
    try:
        prof = load_profile(p, 0.05)
    except RigError as e:
        assert str(p) in str(e) and "\n" not in str(e)
        return
    assert np.all(np.isfinite(prof)) and len(prof) >= 1


CSV_TEXT = st.lists(st.one_of(
    st.just("time_s,position_m"), st.just("position_m,time_s"), st.just("# note"), st.just(""),
    st.text(alphabet="0123456789.,-+eE naNinf\"#\t", max_size=24),
    st.tuples(st.floats(allow_nan=True, allow_infinity=True), st.floats(allow_nan=True, allow_infinity=True)).map(
        lambda ab: f"{ab[0]!r},{ab[1]!r}")), max_size=12).map("\n".join)


@settings(max_examples=200, deadline=None)
@given(text=CSV_TEXT)
def test_any_profile_text_is_a_profile_or_one_line_naming_the_file(tmp_path_factory, text):
    """Whatever a CSV file holds (headers in any order, comments, blanks, nan/inf, ragged rows, junk), the
    loader returns a finite profile or refuses in one line that names the file; never another exception."""
    p = tmp_path_factory.mktemp("prof") / "p.csv"
    p.write_text(text)
    try:
        prof = load_profile(p, 0.01, max_s=60.0)
    except RigError as e:
        assert str(p) in str(e) and "\n" not in str(e)
        return
    assert prof.ndim == 1 and len(prof) >= 1 and np.all(np.isfinite(prof))


@settings(max_examples=100, deadline=None)
@given(steps=st.lists(st.integers(1, 40), min_size=1, max_size=12),
       x=st.lists(st.floats(-2e-5, 2e-5, allow_nan=False), min_size=13, max_size=13), t0=st.integers(-50, 50))
def test_a_profile_passes_through_its_points_and_is_linear_between(tmp_path_factory, steps, x, t0):
    """Times on the loop's grid: the resampled profile holds every given position at its time (from the first
    time on, whatever it is) and moves linearly between them."""
    dt = 0.002
    k = np.concatenate([[0], np.cumsum(steps)])
    t = (t0 + k) * dt
    xs = np.array(x[:len(k)])
    p = tmp_path_factory.mktemp("prof") / "p.csv"
    p.write_text("time_s,position_m\n" + "\n".join(f"{float(a)!r},{float(b)!r}" for a, b in zip(t, xs)))
    prof = load_profile(p, dt)
    assert len(prof) == k[-1] + 1
    assert prof[k] == pytest.approx(xs, abs=1e-12)
    mid = (k[:-1] + k[1:]) / 2
    whole = mid == np.floor(mid)
    assert prof[mid[whole].astype(int)] == pytest.approx(((xs[:-1] + xs[1:]) / 2)[whole], abs=1e-12)

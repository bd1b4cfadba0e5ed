"""Diagnosis on recordings with the habits of real rigs (issue 12): sensor offset, drift and pickup fitted as
sensor terms and never named as physics; the two sensors tell pickup from a force; quantisation, mid-run starts,
other excitations and sample rates. Short simulated recordings (20-40 s), a few seconds each."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rig.diagnose import prove
from rig.diagnose.catalogue.periodic_disturbance import force_for_line
from rig.diagnose.engine import diagnose
from rig.diagnose.report import diagnosis_dict, fit_columns
from rig.diagnose.report import effect_evidence, summary
from rig.recordings.recording import Recording
from sim_backend.linear import ActuatorParams

P0 = ActuatorParams()
LIN = {"K_L": 6.4e8, "K_Q": 2.02e-6, "w_nv": 545.0, "zeta": 0.62, "K_C": 6.9e-11}


def _case(effects, sensor=None, excitation=None, duration_s=20.0, fs=1000.0, pre_s=0.0, hidden=None, seed=4):
    exc = excitation or {"kind": "linear_chirp", "f0_hz": 0.1, "f1_hz": 100.0, "amplitude_V": 2.0}
    c = prove.Case(name="habit", effects=effects, linear=LIN, fs_hz=fs, duration_s=duration_s, seed=seed,
                   hidden=hidden or {}, excitation=exc, sensor={"position_noise_m": 2e-8, **(sensor or {})},
                   pre_s=pre_s)
    return c, prove.simulate_case(c)


def _pickup(*lines):
    return [{"frequency_hz": f, "amplitude": a, "phase_rad": ph} for f, a, ph in lines]


def test_offset_drift_and_pickup_are_sensor_terms_not_physics():
    c, rec = _case({"transport_delay": {"delay_s": 1.5e-3}},
                   {"offset_m": 5e-6, "drift_m_per_s": 40e-9,
                    "position_lines": _pickup((50.02, 8e-8, 0.3), (100.04, 3e-8, -1.0))})
    d = diagnose(rec, P0)
    assert d.names() == ["transport_delay"], summary(d)
    s = d.sensor
    assert abs(s.offset_m - 5e-6) < 0.2e-6 and abs(s.drift_m_per_s - 40e-9) < 5e-9
    got = {round(l.frequency_hz): l for l in s.lines}
    assert set(got) == {50, 100}
    for f, amp in ((50.02, 8e-8), (100.04, 3e-8)):
        line = got[round(f)]
        assert abs(line.frequency_hz - f) / f < 0.001 and line.source == "pickup"
        assert abs(line.amplitude - amp) < 0.15 * amp
        assert "not in acceleration" in line.evidence
    assert d.fit.augmented.residual_rms_m < 1.3 * c.noise_m()
    doc = diagnosis_dict(d, rec)
    assert set(doc["sensor"]) >= {"offset_m", "drift_m_per_s", "lines"}
    assert {"frequency_hz", "amplitude_m"} <= set(doc["sensor"]["lines"][0])
    # fit.csv models the measurement as recorded: measured - augmented is the noise
    cols = fit_columns(d, rec)
    used = cols[:, 6] > 0
    assert np.std((cols[:, 1] - cols[:, 4])[used]) < 1.3 * c.noise_m()
    assert abs(np.mean(cols[:, 5]) - (5e-6 + 40e-9 * rec.duration_s / 2)) < 0.3e-6   # the sensor column


def test_force_line_is_physics_pickup_line_is_not():
    """A 50 Hz force moves the mass (both sensors), a 60 Hz pickup only the transducer."""
    f_n = force_for_line(P0.with_(**LIN), 50.0, 8e-8)
    c, rec = _case({"periodic_disturbance": {"frequency_hz": 50.0}},
                   {"position_lines": _pickup((60.0, 8e-8, 0.5))},
                   hidden={"periodic_disturbance": {"force_n": f_n, "phase_rad": 0.2}})
    d = diagnose(rec, P0)
    assert d.names() == ["periodic_disturbance"], summary(d)
    e = d.effects[0]
    assert abs(e.parameters["frequency_hz"] - 50.0) < 0.05
    assert "both sensors" in effect_evidence(e, d.mismatch)
    assert [round(l.frequency_hz) for l in d.sensor.lines] == [60]
    assert d.sensor.lines[0].source == "pickup"


def test_without_accelerometer_a_mains_line_is_taken_as_pickup():
    c, rec = _case({}, {"position_lines": _pickup((50.0, 6e-8, 0.0))})
    rec = Recording.from_signals(rec.valve_cmd_V, rec.position_m, np.zeros(rec.n), fs_hz=rec.fs_hz)
    d = diagnose(rec, P0)
    assert d.effects == (), summary(d)
    (line,) = d.sensor.lines
    assert line.source == "pickup (assumed)" and "mains" in line.evidence
    assert not d.sensor.accel.usable and "constant" in d.sensor.accel.note


def test_quantised_transducer_sets_the_noise_floor():
    q = 6e-8
    c, rec = _case({}, {"quant_step_m": q, "offset_m": -3e-6})
    d = diagnose(rec, P0)
    assert d.effects == (), summary(d)
    assert d.sensor.quantisation_step_m == pytest.approx(q, rel=0.01)
    assert d.noise_m == pytest.approx(math.sqrt(2e-8 ** 2 + q * q / 12), rel=0.15)
    assert d.verdict.status == "explained"


def test_multisine_empty_lines_detect_nonlinearity():
    exc = {"kind": "odd_multisine", "f0_hz": 0.2, "f1_hz": 100.0, "amplitude_V": 2.2, "period_s": 5.0, "seed": 3}
    _, clean = _case({}, excitation=exc, duration_s=30.0)
    d0 = diagnose(clean, P0)
    assert d0.command.kind == "multisine" and d0.effects == (), summary(d0)
    ms0 = d0.mismatch.multisine_lines
    assert abs(ms0["odd_z"]) < 5 and abs(ms0["even_z"]) < 5 and ms0["odd_over_noise"] < 1.1
    _, sat = _case({"valve_saturation": {"limit_ma": 3.0}}, excitation=exc, duration_s=30.0)
    d1 = diagnose(sat, P0)
    assert d1.names() == ["valve_saturation"], summary(d1)
    ms = d1.mismatch.multisine_lines
    assert ms["odd_z"] > 20 and ms["odd_over_noise"] > 1.5 and abs(ms["even_z"]) < 5    # odd, not even
    assert "unexcited odd lines" in effect_evidence(d1.effects[0], d1.mismatch)


@pytest.mark.parametrize("effect, drop", [("valve_saturation", "top"), ("valve_deadband", "bottom")])
def test_gain_by_level_separates_saturation_from_deadband(effect, drop):
    exc = {"kind": "multilevel_chirp", "f0_hz": 0.1, "f1_hz": 100.0, "levels_V": [0.5, 1.5, 3.0]}
    prm = {"valve_saturation": {"limit_ma": 4.5}, "valve_deadband": {"width_ma": 0.4}}[effect]
    _, rec = _case({effect: prm}, excitation=exc, duration_s=40.0)
    d = diagnose(rec, P0)
    assert d.names() == [effect], summary(d)
    rows = d.evidence["levels"]["rows"]
    g = [r["gain_measured"] for r in rows]
    assert len(g) == 3
    lowest = int(np.argmin(g))
    assert lowest == (2 if drop == "top" else 0), g
    assert drop in d.evidence["levels"]["finding"]
    # the augmented model reproduces the gain by level
    assert max(abs(r["gain_measured"] - r["gain_augmented"]) for r in rows) < 0.01


def test_mid_run_start_drops_the_transient_and_says_so():
    c, rec = _case({"transport_delay": {"delay_s": 2e-3}}, duration_s=20.0, pre_s=11.3)
    assert abs(rec.valve_cmd_V[0]) > 0.1
    d = diagnose(rec, P0)
    assert d.names() == ["transport_delay"], summary(d)
    assert abs(d.effects[0].parameters["delay_s"] - 2e-3) < 0.2 * 2e-3
    assert d.sensor.start_transient_s > 0 and not d.used[: int(0.5 * rec.fs_hz)].any()
    assert any("mid-run" in n for n in d.mismatch.notes)


@pytest.mark.parametrize("fs, kind", [(500.0, "log_sweep"), (5000.0, "band_noise"), (2000.0, "steps")])
def test_other_rates_and_excitations_find_a_stand_mode(fs, kind):
    exc = {"kind": kind, "amplitude_V": 2.0}
    if kind != "steps":
        exc.update(f0_hz=0.2, f1_hz=100.0)
    if kind != "log_sweep":
        exc["seed"] = 2
    truth = {"base_resonance": {"frequency_hz": 47.0, "damping_ratio": 0.03}}
    _, rec = _case(truth, {"offset_m": 2e-6, "drift_m_per_s": -20e-9}, excitation=exc, fs=fs,
                   hidden={"base_resonance": {"mass_kg": 220.0}}, duration_s=20.0)
    d = diagnose(rec, P0)
    assert d.names() == ["base_resonance"], summary(d)
    assert abs(d.effects[0].parameters["frequency_hz"] - 47.0) < 0.05 * 47.0

"""The blind-case generator and the grading of `rig prove` (case draws, confusion matrix, score)."""
from __future__ import annotations

import numpy as np
import pytest

from rig.diagnose import grading, prove
from rig.diagnose.catalogue.periodic_disturbance import force_for_line
from tests.rig.diagnose import typed
from sim_backend.actuator import Effects, simulate_stand
from sim_backend.linear import IDENTIFIED, ActuatorParams

P0 = ActuatorParams()


def test_draw_cases_deterministic_and_mixed():
    a = prove.draw_cases(30, seed=1)
    b = prove.draw_cases(30, seed=1)
    c = prove.draw_cases(30, seed=2)
    assert [x.effects for x in a] == [x.effects for x in b] and [x.linear for x in a] == [x.linear for x in b]
    assert [x.effects for x in a] != [x.effects for x in c]
    counts = [len(x.effects) for x in a]
    assert counts.count(0) >= 0.2 * len(a)                  # a decent share of clean cases
    assert counts.count(2) >= 5 and max(counts) == 2         # pairs must be found too
    used = {name for x in a for name in x.effects}
    assert used == set(grading.CATALOGUE)                       # every effect of the catalogue is tried
    assert len({x.name for x in a}) == len(a)


def test_draw_cases_physical_ranges():
    for case in prove.draw_cases(60, seed=5):
        for k in IDENTIFIED:                                   # linear parameters moved +-15 %
            assert 0.85 <= case.linear[k] / getattr(P0, k) <= 1.15
        assert case.fs_hz in (1000.0, 2000.0) and 1.8 <= case.amplitude_V <= 2.5
        e = case.effects
        if "transport_delay" in e:
            assert 0.5e-3 <= e["transport_delay"]["delay_s"] <= 3e-3
        if "base_resonance" in e:
            assert 30 <= e["base_resonance"]["frequency_hz"] <= 90
            assert 0.02 <= e["base_resonance"]["damping_ratio"] <= 0.05
        if "valve_saturation" in e:
            peak_ma = P0.K_v * case.amplitude_V
            assert 0.5 * peak_ma <= e["valve_saturation"]["limit_ma"] <= 0.85 * peak_ma
        if "valve_deadband" in e:
            assert 0.2 <= e["valve_deadband"]["width_ma"] <= 1.0
        if "coulomb_friction" in e:
            assert 150 <= e["coulomb_friction"]["force_n"] <= 600
        if "periodic_disturbance" in e:
            assert 10 <= e["periodic_disturbance"]["frequency_hz"] <= 90
            assert set(e["periodic_disturbance"]) == {"frequency_hz"}      # force/phase stay hidden
            assert case.hidden["periodic_disturbance"]["force_n"] > 0


@pytest.mark.parametrize("f_hz", [12.0, 55.0, 88.0])
def test_disturbance_force_gives_requested_line(f_hz):
    """The drawn force puts a line of the requested amplitude on the position (checked by a longer run)."""
    p = P0.with_(K_L=7.2e8)
    want_m = 1e-7
    force = force_for_line(p, f_hz, want_m)
    fs, n = 2000.0, 8000
    y = simulate_stand(p, np.zeros(n), fs, Effects(disturbance_frequency_hz=f_hz, disturbance_force_n=force))
    t = np.arange(n)[n // 2:] / fs
    X = np.c_[np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t), np.ones_like(t)]
    c, *_ = np.linalg.lstsq(X, y["position_m"][n // 2:], rcond=None)
    assert np.hypot(c[0], c[1]) == pytest.approx(want_m, rel=0.03)
    assert 10.0 < force < 5000.0                     # hundreds of newtons: a neighbouring machine, not a crash


def test_simulated_case_matches_truth():
    case = prove.Case(name="t", effects={"transport_delay": {"delay_s": 1e-3}}, linear={"K_L": 7e8},
                      duration_s=2.0, fs_hz=2000.0, seed=4)
    rec = prove.simulate_case(case)
    assert rec.n == 4000 and rec.fs_hz == pytest.approx(2000.0)
    clean = simulate_stand(P0.with_(K_L=7e8), rec.valve_cmd_V, 2000.0, Effects(delay_s=1e-3))["position_m"]
    resid = rec.position_m - clean
    assert np.std(resid) == pytest.approx(prove.POSITION_NOISE_M, rel=0.1)   # only the sensor noise


def _row(truth, named, errors=None, aug=1.0):
    return {"truth": sorted(truth), "named": sorted(named), "right": set(truth) == set(named),
            "parameter_errors": errors or {}, "residual_over_noise": {"augmented": aug}, "elapsed_s": 1.0}


def test_confusion_and_score_by_hand():
    rows = [
        _row([], []),                                                     # clean, right
        _row([], ["coulomb_friction"]),                                   # invented on a clean case
        _row(["transport_delay"], ["transport_delay"], {"transport_delay.delay_s": 0.05}),
        _row(["valve_deadband"], ["coulomb_friction"]),                   # mistaken for friction
        _row(["base_resonance", "periodic_disturbance"], ["base_resonance"],
             {"base_resonance.frequency_hz": 0.08}, aug=2.0),             # missed one of a pair
    ]
    m = grading.confusion(rows)
    assert m["none"]["none"] == 1
    assert m["none"]["coulomb_friction"] == 1
    assert m["transport_delay"]["transport_delay"] == 1
    assert m["valve_deadband"]["coulomb_friction"] == 1
    assert m["base_resonance"]["base_resonance"] == 1
    assert m["periodic_disturbance"]["none"] == 1
    assert sum(sum(r.values()) for r in m.values()) == 6
    s = grading.score(rows)
    assert (s["cases"], s["right"], s["clean_cases"], s["invented_on_clean"]) == (5, 2, 2, 1)
    assert s["delays"] == {"n": 1, "within": 1, "tolerance": 0.2, "worst": 0.05}
    assert s["frequencies"]["n"] == 1 and s["frequencies"]["within"] == 0
    assert s["residual_within_1.3_noise"]["within"] == 4
    text = grading.score_text(s)
    assert "2/5 named right" in text and "invented on clean cases: 1/2" in text
    md = grading.confusion_markdown(m)
    assert md.count("\n") == 2 + len(grading.CATALOGUE) + 1


def test_score_gives_the_cpu_time_per_case():
    """The speed targets are in CPU time per case (issue 26): median and max over the cases that measured it,
    printed beside the wall time; rows without it (a folder graded before) leave it out."""
    rows = [{**_row([], []), "cpu_s": c} for c in (2.0, 9.0, 4.0)] + [_row([], [])]
    s = grading.score(rows)
    assert s["cpu_seconds_per_case"] == {"median": 4.0, "max": 9.0, "n": 3}
    assert "CPU median 4.0 s, max 9.0 s" in grading.score_text(s)
    assert "CPU" not in grading.score_text(grading.score([_row([], [])]))


def test_grade_parameter_errors():
    D = typed.diagnosis({"transport_delay": {"delay_s": 2.2e-3}, "valve_saturation": {"limit_ma": 3.0}},
                        fit=(typed.figures(0.3), typed.figures(0.1), typed.figures(0.02, 1.0)),
                        params_refit={"K_L": 7.7e8})
    r = grading.grade("x", {"transport_delay": {"delay_s": 2e-3}}, D, true_linear={"K_L": 7e8})
    assert r["right"] is False and r["named"] == ["transport_delay", "valve_saturation"]
    assert r["parameter_errors"] == {"transport_delay.delay_s": pytest.approx(0.1)}
    assert r["linear_max_error"] == pytest.approx(0.1)
    assert r["nrmse"] == {"nominal": 0.3, "refit": 0.1, "augmented": 0.02}

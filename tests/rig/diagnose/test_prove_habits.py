"""`rig prove --habits`: the blind set draws the habits of real recordings with random sizes, simulates them, and
grades the sensor side too (pickup lines within 1 %, sensor artefacts named as physics, the score by habit)."""
from __future__ import annotations

import numpy as np
import pytest

from rig.diagnose import grading, prove
from tests.rig.diagnose import typed


def test_habit_draws_are_deterministic_and_cover_the_habits():
    a = prove.draw_cases(60, seed=11, duration_s=200.0, habits=True)
    b = prove.draw_cases(60, seed=11, duration_s=200.0, habits=True)
    assert [(c.sensor, c.excitation, c.pre_s, c.fs_hz, c.duration_s) for c in a] == \
           [(c.sensor, c.excitation, c.pre_s, c.fs_hz, c.duration_s) for c in b]
    kinds = {c.excitation["kind"] for c in a}
    assert kinds == set(prove.EXCITATIONS)
    assert {c.fs_hz for c in a} == set(prove.RATES_HZ)
    assert min(c.duration_s for c in a) >= 20.0 and max(c.duration_s for c in a) <= 200.0
    assert all(c.fs_hz * c.duration_s <= 6e5 + 1 for c in a)
    tags = {t.split(":")[0] for c in a for t in c.habits}
    assert {"offset", "drift", "pickup", "quantised", "mid-run", "accel-pickup", "adc-filter", "noise"} <= tags
    for c in a:
        s = c.sensor
        assert 0.5e-6 <= abs(s["offset_m"]) <= 20e-6 and 5e-9 <= abs(s["drift_m_per_s"]) <= 80e-9
        for ln in s.get("position_lines", []):
            base = 50.0 if abs(ln["frequency_hz"] / round(ln["frequency_hz"] / 50) - 50) < 0.2 else 60.0
            assert abs(ln["frequency_hz"] / round(ln["frequency_hz"] / base) / base - 1) < 0.0025
        if "periodic_disturbance" in c.effects:                     # a force line apart from the pickup
            f = c.effects["periodic_disturbance"]["frequency_hz"]
            assert all(abs(f - ln["frequency_hz"]) > 2.0 for ln in s.get("position_lines", []))
        assert c.noise_m() >= s["position_noise_m"]


def test_habit_case_is_simulated_as_drawn():
    case = prove.Case(name="h", effects={}, linear={}, fs_hz=500.0, duration_s=20.0, seed=3, pre_s=4.0,
                      excitation={"kind": "linear_chirp", "f0_hz": 0.1, "f1_hz": 100.0, "amplitude_V": 2.0},
                      sensor={"position_noise_m": 2e-8, "offset_m": 3e-6, "quant_step_m": 4e-8,
                              "position_lines": [{"frequency_hz": 50.0, "amplitude": 5e-8, "phase_rad": 0.0}]})
    rec = prove.simulate_case(case)
    assert rec.n == 10000 and rec.fs_hz == pytest.approx(500.0)
    full = prove.excitation_of(case).cmd_V
    np.testing.assert_allclose(rec.valve_cmd_V, full[2000:])                          # starts 4 s into the run
    k = rec.position_m / 4e-8
    assert np.allclose(k, np.round(k))                                                 # quantised
    assert case.noise_m() == pytest.approx(np.sqrt(4e-16 + 16e-16 / 12))


def test_grade_and_score_the_sensor_side():
    D = typed.diagnosis({"periodic_disturbance": {"frequency_hz": 100.0}}, lines_hz=(50.02, 150.2),
                        fit=(typed.figures(), typed.figures(), typed.figures(over=1.0, rms_m=2.4e-8)))
    r = grading.grade("x", {}, D, noise_m=2e-8, pickup_hz=[50.0, 100.0, 150.0], habits=["steps", "pickup:50Hzx3"],
                    duration_s=100.0, fs_hz=2000.0, elapsed_s=7.0)
    assert r["pickup_lines"]["within"] == 2 and r["pickup_lines"]["n"] == 3          # 100 Hz not reported
    assert r["residual_over_true_noise"] == pytest.approx(1.2)
    s = grading.score([r])
    # the 100 Hz line is missed (graded apart), the worst frequency error is over the lines found (150.2 Hz)
    assert s["sensor_named_as_physics"] == 1 and s["mains_lines"] == {
        "n": 3, "found": 2, "within_1pct": 2, "worst": pytest.approx(0.2 / 150.0, rel=1e-6),
        "missed": [{"case": "x", "frequency_hz": 100.0, "amplitude_m": None}]}
    assert s["by_habit"]["pickup"] == {"cases": 1, "right": 0, "invented": 1, "residual_ok": 1}
    assert s["seconds_per_100s_at_2khz"]["median"] == pytest.approx(7.0)       # a 100 s case at 2 kHz
    md = grading.habits_markdown(s)
    assert "| pickup | 1 | 0 | 1 | 1 |" in md and "| steps | 1 | 0 | 1 | 1 |" in md
    assert "| x | steps, pickup:50Hzx3 | none | periodic_disturbance | NO |" in grading.table_markdown([r])

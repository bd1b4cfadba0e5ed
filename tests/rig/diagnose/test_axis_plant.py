"""The diagnosis on other rigs' plants (issue 13): an EMPS-like electro-mechanical axis recorded in closed loop at
1 kHz (sim_backend.axis: real stick-slip friction, the published model and cascade), and a clean open-loop axis."""
import numpy as np
import pytest

from rig.diagnose.engine import diagnose
from rig.diagnose.report import diagnosis_dict, summary, summary_text
from rig.errors import RecordingError
from rig.plant.file import load_plant, parse_plant
from rig.recordings.recording import Recording
from sim_backend.axis import EMPS, Axis, Sensor, emps_like, simulate_axis
from tests.paths import REPO

pytestmark = pytest.mark.slow


def _rec(cmd, pos, unit="V"):
    rec = Recording.from_signals(cmd, pos, None, fs_hz=1000.0, source="axis")
    rec.command_unit = unit
    rec.accel_present = False
    return rec


def test_emps_like_closed_loop_names_friction_and_halves_the_residual():
    cmd, pos = emps_like()
    plant = load_plant(REPO / "docs" / "examples" / "emps_like.toml")
    d = diagnose(_rec(cmd, pos), plant)
    named = {e.name: e.parameters for e in d.effects}
    assert "coulomb_friction" in named, summary(d)
    assert abs(named["coulomb_friction"]["force_n"] / EMPS.coulomb_n - 1) < 0.25
    assert set(named) <= {"coulomb_friction", "constant_force"}, summary(d)     # nothing invented
    assert d.fit.augmented.residual_rms_m < 0.5 * d.fit.refit.residual_rms_m
    assert "Closed-loop data" in summary(d) and "pole at the origin" in " ".join(d.mismatch.notes)
    doc = diagnosis_dict(d)
    assert doc["plant"]["family"] == "mechanical_axis" and doc["plant"]["shooting"]["segments"] >= 20
    assert abs(doc["plant"]["augmented_linear"]["mass_kg"] / EMPS.mass_kg - 1) < 0.1


def test_clean_open_loop_axis_names_nothing():
    ax = Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0)
    rng = np.random.default_rng(4)
    from rig.excitation import band_noise
    u = band_noise(1000.0, 20.0, 0.3, 30.0, 40.0, seed=5).cmd_V
    cmd, pos = simulate_axis(ax, 1000.0, command=u, sensor=Sensor(step_m=1e-7, noise_m=2e-7, offset_m=3e-4, seed=2))
    plant = parse_plant({"family": "mechanical_axis", "input_unit": "N", "mass_kg": {"value": 25.0, "min": 5.0,
                         "max": 100.0}, "damping_n_s_per_m": {"value": 50.0, "min": 5.0, "max": 500.0}}, "clean.toml")
    d = diagnose(_rec(cmd, pos, "N"), plant)
    assert d.effects == (), summary(d)
    text = summary_text(d)           # the report speaks of this plant: its unit and its free parameters
    assert "its free parameters mass_kg, damping_n_s_per_m" in text and " N" in d.command.describe()
    assert "six parameters" not in text and " V" not in d.command.describe()
    assert d.fit.refit.residual_over_noise_holdout < 1.3
    assert abs(d.params_refit["mass_kg"] / 20.0 - 1) < 0.05 and rng is not None


def test_unit_mismatch_is_one_line():
    cmd, pos = emps_like()
    plant = parse_plant({"family": "mechanical_axis", "input_unit": "N", "mass_kg": 90.0,
                         "damping_n_s_per_m": 200.0}, "force.toml")
    with pytest.raises(RecordingError, match="command is in V but the plant .force.toml. takes input_unit = 'N'"):
        diagnose(_rec(cmd[:2000], pos[:2000]), plant)


def test_closed_loop_friction_with_a_deadband_is_named_by_the_pair_step():
    """Coulomb friction and an input deadband both stop the carriage near zero force: on a short closed-loop run
    each alone takes the other's share, the forward selection ends far from the noise, and the pair step (both
    fitted jointly from their first-round fits) must name both, with their sizes."""
    from rig.diagnose.prove_axis import _loop_for, _moves
    from sim_backend.axis import trapezoid_program
    plant = load_plant(REPO / "docs" / "examples" / "emps_like.toml")
    ax = Axis(mass_kg=78.0, damping_n_s_per_m=144.0, gain_n_per_unit=35.15, coulomb_n=6.3, deadband=0.14)
    ref = trapezoid_program(1000.0, _moves(np.random.default_rng(2), 8.0), 0.8, 0.3)[:8000]
    cmd, pos = simulate_axis(ax, 1000.0, reference=ref, loop=_loop_for(plant.values()),
                             sensor=Sensor(step_m=1e-7, noise_m=1.5e-7, offset_m=-3.7e-4, seed=3))
    d = diagnose(_rec(cmd, pos), plant)
    named = {e.name: e.parameters for e in d.effects}
    assert set(named) == {"coulomb_friction", "input_deadband"}, summary(d)
    assert abs(named["coulomb_friction"]["force_n"] / 6.3 - 1) < 0.1
    assert abs(named["input_deadband"]["width_V"] / 0.14 - 1) < 0.1
    pairs = [c for c in d.candidates if c.get("step") == "pair"]
    assert any(c["passed"] and set(c["effects"]) == set(named) for c in pairs), "the pair step did not find it"
    assert d.verdict.status in ("explained", "partly")


def test_a_stand_mode_at_the_edge_of_its_range_is_not_a_finding():
    """base_resonance with its damping ratio or base mass at a bound, or its frequency at the excited band's edge,
    fails the edge test on a plant file's axis; a mode inside its range passes; the eha plant does not run it."""
    from rig.diagnose.problem import ModelFit, Problem
    from rig.diagnose.search import _at_edge
    from sim_backend.linear import ActuatorParams
    plant = load_plant(REPO / "docs" / "examples" / "logger_axis.toml")
    n = 2000
    pb = Problem(np.sin(np.arange(n) / 50.0), np.zeros(n), 1000.0, plant, np.ones(n, bool), base_band=(5.0, 400.0))
    lo_m, hi_m = pb.effect_bounds("base_resonance")[2]

    def fit(f_hz, zeta, mass):
        return ModelFit(lin={}, fx={"base_resonance": {"frequency_hz": f_hz, "damping_ratio": zeta, "mass_kg": mass}},
                   rss_fit=1.0, rss_hold=1.0, k=3)
    inside = fit(60.0, 0.05, 20.0 * lo_m)
    assert not _at_edge(pb, inside, "base_resonance")
    assert _at_edge(pb, fit(161.0, 0.003, 20.0 * lo_m), "base_resonance")      # damping at its lower bound
    assert _at_edge(pb, fit(60.0, 0.05, hi_m), "base_resonance")                # base mass at its upper bound
    assert _at_edge(pb, fit(400.0, 0.05, 20.0 * lo_m), "base_resonance")       # at the band's edge
    assert not _at_edge(pb, fit(60.0, 0.05, hi_m), "coulomb_friction")         # only the stand mode
    eha = Problem(np.sin(np.arange(n) / 50.0), np.zeros(n), 1000.0, ActuatorParams(), np.ones(n, bool))
    assert pb.plant.axis_search and not eha.plant.axis_search


def test_velocity_output_axis_names_a_deadband_and_a_dead_time_in_samples():
    """A geared DC motor as its documentation has it: a voltage staircase in, the speed out at 100 Hz (a plant
    file's `output = "velocity"`), a dead zone of +-3.5 V and a dead time of 3 samples as a sampled model counts
    it (2 samples of delay plus the hold's one). Made by the diagnosis's own model of the axis: the plumbing of a
    speed output end to end, not the physics of the search."""
    from rig.diagnose.plants import model_for
    fs = 100.0
    rng = np.random.default_rng(3)
    u = np.repeat(rng.uniform(-10, 10, 60), 150)
    plant = parse_plant({"family": "mechanical_axis", "input_unit": "V", "output": "velocity",
                         "mass_kg": {"value": 0.05, "min": 0.001, "max": 10.0},
                         "damping_n_s_per_m": {"value": 0.1, "min": 0.001, "max": 100.0}, "gain_n_per_unit": 0.01},
                        "dc.toml")
    y = model_for(plant).simulate({"mass_kg": 0.02, "damping_n_s_per_m": 0.05}, u, fs,
                                  {"input_deadband": {"width_V": 3.5}, "transport_delay": {"delay_s": 0.02}})
    y = y + rng.normal(0, 0.002 * np.ptp(y), len(y))
    rec = Recording.from_signals(u, y, None, fs_hz=fs, source="dcmotor")
    rec.command_unit, rec.accel_present, rec.output_unit, rec.output_kind = "V", False, "m/s", "velocity"
    d = diagnose(rec, plant)
    named = {e.name: e.parameters for e in d.effects}
    assert set(named) == {"input_deadband", "transport_delay"}, summary(d)
    assert abs(named["input_deadband"]["width_V"] / 3.5 - 1) < 0.05
    assert abs(named["transport_delay"]["dead_time_samples"] - 3.0) < 0.25
    assert "m/s" in summary(d) and d.verdict.status == "explained"

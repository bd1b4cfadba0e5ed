"""The mechanics real axes have (issue 26): Stribeck friction and backlash, each one catalogue entry. A simulated
recording with the effect (sim_backend.axis: stick-slip with a breakaway, a load behind a gear's play) names it;
the same recording without it does not."""
import numpy as np
import pytest

from rig.diagnose import catalogue
from rig.diagnose.engine import diagnose
from rig.diagnose.prove_axis import _names, draw_axis_cases
from rig.diagnose.report import summary
from rig.excitation import band_noise
from rig.plant.file import load_plant, parse_plant
from rig.plant.zoh import play
from rig.recordings.recording import Recording
from sim_backend.axis import Axis, Sensor, simulate_axis
from tests.paths import REPO

PLANT = {"family": "mechanical_axis", "input_unit": "N", "mass_kg": {"value": 25.0, "min": 5.0, "max": 100.0},
         "damping_n_s_per_m": {"value": 50.0, "min": 5.0, "max": 500.0}}
PEAK_N = 40.0


def _diagnosed(duration_s: float = 20.0, **mechanics):
    """An open-loop axis of 20 kg under a 40 N band-noise force, an encoder of 0.1 um, diagnosed."""
    ax = Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0, **mechanics)
    u = band_noise(1000.0, duration_s, 0.3, 30.0, PEAK_N, seed=5).cmd_V
    cmd, pos = simulate_axis(ax, 1000.0, command=u, sensor=Sensor(step_m=1e-7, noise_m=2e-7, offset_m=3e-4, seed=2))
    rec = Recording.from_signals(cmd, pos, None, fs_hz=1000.0, source="axis")
    rec.command_unit = "N"
    rec.accel_present = False
    d = diagnose(rec, parse_plant(PLANT, "axis.toml"))
    return d, {e.name: e.parameters for e in d.effects}


def test_play_operator_by_hand():
    x = np.array([0.0, 1.0, 2.0, 1.5, 1.0, 0.5, 1.0])
    # width 1: the load follows 0.5 behind; on reversal at 2.0 it stays at 1.5 until the drive is 0.5 below it
    assert np.allclose(play(x, 1.0), [0.0, 0.5, 1.5, 1.5, 1.5, 1.0, 1.0])
    assert np.allclose(play(x, 0.0), x)


def test_backlash_applies_to_a_position_sensor_only():
    assert "backlash" in catalogue.for_plant("mechanical_axis", True, "position")
    assert "backlash" not in catalogue.for_plant("mechanical_axis", True, "velocity")
    assert "backlash" not in catalogue.for_plant("eha", True) and "stribeck_friction" not in \
        catalogue.for_plant("eha", True)


def test_a_stribeck_draw_brings_its_coulomb_level():
    assert set(_names(["stribeck_friction"])) == {"stribeck_friction", "coulomb_friction"}
    plant = load_plant(REPO / "docs" / "examples" / "emps_axis.toml")
    cases = draw_axis_cases(40, 3, plant)
    with_stribeck = [c for c in cases if "stribeck_friction" in c.effects]
    assert with_stribeck and all("coulomb_friction" in c.effects for c in with_stribeck)
    assert any("backlash" in c.effects for c in cases)


@pytest.mark.slow
def test_backlash_is_named_with_its_width():
    d, named = _diagnosed(backlash_m=5e-4)
    assert "backlash" in named, summary(d)
    assert abs(named["backlash"]["width_m"] / 5e-4 - 1) < 0.1, summary(d)


@pytest.mark.slow
def test_stribeck_friction_is_named_above_its_coulomb_level():
    d, named = _diagnosed(12.0, coulomb_n=0.1 * PEAK_N, stribeck_n=0.1 * PEAK_N, stribeck_m_per_s=5e-3)
    assert {"coulomb_friction", "stribeck_friction"} <= set(named), summary(d)
    assert abs(named["coulomb_friction"]["force_n"] / (0.1 * PEAK_N) - 1) < 0.25, summary(d)
    assert abs(named["stribeck_friction"]["breakaway_n"] / (0.1 * PEAK_N) - 1) < 0.5, summary(d)


@pytest.mark.slow
def test_coulomb_friction_alone_is_not_called_stribeck_nor_backlash():
    d, named = _diagnosed(coulomb_n=0.1 * PEAK_N)
    assert "coulomb_friction" in named, summary(d)
    assert "stribeck_friction" not in named and "backlash" not in named, summary(d)


def test_a_play_refines_the_segment_states_so_a_friction_of_0_n_adds_nothing():
    """A recording through a play, evaluated as the search evaluates a model (multiple shooting: each segment
    started from the data): the true play leaves the held-out residual near the noise, and a Coulomb friction of
    0 N beside it gains nothing (it may lose: friction beside a play keeps the slow models' two steps). Before, only a slow (friction) model's segment states were refined, so a
    friction of 0 N "removed" most of the play model's held-out residual and was named (rig prove --plant
    emps_axis.toml seed 1, a10: coulomb_friction 0 N beside a 0.69 mm play)."""
    from rig.diagnose.problem import Problem
    noise_m, width_m = 2e-7, 7e-4
    ax = Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0, backlash_m=width_m)
    u = band_noise(1000.0, 12.0, 0.3, 30.0, PEAK_N, seed=5).cmd_V
    cmd, pos = simulate_axis(ax, 1000.0, command=u, sensor=Sensor(noise_m=noise_m, offset_m=3e-4, seed=2))
    plant = parse_plant(PLANT, "axis.toml")
    pb = Problem(cmd, pos, 1000.0, plant, np.ones(len(pos), bool), noise=noise_m)
    assert pb.shoot is not None
    lin = {"mass_kg": 20.0, "damping_n_s_per_m": 60.0}
    play_only = pb.evaluate(lin, {"backlash": {"width_m": width_m}}, k=1)
    with_zero = pb.evaluate(lin, {"backlash": {"width_m": width_m}, "coulomb_friction": {"force_n": 0.0}}, k=2)
    held_out_rms = np.sqrt(play_only.rss_hold / pb.mhold.sum())
    assert held_out_rms < 3.0 * noise_m, held_out_rms / noise_m
    assert with_zero.rss_hold > 0.98 * play_only.rss_hold, with_zero.rss_hold / play_only.rss_hold


def test_a_plays_segment_states_settle_before_the_step_cap():
    """The refinement of a play's segment states reaches its settling criterion (no start moved by more than
    SHOOT_GN_SETTLED x the noise) well before SHOOT_GN_PLAY_STEPS: the drive's side of the play is set once from the
    data (a start velocity near 0 whose sign flipped between steps had moved the drive by the whole play, and the
    steps cycled to the cap), and steps that shrink geometrically are taken to the end of their series (Aitken).
    Before, a play's model evaluation ran all 40 steps (rig prove --plant emps_axis.toml seed 1, a10)."""
    from rig.diagnose import problem
    noise_m, width_m = 2e-7, 7e-4
    ax = Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0, backlash_m=width_m)
    u = band_noise(1000.0, 12.0, 0.3, 30.0, PEAK_N, seed=5).cmd_V
    cmd, pos = simulate_axis(ax, 1000.0, command=u, sensor=Sensor(noise_m=noise_m, offset_m=3e-4, seed=2))
    pb = problem.Problem(cmd, pos, 1000.0, parse_plant(PLANT, "axis.toml"), np.ones(len(pos), bool), noise=noise_m)
    steps, drives = [], []
    read, simulate_drive = pb.plant.read, pb.plant.simulate_drive
    pb.plant.read = lambda *a, **k: steps.append(1) or read(*a, **k)            # one a step of the states
    pb.plant.simulate_drive = lambda *a, **k: drives.append(1) or simulate_drive(*a, **k)
    for width in (0.8 * width_m, width_m, 1.2 * width_m):       # as a fit tries the width
        steps.clear(); drives.clear()
        pb.simulate({"mass_kg": 20.0, "damping_n_s_per_m": 60.0}, {"backlash": {"width_m": width}})
        assert 1 < len(steps) <= problem.SHOOT_GN_PLAY_STEPS // 2, (width, len(steps))
        assert len(drives) == 1, (width, len(drives))           # the steps add free responses (superposition)


@pytest.mark.parametrize("fx", [{"backlash": {"width_m": 7e-4}},
                                {"backlash": {"width_m": 7e-4}, "transport_delay": {"delay_s": 0.0037}},
                                {"backlash": {"width_m": 7e-4}, "constant_force": {"force_n": 3.0}},
                                {"backlash": {"width_m": 7e-4},
                                 "base_resonance": {"frequency_hz": 40.0, "damping_ratio": 0.05, "mass_kg": 200.0}}])
def test_a_plays_reading_by_superposition_is_the_simulation_from_the_same_states(fx):
    """A drive without friction is linear in its segment states until the play: the one simulation from zero states
    plus each state's free response reads what the simulation from those states reads (to rounding)."""
    from rig.diagnose.problem import Problem
    u = band_noise(1000.0, 12.0, 0.3, 30.0, PEAK_N, seed=5).cmd_V
    cmd, pos = simulate_axis(Axis(mass_kg=20.0, damping_n_s_per_m=60.0, gain_n_per_unit=1.0, backlash_m=7e-4),
                             1000.0, command=u, sensor=Sensor(noise_m=2e-7, offset_m=3e-4, seed=2))
    pb = Problem(cmd, pos, 1000.0, parse_plant(PLANT, "axis.toml"), np.ones(len(pos), bool), noise=2e-7)
    lin = {"mass_kg": 20.0, "damping_n_s_per_m": 60.0}
    O = pb.free_response(lin, fx)
    X = np.random.default_rng(3).normal(scale=1e-2, size=(pb.shoot.count, O.shape[1]))
    simulated = pb.plant.simulate(lin, pb.cmd, pb.fs, fx, pb.shoot.starts, X)
    superposed = pb._play_reading(lin, fx, O)(X)
    assert np.max(np.abs(simulated)) > 1e-3
    assert np.max(np.abs(superposed - simulated)) < 1e-12 * np.max(np.abs(simulated))


def test_aitken_takes_geometric_steps_to_the_end_of_their_series():
    from rig.diagnose.problem import SHOOT_AITKEN_RHO, _aitken
    O = np.column_stack([np.ones(50), np.arange(50) / 1000.0])
    last = np.array([[1e-4, 2e-3], [1e-4, 2e-3], [1e-4, 2e-3], [1e-4, 0.0]])
    dX = np.array([0.5 * last[0], 0.999 * last[1], -0.5 * last[2], [0.0, 1e-3]])   # rho 0.5, 0.999, -0.5, turned
    f = _aitken(dX, last, O)
    assert np.isclose(f[0], 2.0)                                 # 1 / (1 - 0.5): the rest of the series
    assert np.isclose(f[1], 1.0 / (1.0 - SHOOT_AITKEN_RHO))      # capped
    assert f[2] == 1.0 and f[3] == 1.0                           # no geometric series: a plain step

"""Diagnosis engine on simulated recordings (sim_backend.actuator.simulate_stand is the physics):
the fast candidate models against the simulator, a clean case (must say none) and a pair of effects."""
import numpy as np
import pytest

from rig.diagnose.catalogue import stand_effects
from rig.diagnose.engine import diagnose
from rig.diagnose.report import effect_evidence, summary
from rig.diagnose.models import sim_linear, sim_reduced
from rig.recordings.recording import Recording
from sim_backend.actuator import linear_chirp, simulate_stand
from sim_backend.linear import ActuatorParams

pytestmark = pytest.mark.slow

FS = 1000.0
P_TRUE = ActuatorParams().with_(K_L=6.2e8, K_C=7.2e-11, K_Q=1.80e-6, w_nv=560.0, zeta=0.6, C=2050.0)


def _rec(p, effects, duration_s=50.0, amplitude_V=2.0, seed=3, fs=FS):
    t, cmd = linear_chirp(fs, duration_s, 0.1, 100.0, amplitude_V)
    fx = stand_effects(effects, position_noise_m=2e-8, seed=seed)
    y = simulate_stand(p, cmd, fs, fx)
    return Recording.from_signals(cmd, y["position_m"], y["accel_mps2"], fs_hz=fs, source="sim")


@pytest.mark.parametrize("effects", [
    {},
    {"transport_delay": {"delay_s": 1.3e-3}, "valve_saturation": {"limit_ma": 2.6}},
    {"base_resonance": {"frequency_hz": 47.0, "damping_ratio": 0.04, "mass_kg": 220.0}},
])
def test_exact_linear_model_matches_simulator(effects):
    t, cmd = linear_chirp(FS, 20.0, 0.1, 100.0, 2.0)
    ref = simulate_stand(P_TRUE, cmd, FS, stand_effects(effects))["position_m"]
    b = effects.get("base_resonance")
    got = sim_linear(P_TRUE, cmd, FS, delay_s=effects.get("transport_delay", {}).get("delay_s", 0.0),
                     sat_ma=effects.get("valve_saturation", {}).get("limit_ma", 0.0),
                     base=(b["frequency_hz"], b["damping_ratio"], b["mass_kg"]) if b else None)
    assert np.sqrt(np.mean((got - ref) ** 2)) < 1e-9          # 5 % of the recordings' noise
    assert np.std(ref) > 5e-7


def test_reduced_model_matches_simulator():
    t, cmd = linear_chirp(FS, 20.0, 0.1, 100.0, 2.0)
    eff = {"valve_deadband": {"width_ma": 0.4}, "coulomb_friction": {"force_n": 300.0},
           "transport_delay": {"delay_s": 0.8e-3}}
    ref = simulate_stand(P_TRUE, cmd, FS, stand_effects(eff))["position_m"]
    got = sim_reduced(P_TRUE, cmd, FS, delay_s=0.8e-3, dead_ma=0.4, fric_n=300.0)
    lin = sim_linear(P_TRUE, cmd, FS, delay_s=0.8e-3)
    err = np.sqrt(np.mean((got - ref) ** 2))
    assert err < 3e-9
    assert np.sqrt(np.mean((lin - ref) ** 2)) > 30 * err    # the nonlinear effects are really there


def test_clean_recording_says_none():
    d = diagnose(_rec(P_TRUE, {}), ActuatorParams())
    assert d.effects == (), summary(d)
    assert "none" in summary(d)
    assert d.fit.nominal.residual_over_noise > 3          # the parameters did move ...
    assert d.fit.refit.residual_over_noise < 1.1          # ... and the refit explains it


def test_pair_delay_and_base_found():
    truth = {"transport_delay": {"delay_s": 1.2e-3},
             "base_resonance": {"frequency_hz": 66.0, "damping_ratio": 0.03, "mass_kg": 200.0}}
    d = diagnose(_rec(P_TRUE, truth), ActuatorParams())
    assert d.names() == ["base_resonance", "transport_delay"], summary(d)
    got = {e.name: e.parameters for e in d.effects}
    assert abs(got["transport_delay"]["delay_s"] - 1.2e-3) < 0.2 * 1.2e-3
    assert abs(got["base_resonance"]["frequency_hz"] - 66.0) < 0.05 * 66.0
    assert d.fit.augmented.residual_over_noise < 1.3
    assert all(e.score > 0 and effect_evidence(e, d.mismatch) for e in d.effects)


def test_constant_command_is_a_clear_error():
    from rig.errors import RecordingError
    n = 5000
    rec = Recording.from_signals(np.zeros(n), 1e-9 * np.random.default_rng(0).standard_normal(n), fs_hz=FS,
                                 source="flat.csv")
    with pytest.raises(RecordingError, match="flat.csv"):
        diagnose(rec, ActuatorParams())


def test_disturbance_beside_a_stand_mode_with_its_start_transient():
    """A 40 N line 2 Hz above a lightly damped stand mode rings at start-up: the disturbance regressors are the
    stand's response to the force from t = 0, so the augmented model still reaches the noise."""
    truth = {"base_resonance": {"frequency_hz": 45.0, "damping_ratio": 0.01, "mass_kg": 250.0},
             "periodic_disturbance": {"frequency_hz": 47.0, "force_n": 40.0, "phase_rad": 1.0}}
    d = diagnose(_rec(P_TRUE, truth, duration_s=40.0), ActuatorParams())
    assert d.names() == ["base_resonance", "periodic_disturbance"], summary(d)
    got = {e.name: e.parameters for e in d.effects}
    assert abs(got["periodic_disturbance"]["frequency_hz"] - 47.0) < 0.05
    assert abs(got["periodic_disturbance"]["force_n"] - 40.0) < 4.0
    assert abs(got["base_resonance"]["frequency_hz"] - 45.0) < 0.05 * 45.0
    assert d.fit.augmented.residual_over_noise_fit < 1.3

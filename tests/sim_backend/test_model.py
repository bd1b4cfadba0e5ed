"""Foundation: the paper's figures, the linear models and the config errors."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from rig.config import Config, config_from_dict, load_config
from rig.errors import ConfigError
from sim_backend.linear import (ActuatorParams, actuator_params, g_act, g_act_full, g_eha, g_eha_frf,
                                g_valve, model_figures)

RIG = [sys.executable, "-m", "rig.cli"]


def test_six_figures_from_table1_formulas():
    fig = model_figures(actuator_params(), 16000.0)
    # PHYSICS_NOTES: the formulas with Table 1 values (the paper rounds w_h up by ~2.5 %)
    assert fig["valve_natural_frequency_hz"] == pytest.approx(83.40, abs=0.01)
    assert fig["hydraulic_natural_frequency_hz"] == pytest.approx(2125, abs=1)
    assert fig["loaded_hydraulic_natural_frequency_hz"] == pytest.approx(251.4, abs=0.1)
    assert fig["hydraulic_damping_ratio"] == pytest.approx(0.0257, abs=1e-4)
    assert fig["lag_corner_rad_s"] == pytest.approx(46.70, abs=0.01)
    assert fig["dc_gain_m_per_V"] == pytest.approx(2.680e-6, rel=1e-3)


def test_rig_model_json_cli():
    out = subprocess.run(RIG + ["model", "--json"], capture_output=True, text=True, check=True)
    fig = json.loads(out.stdout)                      # only JSON on stdout
    for key in ("valve_natural_frequency_hz", "hydraulic_natural_frequency_hz",
                "loaded_hydraulic_natural_frequency_hz", "hydraulic_damping_ratio", "lag_corner_rad_s",
                "dc_gain_m_per_V"):
        assert key in fig
    assert fig["dc_gain_m_per_V"] == pytest.approx(2.680e-6, rel=1e-3)


def test_transfer_functions_agree_with_each_other():
    import control
    p = actuator_params()
    w = 2 * np.pi * np.array([0.1, 1, 10, 50, 100, 500])
    full = np.array([control.evalfr(g_eha(p), 1j * wk) for wk in w])
    assert np.allclose(full, g_eha_frf(p, w), rtol=1e-9)
    # Eq. 9 drops C K_C / A_p^2 (1.3e-4) and, in its factored form, K_L / K_h (0.068) from the s term
    # of Eq. 8: equal at DC, at most ~7 % (0.6 dB) high above the lag corner
    red = np.array([control.evalfr(g_valve(p) * g_act(p), 1j * wk) for wk in w])
    ratio = np.abs(red) / np.abs(full)
    assert ratio[0] == pytest.approx(1.0, abs=1e-4)
    assert np.all(ratio < 1 + p.K_L / p.K_h + 0.005) and ratio[-1] > 1.05
    # DC gains of the pieces
    assert control.dcgain(g_valve(p)) == pytest.approx(p.K_v)
    assert control.dcgain(g_act_full(p)) == pytest.approx(p.K_Q * p.A_p / (p.K_C * p.K_L), rel=1e-9)


def test_loaded_case_moves_hydraulic_frequency():
    p = actuator_params()
    loaded = p.with_(M=4000.0)
    assert loaded.w_h / p.w_h == pytest.approx(math.sqrt(56 / 4000), rel=1e-12)


@pytest.mark.parametrize("text, needle", [
    ("[actuator]\nM = -56\n", "actuator.M: expected >= 0.01 kg"),
    ("[actuator]\nA_p = 0\n", "actuator.A_p: expected >= 1e-06 m^2"),
    ("[valve]\nK_Q = \"big\"\n", "valve.K_Q: expected a number"),
    ("[valve]\nflow = 1\n", "valve.flow: unknown key"),
    ("[pump]\nP_s = 1\n", "[pump]: unknown section"),
    ("[loop]\noverrun_policy = \"maybe\"\n", "loop.overrun_policy: expected one of"),
    ("[actuator\nM = 1\n", "invalid TOML"),
    ("[fluid]\nbeta = true\n", "fluid.beta: expected a number"),
])
def test_config_errors_name_file_and_key(tmp_path, text, needle):
    f = tmp_path / "rig.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(f)
    assert str(f) in str(e.value) and needle in str(e.value)
    # the CLI: one line on stderr, exit status non-zero, no traceback
    r = subprocess.run(RIG + ["model", "--config", str(f)], capture_output=True, text=True)
    assert r.returncode != 0
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr


def test_config_defaults_and_override(tmp_path):
    assert Config().valve.K_Q == 1.94e-6 and Config().actuator.C == 1951
    f = tmp_path / "rig.toml"
    f.write_text("[valve]\nw_nv = 600\n[machine]\nmass_kg = 12000\n")
    cfg = load_config(f)
    assert cfg.valve.w_nv == 600.0 and cfg.machine.mass_kg == 12000.0 and cfg.valve.zeta == 0.65
    assert ActuatorParams.from_config(cfg).w_nv == 600.0


def test_missing_modal_model_file_is_named(tmp_path):
    f = tmp_path / "rig.toml"
    f.write_text('[machine]\nmodal_model = "nope.toml"\n')
    with pytest.raises(ConfigError, match="machine.modal_model: file not found"):
        load_config(f)
    with pytest.raises(ConfigError):
        config_from_dict({"vibration": {"band_lo_hz": 50.0, "band_hi_hz": 10.0}})

"""The plant file's [plant] table, the model families' equations and the one ZOH simulator."""
import math

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings, strategies as st

from rig.errors import EXIT_SUSPECT, ConfigError
from rig.plant.file import load_plant, parse_plant
from rig.plant.model import axis_state_space
from rig.plant.zoh import discretise, run_segments, substeps
from tests.paths import REPO

AXIS = {"family": "mechanical_axis", "input_unit": "V", "mass_kg": {"value": 95.0, "min": 10.0, "max": 500.0},
        "damping_n_s_per_m": 200.0, "gain_n_per_unit": 35.15}


def test_worked_example_loads():
    p = load_plant(REPO / "docs" / "examples" / "emps_like.toml")
    assert p.family == "mechanical_axis" and p.input_unit == "V"
    assert p.free == ("mass_kg", "damping_n_s_per_m")
    assert p.params["gain_n_per_unit"].value == 35.15 and not p.params["gain_n_per_unit"].free
    assert p.integrating()                      # k = 0: a pole at the origin


def test_no_plant_table_is_the_eha_default(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text("[signals]\ntime = 't'\n")
    assert load_plant(f).family == "eha"


@pytest.mark.parametrize("table, words", [
    ({**AXIS, "family": "gearbox"}, "family"),
    ({**AXIS, "input_unit": "mV"}, "input_unit"),
    ({**AXIS, "mass_kg": {"value": 600.0, "min": 10.0, "max": 500.0}}, "mass_kg: value 600 outside"),
    ({**AXIS, "mass_kg": {"value": 95.0, "min": 10.0}}, "mass_kg: a free parameter needs both"),
    ({**AXIS, "mass_kg": -1.0}, "mass_kg: expected a positive"),
    ({**AXIS, "mass_kg": "heavy"}, "mass_kg: expected a finite number"),
    ({k: v for k, v in AXIS.items() if k != "gain_n_per_unit"}, "gain_n_per_unit: missing"),
    ({**AXIS, "input_unit": "N", "gain_n_per_unit": 2.0}, "the gain is 1"),
    ({**AXIS, "spring": 3.0}, "spring: not a parameter"),
    ({"family": "transfer_function", "num": [1.0, 2.0], "den": [1.0, 3.0]}, "strictly proper"),
    ({"family": "transfer_function", "num": [0.0], "den": [1.0, 3.0]}, "every coefficient is 0 and fixed"),
    ({"family": "transfer_function", "num": [1.0], "den": [0.0, 1.0, 3.0]}, "den[0]"),
    ({"family": "eha", "K_Q": {"value": 1e-6, "min": 1e-7, "max": 1e-5}}, "K_Q"),
    # found by the abuse trial: K_L = 1e300 passed and the diagnosis ended in a ValueError traceback; an eha
    # value is held to its [actuator], [valve] or [fluid] range
    ({"family": "eha", "K_L": 1e300}, "K_L: expected <= 1e+11 N/m, got 1e+300"),
    ({"family": "eha", "zeta": 50.0}, "zeta: expected <= 10, got 50.0"),
    ({"family": "eha", "beta": 1.0}, "beta: expected >= 1e+07 Pa, got 1.0"),
])
def test_bad_plant_gives_one_line_naming_file_and_key(table, words):
    with pytest.raises(ConfigError) as e:
        parse_plant(table, "rig_b.toml")
    msg = str(e.value)
    assert msg.startswith("rig_b.toml: [plant]") and words in msg and "\n" not in msg


def test_force_input_has_gain_one_and_transfer_function_parses():
    p = parse_plant({"family": "mechanical_axis", "input_unit": "N", "mass_kg": 2.0, "damping_n_s_per_m": 3.0},
                    "f.toml")
    assert p.values()["gain_n_per_unit"] == 1.0 and p.free == ()
    tf = parse_plant({"family": "transfer_function", "num": [2e-3], "den": [1, {"value": 30, "min": 3, "max": 300}, 0]},
                     "f.toml")
    assert tf.free == ("den1",) and tf.integrating()
    A, B, Bf, C, Cv = tf.state_space(tf.values())
    w = np.array([2.0, 20.0])
    H = np.array([C @ np.linalg.solve(1j * wk * np.eye(2) - A, B) for wk in w])
    assert np.allclose(H, 2e-3 / ((1j * w) ** 2 + 30 * 1j * w), rtol=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.dictionaries(st.sampled_from(["family", "input_unit", "mass_kg", "damping_n_s_per_m", "gain_n_per_unit",
                                        "stiffness_n_per_m", "num", "den", "x"]),
                       st.one_of(st.floats(allow_nan=True), st.text(max_size=5), st.booleans(),
                                 st.sampled_from(["eha", "mechanical_axis", "transfer_function", "V", "N"]),
                                 st.lists(st.floats(-10, 10), max_size=3),
                                 st.fixed_dictionaries({"value": st.floats(-1e3, 1e3), "min": st.floats(-1e3, 1e3),
                                                        "max": st.floats(-1e3, 1e3)})), max_size=6))
def test_any_table_is_a_plant_or_one_config_error(table):
    try:
        p = parse_plant(table, "h.toml")
    except ConfigError as e:
        assert "\n" not in str(e) and str(e).startswith("h.toml: [plant]")
        return
    assert p.family in ("eha", "mechanical_axis", "transfer_function")


def test_zoh_matches_scipy_and_the_delay_is_exact():
    A, B, Bf, C, Cv = axis_state_space(95.0, 200.0, 1e4, 35.0)
    T = 1e-3
    Ad, G0, G1, m = discretise(A, B, T, 0.0)
    ref = scipy.signal.cont2discrete((A, B[:, None], C[None, :], np.zeros((1, 1))), T, method="zoh")
    assert np.allclose(Ad, ref[0], rtol=1e-12, atol=1e-15) and np.allclose(G0, ref[1][:, 0], rtol=1e-10)
    # a delay of 2.4 samples: the response equals the undelayed one shifted by 2.4 samples (a smooth input)
    t = np.arange(4000) * T
    u = np.sin(2 * math.pi * 3 * t) * (1 - np.cos(2 * math.pi * t / 4.0)) / 2
    Ah, Bn, Bo, m = substeps(A, B, T, 1, 2.4e-3)
    y = run_segments(Ah, Bn, Bo, np.zeros(2), Cv, C, u, m)
    y0 = run_segments(*substeps(A, B, T, 1, 0.0)[:3], np.zeros(2), Cv, C, u, 0)
    ys = np.interp(t - 2.4e-3, t, y0)
    assert np.max(np.abs(y - ys)) < 2e-3 * np.max(np.abs(y0))
    assert m == 2


def test_friction_and_constant_force_in_the_simulator():
    """A free mass pushed by a constant force against Coulomb friction: the steady speed (F - F_c) / c, and a push
    below F_c does not move it (the smooth friction's creep stays tiny)."""
    M, c, Fc = 10.0, 20.0, 5.0
    A, B, Bf, C, Cv = axis_state_space(M, c, 0.0, 1.0)
    fs, n_sub = 1000.0, 5
    Ah, Bn, Bo, m = substeps(A, B, 1 / fs, n_sub, 0.0)
    from rig.plant.zoh import phi
    Gf = phi(A, Bf, 1 / (fs * n_sub))[1]
    u = np.full(5000, 8.0)
    y = run_segments(Ah, Bn, Bo, Gf, Cv, C, u, m, friction_n=Fc, smoothing_m_per_s=1e-5, force_n=0.0)
    v_end = (y[-1] - y[-1001]) / 1.0
    assert abs(v_end - (8.0 - Fc) / c) < 1e-4
    y = run_segments(Ah, Bn, Bo, Gf, Cv, C, np.zeros(5000), m, friction_n=Fc, smoothing_m_per_s=1e-5, force_n=3.0)
    assert abs(y[-1]) < 1e-4                    # 3 N < F_c: stuck (creep of a stiff tanh only)
    starts = np.array([0, 2500]); X0 = np.array([[0.0, 0.0], [0.5, 0.0]])
    y = run_segments(Ah, Bn, Bo, Gf, Cv, C, np.zeros(5000), m, starts=starts, X0=X0)
    assert y[2499] == 0.0 and y[2500] == 0.5    # the state is set at each segment start


def test_a_misspelt_table_is_named_before_the_recording_is_read(tmp_path):
    """Issue 29: `[signal]` was ignored silently, and the error that followed was about the recording's columns."""
    from rig.plant.file import load_subject
    f = tmp_path / "plant.toml"
    f.write_text('[plant]\nfamily = "mechanical_axis"\ninput_unit = "N"\nmass_kg = 2.0\ndamping_n_s_per_m = 3.0\n'
                 '[signal]\ncommand = "u"\n')
    with pytest.raises(ConfigError) as e:
        load_subject(tmp_path / "missing.csv", f)
    assert str(e.value) == (f"{f}: [signal]: not a table of a plant file (expected [plant] and [signals]; did you "
                            f"mean [signals]?)")


def test_a_missing_input_unit_is_named_as_such():
    """Issue 29: a mechanical_axis without input_unit was told about gain_n_per_unit."""
    with pytest.raises(ConfigError, match=r"\[plant\] input_unit: missing: the command's unit"):
        parse_plant({"family": "mechanical_axis", "mass_kg": 2.0, "damping_n_s_per_m": 3.0}, "p.toml")


def test_an_eha_plant_file_says_which_values_the_diagnosis_refits():
    """The README's plant file gives every eha value as a number: the ones the diagnosis refits read "refit from
    here", the others "(fixed)" (a newcomer read all eleven as fixed just before "refit of the linear
    parameters")."""
    from rig.plant.model import EHA_REFIT_KEYS
    text = load_plant(REPO / "docs" / "examples" / "spreadsheet_csv.toml").describe()
    parts = dict(p.split("=", 1) for p in text.split(": ", 1)[1].split(", "))
    assert {k for k, v in parts.items() if v.endswith("(refit from here)")} == set(EHA_REFIT_KEYS), text
    assert {k for k, v in parts.items() if v.endswith("(fixed)")} == {"M", "A_p", "C", "V_t", "K_v", "beta"}, text


def test_a_subject_is_read_in_layer_order_from_plain_values(tmp_path):
    """`rig diagnose` / `rig identify` read the configuration, then the plant file (once: its [plant] and its
    [signals]), then the recording: the eha plant is the configuration's actuator with the plant file's values
    over it, the recording read through the same file's signal map, and the first bad file is the one named."""
    from rig.plant.file import load_subject
    cfg = tmp_path / "rig.toml"
    cfg.write_text("[actuator]\nC = 2100.0\n")
    plant = tmp_path / "plant.toml"
    plant.write_text('[plant]\nfamily = "eha"\nK_L = 7.0e8\n[signals]\ntime = "zeit"\n'
                     'command = { name = "u_mV", unit = "mV" }\nposition = { name = "x_um", unit = "um" }\n')
    t = np.arange(5000) / 1000.0
    u = 500.0 * np.sin(2 * math.pi * 3.0 * t) * np.sin(2 * math.pi * 0.7 * t)
    x = 20.0 * np.sin(2 * math.pi * 3.0 * t - 0.3) * np.sin(2 * math.pi * 0.7 * t)
    rec_path = tmp_path / "lab.csv"
    rec_path.write_text("zeit,u_mV,x_um\n" + "\n".join(f"{a:.4f},{b:.6f},{c:.6f}" for a, b, c in zip(t, u, x)))
    s = load_subject(rec_path, plant, cfg)
    assert s.plant.actuator.C == 2100.0 and s.plant.actuator.K_L == 7.0e8        # config's, then the file's
    assert s.plant.actuator.K_Q == load_plant(plant).actuator.K_Q                 # the rest: Table 1
    np.testing.assert_allclose(s.rec.valve_cmd_V, u / 1e3, rtol=0, atol=1e-9)     # through its own [signals]
    np.testing.assert_allclose(s.rec.position_m, x / 1e6, rtol=0, atol=1e-12)
    bad_cfg = tmp_path / "bad_rig.toml"
    bad_cfg.write_text("[actuator]\nC = -1.0\n")
    bad_plant = tmp_path / "bad_plant.toml"
    bad_plant.write_text('[plant]\nfamily = "gearbox"\n[signals]\ncommand = 3\n')
    with pytest.raises(ConfigError, match="bad_rig.toml"):
        load_subject(rec_path, bad_plant, bad_cfg)
    with pytest.raises(ConfigError, match=r"bad_plant.toml: \[plant\] family"):       # [plant] before [signals]
        load_subject(rec_path, bad_plant, cfg)


def _axis_recording(path, n=6000, fs=1000.0):
    """An open-loop mechanical axis (10 kg, 100 N s/m, 1e4 N/m, 10 N/V) under a random command, rig's CSV."""
    t = np.arange(n) / fs
    u = np.random.default_rng(1).standard_normal(n)
    axis = scipy.signal.StateSpace([[0.0, 1.0], [-1e3, -10.0]], [[0.0], [1.0]], [[1.0, 0.0]], [[0.0]])
    _, y, _ = scipy.signal.lsim(axis, u, t, interp=False)
    path.write_text("time_s,valve_cmd_V,position_m,accel_mps2\n" +
                    "\n".join(f"{a:.6f},{b:.9g},{c:.9g},0" for a, b, c in zip(t, u, y)) + "\n")
    return path


ABSURD = {  # found by the abuse trial: NRMSE inf or nan with exit 0, or a traceback (rig diagnose)
    "gain": ('family = "mechanical_axis"\ninput_unit = "V"\nmass_kg = 10.0\ndamping_n_s_per_m = 100.0\n'
             'gain_n_per_unit = 1e300\n', "mechanical_axis", "gain_n_per_unit = 1e+300"),
    "stiffness": ('family = "mechanical_axis"\ninput_unit = "V"\nmass_kg = 10.0\ndamping_n_s_per_m = 100.0\n'
                  'stiffness_n_per_m = 1e300\ngain_n_per_unit = 10.0\n', "mechanical_axis",
                  "stiffness_n_per_m = 1e+300"),
    "transfer_function": ('family = "transfer_function"\ninput_unit = "V"\nnum = [1e300]\nden = [1, 1e-300, 0]\n',
                          "transfer_function", "num0 = 1e+300"),
}


@pytest.mark.parametrize("case", sorted(ABSURD))
@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_values_the_fit_cannot_compute_with_are_one_line_naming_the_plant_file(tmp_path, capsys, case, command):
    """Finite, positive, and still beyond what floating point computes (no range fits every axis, so none is
    invented): the plant file is named with the values the fit stopped at, exit 2, no traceback, no JSON."""
    from rig.cli import main
    table, family, value = ABSURD[case]
    plant = tmp_path / "absurd.toml"
    plant.write_text("[plant]\n" + table)
    rec = _axis_recording(tmp_path / "axis.csv")
    assert main([command, str(rec), "--plant", str(plant), "--json"]) == 2
    r = capsys.readouterr()
    lines = [ln for ln in r.err.splitlines() if not ln.startswith("[")]           # progress lines aside
    assert r.out == "" and len(lines) == 1, r.err
    assert lines[0].startswith(f"rig {command}: error: {plant}: [plant] {family}: no fit is possible: ")
    assert value in lines[0] and "not finite" in lines[0]


@pytest.mark.parametrize("command", ["identify", "diagnose"])
def test_a_mass_of_1e300_ends_in_figures_without_a_numpy_warning(tmp_path, capsys, command):
    """Found by the abuse trial: a mass of 1e300 kg (with a spring) printed scipy's `RuntimeWarning: invalid value
    encountered in cast` on stderr: balancing the ZOH matrix (rig/plant/zoh.py phi) scales by ~1e148, which scipy
    also casts to int. The model is computable (finite, its position next to nothing), so it ends in figures
    that say it explains nothing, and no warning."""
    import json
    import warnings
    from rig.cli import main
    plant = tmp_path / "heavy.toml"
    plant.write_text('[plant]\nfamily = "mechanical_axis"\ninput_unit = "V"\nmass_kg = 1e300\n'
                     'damping_n_s_per_m = 100.0\nstiffness_n_per_m = 1e4\ngain_n_per_unit = 10.0\n')
    rec = _axis_recording(tmp_path / "axis.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # any warning is noise on the user's terminal
        code = main([command, str(rec), "--plant", str(plant), "--json"])
    r = capsys.readouterr()
    res = json.loads(r.out)
    nrmse = res["fit"]["nominal"]["nrmse"] if command == "diagnose" else res["fit"]["nrmse"]
    assert math.isfinite(nrmse) and nrmse > 1.0
    said = [ln for ln in r.err.splitlines() if not ln.startswith("[")]             # progress lines aside
    if command == "diagnose":
        assert code == 0 and said == [], r.err
    else:                                               # identify's poor-fit rule: one line, exit 5, no numpy noise
        assert code == EXIT_SUSPECT and said == [f"rig identify: warning: {res['warning']}"], r.err


def test_identify_through_a_plant_file_says_a_poor_fit_as_the_eha_path_does(tmp_path, capsys):
    """Found by a helper: `rig identify REC --plant FILE` ended a fit that explains nothing (NRMSE 4.7, the
    plant's values all fixed and wrong) with exit 0 and no warning, where the eha path says "poor fit" and exits
    EXIT_SUSPECT. Now the one rule (rig.identify.poor_fit: NRMSE above POOR_NRMSE) on both paths; a fitting plant
    file stays quiet."""
    import json
    from rig.cli import main
    rec = _axis_recording(tmp_path / "axis.csv")
    wrong = tmp_path / "wrong.toml"
    wrong.write_text('[plant]\nfamily = "mechanical_axis"\ninput_unit = "V"\nmass_kg = 10.0\n'
                     'damping_n_s_per_m = 100.0\ngain_n_per_unit = 10.0\n')          # no spring: the data has one
    assert main(["identify", str(rec), "--plant", str(wrong)]) == EXIT_SUSPECT
    r = capsys.readouterr()
    said = [ln for ln in r.err.splitlines() if not ln.startswith("[")]
    assert len(said) == 1 and said[0].startswith("rig identify: warning: poor fit (NRMSE "), r.err
    assert said[0].endswith(f"): the recording is not a clean response of the plant of {wrong}")
    assert main(["identify", str(rec), "--plant", str(wrong), "--json"]) == EXIT_SUSPECT
    res = json.loads(capsys.readouterr().out)
    from rig.identify import POOR_NRMSE                 # the eha path's threshold
    assert res["fit"]["nrmse"] > POOR_NRMSE and res["warning"].startswith("poor fit (NRMSE ")
    good = tmp_path / "good.toml"
    good.write_text('[plant]\nfamily = "mechanical_axis"\ninput_unit = "V"\n'
                    'mass_kg = { value = 20.0, min = 1.0, max = 100.0 }\n'
                    'damping_n_s_per_m = { value = 50.0, min = 1.0, max = 1000.0 }\n'
                    'stiffness_n_per_m = { value = 5e3, min = 1e2, max = 1e6 }\ngain_n_per_unit = 10.0\n')
    assert main(["identify", str(rec), "--plant", str(good), "--json"]) == 0
    r = capsys.readouterr()
    assert "warning" not in json.loads(r.out) and all(ln.startswith("[") for ln in r.err.splitlines()), r.err


def test_a_mass_of_1e_minus_300_ends_in_figures_not_a_traceback(tmp_path, capsys):
    """Found by the abuse trial: a free mass within [1e-301, 1e-299] kg ended `rig diagnose` in a ValueError
    traceback (a fit's step into a model beyond floating point). Such a model is now not computable (nan) and
    the fit does not step there: the diagnosis ends with finite figures, saying how poor the model is."""
    import json
    from rig.cli import main
    plant = tmp_path / "tiny.toml"
    plant.write_text('[plant]\nfamily = "mechanical_axis"\ninput_unit = "V"\n'
                     'mass_kg = { value = 1e-300, min = 1e-301, max = 1e-299 }\ndamping_n_s_per_m = 100.0\n'
                     'stiffness_n_per_m = 1e4\ngain_n_per_unit = 10.0\n')
    rec = _axis_recording(tmp_path / "axis.csv")
    assert main(["diagnose", str(rec), "--plant", str(plant), "--json"]) == 0
    fit = json.loads(capsys.readouterr().out)["fit"]
    assert all(math.isfinite(fit[m]["nrmse"]) and fit[m]["nrmse"] > 0.5 for m in ("nominal", "refit"))

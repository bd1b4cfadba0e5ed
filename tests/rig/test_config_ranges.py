"""Physical ranges for every config value (issue 17): each numeric key states its range in the field metadata,
a value outside it (or a frequency at or above the loop's Nyquist frequency) ends in one line naming the file
and the key, and the shipped configs load. Property tests: any value for any key is a Config or a ConfigError,
never another exception; any value inside the ranges runs `rig model` and a short `rig run` without a
traceback."""
from __future__ import annotations

import dataclasses
import tomllib
import math
import re
import tempfile
import tomllib
import typing
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from rig import config as C
from rig.cli import main
from rig.errors import ConfigError
from tests.paths import REPO

SECTIONS = {f.name: typing.get_type_hints(C.Config)[f.name] for f in dataclasses.fields(C.Config)
            if f.name != "source"}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return repr(v)


def _toml(data: dict) -> str:
    return "".join(f"[{sec}]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in keys.items())
                   for sec, keys in data.items())


def _write(data: dict) -> Path:
    p = Path(tempfile.mkdtemp(prefix="rig-cfg-")) / "c.toml"
    p.write_text(_toml(data))
    return p


# ---- the cases, one each -------------------------------------------------------------------------
@pytest.mark.parametrize("section, key, value, expected", [
    ("actuator", "M", 1e-30, "expected >= 0.01 kg"),
    ("valve", "zeta", 1e9, "expected <= 10"),
    ("machine", "mass_kg", 1e300, "expected <= 1e+06 kg"),
    ("controller", "notch_hz", 3000.0, "expected < 2500 Hz (the Nyquist frequency of loop.rate_hz = 5000 Hz)"),
    ("vibration", "band_hi_hz", 3000.0, "expected < 2500 Hz"),
    ("loop", "rate_hz", 1.0, "expected >= 10 Hz"),
    ("controller", "gain_trim", [0.0, 1.0, 1.0, 1.0], "expected > 0"),
    ("controller", "gain_trim", [1.0, -1.0, 1.0, 1.0], "expected > 0"),
    ("controller", "gain_trim", [1.0], "expected a list of 4 numbers"),
    ("controller", "gain_trim", [1.0, 1.0, 1.0, 1.0, 1.0], "expected a list of 4 numbers"),
    ("controller", "gain_trim", [1.0, 1.0, float("nan"), 1.0], "expected finite numbers"),
    ("sensors", "floor_V_per_mps2", 0.0, "expected >= 0.001 V/(m/s^2)"),
    ("sensors", "floor_noise_mps2_per_rthz", -1.0, "expected >= 0 m/s^2/sqrt(Hz)"),
    ("sensors", "floor_channels", [4, 5, 6], "expected a list of 4 numbers"),
    ("sensors", "floor_channels", [3, 4, 5, 6], "expected >= 4, got 3"),     # ch0-3: the mount accelerometers
    ("sensors", "floor_range_mps2", 8.0, "expected <= 10 V / floor_V_per_mps2 (5 m/s^2"),
    ("plant_error", "K_Q", 3.0, "expected <= 2"),
    ("plant_error", "w_nv", 0.1, "expected >= 0.5"),
    ("controller", "lead1_pole_hz", 5e-324, "expected >= 0.001 Hz"),   # was a LinAlgError (CI, session 5)
])
@pytest.mark.parametrize("command", [["run", "--sim-time", "--seconds", "0.5", "--quiet"], ["model"]])
def test_questionable_config_value_is_one_line(capsys, section, key, value, expected, command):
    """Were: accepted (M = 1e-30, zeta = 1e9, 1e300 kg, notch above Nyquist limit-cycling at the clamp,
    gain_trim zero/negative/padded) or a traceback (a floor band above Nyquist, rate_hz = 1)."""
    path = _write({section: {key: value}})
    assert main([command[0], "--config", str(path), *command[1:]]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"rig {command[0]}: error: {path}: {section}.{key}: {expected}"), err[0]


def test_low_loop_rate_refuses_the_floor_band(capsys):
    """`[loop] rate_hz = 60` with the default 1-50 Hz floor band: refused naming the band (was a traceback)."""
    path = _write({"loop": {"rate_hz": 60.0}, "controller": {
        k: 1.0 for k in ("lead1_zero_hz", "lead1_pole_hz", "lead2_zero_hz", "lead2_pole_hz", "rolloff_hz",
                         "notch_hz", "notch2_hz", "prewarp_hz", "pi_corner_hz", "ff_lowpass_hz")}})
    assert main(["demo", "--config", str(path)]) == 2
    assert "vibration.band_hi_hz: expected < 30 Hz" in capsys.readouterr().err


def test_hil_rate_bounds_the_floor_band():
    cfg = C.config_from_dict({"vibration": {"band_hi_hz": 400.0}})
    with pytest.raises(ConfigError, match=r"vibration.band_hi_hz: expected < 250 Hz \(the Nyquist frequency of "
                                          r"the HIL loop at 500 Hz\)"):
        C.hil_run_config(cfg)


def test_shipped_configs_load():
    files = sorted((REPO / "drivers" / "devicemaps").glob("*.toml")) + sorted((REPO / "docs").glob("**/*.toml"))
    # plant files (docs/PLANT.md: [plant], [signals]) are not rig configs; tests/rig/test_signalmap.py loads them
    files = [f for f in files if not {"plant", "signals"} & set(tomllib.loads(f.read_text()))]
    assert len(files) >= 2
    for f in files:
        cfg = C.load_config(f)
        if f.parent.name == "devicemaps":                                # the drivers' configs fit the HIL rate
            C.check_nyquist(cfg, cfg.hil.rate_hz, sections=("controller",))


def test_defaults_are_inside_their_own_ranges():
    data = {sec: {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(getattr(C.Config(),
                                                                                                    sec)).items()}
            for sec in SECTIONS}
    assert C.config_from_dict(data) == C.Config(source="<dict>")


def _numeric_fields():
    for sec, cls in SECTIONS.items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] in (bool, str, tuple[str, ...]):        # flags, names, lists of names
                continue
            yield sec, f, hints[f.name]


def test_every_numeric_value_states_a_physical_range():
    """Every number has a lower and an upper bound in its metadata (a frequency's upper bound may be the
    Nyquist frequency of the loop), and a dimensional one names its unit."""
    missing = []
    for sec, f, _ in _numeric_fields():
        m = f.metadata
        lower = m.get("gt") is not None or m.get("ge") is not None
        upper = m.get("lt") is not None or m.get("le") is not None or (m.get("unit") == "Hz" and m.get("nyquist"))
        if not (lower and upper) and not m.get("choices"):
            missing.append(f"{sec}.{f.name}")
    assert not missing, missing


# ---- property tests --------------------------------------------------------------------------------------
ANY_VALUE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-2 ** 70, max_value=2 ** 70),
    st.booleans(), st.text(max_size=8), st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=6),
    st.lists(st.integers(min_value=-5, max_value=5), max_size=6), st.just([]), st.just({"x": 1}))


@st.composite
def any_entry(draw):
    sec = draw(st.sampled_from(sorted(SECTIONS) + ["nonsense"]))
    keys = [f.name for f in dataclasses.fields(SECTIONS[sec])] if sec in SECTIONS else ["x"]
    key = draw(st.sampled_from(keys + ["not_a_key"]))
    return sec, key, draw(ANY_VALUE)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(any_entry(), min_size=1, max_size=4))
def test_any_value_is_a_config_or_one_config_error(entries):
    data: dict = {}
    for sec, key, value in entries:
        data.setdefault(sec, {})[key] = value
    try:
        cfg = C.config_from_dict(data, "p.toml")
    except ConfigError as e:
        text = str(e)
        assert "\n" not in text
        m = re.match(r"p\.toml: (?:\[(\w+)\]|(\w+)\.(\w+)): ", text)
        assert m, text
        if m.group(1):                                      # a section: unknown, or not a table
            assert m.group(1) in {s for s, _, _ in entries}, text
        else:                                               # a key: the one given, or one checked against it
            sec, key = m.group(2), m.group(3)
            assert (sec, key) in {(s, k) for s, k, _ in entries} or \
                key in {f.name for f in dataclasses.fields(SECTIONS[sec])}, text
        return
    assert isinstance(cfg, C.Config)


def _in_range(f, hint):
    """A strategy for values inside field f's stated range (log-uniform across decades where it is wide)."""
    m = f.metadata
    if m.get("choices"):
        return st.sampled_from(m["choices"])
    lo = m["gt"] if m.get("gt") is not None else m.get("ge")
    hi = m["lt"] if m.get("lt") is not None else m.get("le")
    if hint is int:
        return st.integers(min_value=int(lo if lo is not None else 0) + (1 if m.get("gt") is not None else 0),
                           max_value=int(hi if hi is not None else 10 ** 6))
    lo = float(lo if lo is not None else 0.0)
    hi = float(hi if hi is not None else 1e4)         # a frequency: further bounded by Nyquist below
    if lo > 0 and hi / lo > 100:
        return st.floats(min_value=math.log10(lo), max_value=math.log10(hi)).map(lambda e: 10.0 ** e).filter(
            lambda v: lo < v < hi)
    return st.floats(min_value=lo, max_value=hi, exclude_min=True, exclude_max=True)


PHYSICS = ("actuator", "valve", "fluid", "machine", "vibration", "controller", "safety", "stand", "sensors",
           "plant_error")


@st.composite
def valid_entries(draw):
    out: dict = {}
    for _ in range(draw(st.integers(1, 4))):
        sec = draw(st.sampled_from(PHYSICS))
        hints = typing.get_type_hints(SECTIONS[sec])
        f = draw(st.sampled_from([f for f in dataclasses.fields(SECTIONS[sec])
                                  if hints[f.name] in (float, int) and f.name != "seed"]))
        out.setdefault(sec, {})[f.name] = draw(_in_range(f, hints[f.name]))
    return out


def _runs_or_refuses(argv, capsys):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc in (0, 1, 2) and "Traceback" not in err
    if rc == 2:
        assert "error:" in err.strip().splitlines()[-1], err
    return rc


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(valid_entries())
def test_values_inside_the_ranges_run_model_and_a_short_run(capsys, data):
    """A config whose every value is inside its range: `rig model` prints its figures or refuses with one line
    (a cross-check), and a short `rig run` on the simulated rig ends in 0, a FAULT (1, the valves nulled) or
    one line (2) - never a traceback."""
    path = _write(data)
    rc = _runs_or_refuses(["model", "--json", "--config", str(path)], capsys)
    if rc == 0:
        _runs_or_refuses(["run", "--config", str(path), "--sim-time", "--seconds", "0.1", "--settle", "0.02",
                          "--quiet"], capsys)


"""The plant file's [plant] table (TOML) -> Plant. Every problem is one ConfigError naming the file and the key.

    [plant]
    family = "mechanical_axis"          # eha (default) | mechanical_axis | transfer_function
    input_unit = "V"                    # the command's unit: V, N or A
    mass_kg = { value = 95, min = 10, max = 500 }     # free within bounds
    damping_n_s_per_m = { value = 200, min = 1, max = 5000 }
    stiffness_n_per_m = 0               # a number: fixed (optional; 0 = a free axis)
    gain_n_per_unit = 35.15             # the drive's N per V (or per A); with input_unit = "N" fixed at 1

    [plant]
    family = "transfer_function"
    num = [2e-3]                        # position / command = num(s) / den(s), highest power first
    den = [1, { value = 30, min = 3, max = 300 }, 0]

The plant file is read once here (`read_plant_file`): its [plant] table becomes the Plant, its [signals] table
goes as it is to the recording's loader (rig.recordings.signalmap). `load_subject` is what `rig identify` and
`rig diagnose` read, in that order: the configuration (the eha actuator's defaults), the plant file, the recording.
"""
from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from rig.config import check_actuator_value, load_config
from rig.errors import ConfigError
from rig.plant.model import FAMILIES, INPUT_UNITS, Param, Plant, eha_plant
from rig.recordings.recording import Recording, check_plausible
from rig.recordings.signalmap import SignalMap, load_recording_for
from rig.textfile import read_text
from sim_backend.linear import ActuatorParams

AXIS_KEYS = {"mass_kg": True, "damping_n_s_per_m": True, "stiffness_n_per_m": False, "gain_n_per_unit": False}
COMMON_KEYS = ("family", "input_unit")
AXIS_OUTPUTS = ("position", "velocity")          # what a mechanical axis's sensor reads
# the recording's measured output (rig.recordings: its kind) each plant can be held against
OUTPUT_KINDS = {"eha": ("length",), "position": ("length", "angle"), "velocity": ("velocity", "angular velocity")}


def _param(where: str, key: str, raw, *, positive: bool = False) -> Param:
    """A number (fixed) or {value, min, max} (free within bounds; {value} alone is fixed)."""
    def num(x, what):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
            raise ConfigError(f"{where} {key}{what}: expected a finite number, got {x!r}")
        return float(x)
    if isinstance(raw, dict):
        unknown = set(raw) - {"value", "min", "max"}
        if unknown:
            raise ConfigError(f"{where} {key}: unknown field(s) {', '.join(sorted(unknown))} (expected value, min, max)")
        if "value" not in raw:
            raise ConfigError(f"{where} {key}: needs a start value ({key} = {{ value = ..., min = ..., max = ... }})")
        v = num(raw["value"], ".value")
        if "min" not in raw and "max" not in raw:
            p = Param.fixed(v)
        elif "min" not in raw or "max" not in raw:
            raise ConfigError(f"{where} {key}: a free parameter needs both min and max")
        else:
            lo, hi = num(raw["min"], ".min"), num(raw["max"], ".max")
            if not lo < hi:
                raise ConfigError(f"{where} {key}: min {lo:g} must be below max {hi:g}")
            if not lo <= v <= hi:
                raise ConfigError(f"{where} {key}: value {v:g} outside [min, max] = [{lo:g}, {hi:g}]")
            p = Param(v, lo, hi, True)
    else:
        p = Param.fixed(num(raw, ""))
    if positive and (p.value <= 0 or p.lo <= 0):
        raise ConfigError(f"{where} {key}: expected a positive value (and min > 0), got {p.value:g}"
                          + (f" [min {p.lo:g}]" if p.free else ""))
    return p


def parse_plant(table: dict, source: str, p0: ActuatorParams | None = None) -> Plant:
    """Plant from the [plant] table's contents (source names the file in errors)."""
    where = f"{source}: [plant]"
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table")
    family = table.get("family", "eha")
    if family not in FAMILIES:
        raise ConfigError(f"{where} family: {family!r} is not a plant family (expected one of {', '.join(FAMILIES)})")
    if family == "mechanical_axis" and "input_unit" not in table:
        raise ConfigError(f"{where} input_unit: missing: the command's unit (\"N\" when the command is a force, "
                          f"else \"V\" or \"A\" with gain_n_per_unit, the force per unit of command)")
    unit = table.get("input_unit", "V")
    if unit not in INPUT_UNITS:
        raise ConfigError(f"{where} input_unit: {unit!r} (expected one of {', '.join(INPUT_UNITS)})")
    rest = {k: v for k, v in table.items() if k not in COMMON_KEYS}
    if family == "eha":
        if unit != "V":
            raise ConfigError(f"{where} input_unit: the eha plant's command is the valve voltage (V), got {unit!r}")
        base = p0 or ActuatorParams()
        fields = base.as_dict()
        unknown = set(rest) - set(fields)
        if unknown:
            raise ConfigError(f"{where} {sorted(unknown)[0]}: not a parameter of the eha plant (expected "
                              f"{', '.join(fields)})")
        vals = {k: _param(where, k, v, positive=True) for k, v in rest.items()}
        if any(p.free for p in vals.values()):
            k = next(k for k, p in vals.items() if p.free)
            raise ConfigError(f"{where} {k}: the eha plant's values are fixed numbers (the diagnosis refits "
                              "K_L, K_C, K_Q, w_nv, zeta within 0.7-1.4 x these)")
        return eha_plant(base.with_(**{k: check_actuator_value(where, k, p.value) for k, p in vals.items()}),
                         source)
    if family == "mechanical_axis":
        output = rest.pop("output", "position")
        if output not in AXIS_OUTPUTS:
            raise ConfigError(f"{where} output: {output!r} (expected one of {', '.join(AXIS_OUTPUTS)}: what the "
                              "sensor reads)")
        unknown = set(rest) - set(AXIS_KEYS)
        if unknown:
            raise ConfigError(f"{where} {sorted(unknown)[0]}: not a parameter of mechanical_axis (expected "
                              f"{', '.join(AXIS_KEYS)})")
        params = {}
        for key, required in AXIS_KEYS.items():
            if key not in rest:
                if key == "gain_n_per_unit" and unit == "N":
                    params[key] = Param.fixed(1.0)
                    continue
                if required or key == "gain_n_per_unit":
                    raise ConfigError(f"{where} {key}: missing (mechanical_axis needs "
                                      f"{', '.join(k for k, r in AXIS_KEYS.items() if r)}"
                                      + (", gain_n_per_unit" if unit != "N" else "") + ")")
                params[key] = Param.fixed(0.0)
                continue
            params[key] = _param(where, key, rest[key], positive=key != "stiffness_n_per_m")
        if params["stiffness_n_per_m"].value < 0 or params["stiffness_n_per_m"].lo < 0:
            raise ConfigError(f"{where} stiffness_n_per_m: expected >= 0")
        if unit == "N" and (params["gain_n_per_unit"].free or params["gain_n_per_unit"].value != 1.0):
            raise ConfigError(f"{where} gain_n_per_unit: the command is a force (input_unit N), so the gain is 1")
        return Plant(family, params, unit, source, output=output)
    # transfer_function
    unknown = set(rest) - {"num", "den"}
    if unknown:
        raise ConfigError(f"{where} {sorted(unknown)[0]}: not a key of transfer_function (expected num, den)")
    params = {}
    for key in ("num", "den"):
        raw = rest.get(key)
        if not isinstance(raw, list) or not raw:
            raise ConfigError(f"{where} {key}: expected a list of coefficients, highest power of s first")
        for i, x in enumerate(raw):
            params[f"{key}{i}"] = _param(where, f"{key}[{i}]", x)
    nn, nd = len(rest["num"]), len(rest["den"])
    if params["den0"].value == 0 or (params["den0"].free and params["den0"].lo <= 0 <= params["den0"].hi):
        raise ConfigError(f"{where} den[0]: the leading coefficient must be nonzero (and its bounds exclude 0)")
    if all(params[f"num{i}"].value == 0 and not params[f"num{i}"].free for i in range(nn)):
        raise ConfigError(f"{where} num: every coefficient is 0 and fixed: a plant whose output never moves "
                          "(give the gain, or bounds to fit it)")
    if nn >= nd:
        raise ConfigError(f"{where} num: {nn} coefficients for a denominator of {nd}: the model must be strictly "
                          "proper (the position cannot follow the command within the same sample)")
    return Plant(family, params, unit, source, order=(nn, nd))


PLANT_FILE_TABLES = ("plant", "signals")      # docs/PLANT.md


@dataclass(frozen=True)
class PlantFile:
    """A plant file as read (docs/PLANT.md): its [plant] table (None: the default eha plant) and its [signals]
    table (None: the recording is in rig's own format), each checked where it is used."""
    source: str
    plant: dict | None
    signals: dict | None


def read_plant_file(path: str | Path) -> PlantFile:
    """The plant file's tables (unreadable, not TOML, an unknown table: one ConfigError line)."""
    path = Path(path)
    text = read_text(path, "plant file", ConfigError)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML ({e})") from None
    unknown = sorted(set(data) - set(PLANT_FILE_TABLES))
    if unknown:
        near = difflib.get_close_matches(unknown[0], PLANT_FILE_TABLES, n=1)
        raise ConfigError(f"{path}: [{unknown[0]}]: not a table of a plant file (expected "
                          f"{' and '.join(f'[{t}]' for t in PLANT_FILE_TABLES)}"
                          + (f"; did you mean [{near[0]}]?)" if near else ")"))
    return PlantFile(str(path), data.get("plant"), data.get("signals"))


def plant_of(plant_file: PlantFile, p0: ActuatorParams | None = None) -> Plant:
    """The plant of a plant file's [plant] table (no table: the default eha plant), on the eha actuator p0."""
    if plant_file.plant is None:
        return eha_plant(p0, plant_file.source)
    return parse_plant(plant_file.plant, plant_file.source, p0)


def load_plant(path: str | Path, p0: ActuatorParams | None = None) -> Plant:
    """The plant of a plant file (its [plant] table; no table: the default eha plant)."""
    return plant_of(read_plant_file(path), p0)


def configured_actuator(config_path=None) -> ActuatorParams:
    """The eha actuator of the configuration's [actuator], [valve] and [fluid] (no configuration: Table 1)."""
    return ActuatorParams.from_config(load_config(config_path)) if config_path else ActuatorParams()


@dataclass(frozen=True)
class Subject:
    """A recording and the plant a command holds it against: the plant file's, else the eha actuator of the
    configuration (Table 1 without one); `against` names it for people."""
    rec: Recording
    plant: Plant
    against: str


def plant_for(plant_path=None, config_path=None) -> Plant:
    """The plant a recording is held against: the plant file's, else the eha actuator of the configuration's
    [actuator] (default Table 1)."""
    return _held_against(configured_actuator(config_path),
                         read_plant_file(plant_path) if plant_path is not None else None, config_path)


def _held_against(p0: ActuatorParams, plant_file: PlantFile | None, config_path) -> Plant:
    """The plant file's plant on the eha actuator p0; no plant file: that actuator, named by its configuration."""
    if plant_file is None:
        return eha_plant(p0, str(Path(config_path)) if config_path else "Table 1")
    return plant_of(plant_file, p0)


def load_subject(recording, plant_path=None, config_path=None) -> Subject:
    """Read the configuration, the plant file (once: its [plant] and its [signals]) and the recording (through
    that signal map when there is one), and check them together: the command's unit is the plant's input, the
    values plausible. One line for any problem (ConfigError, RecordingError)."""
    p0 = configured_actuator(config_path)
    plant_file = read_plant_file(plant_path) if plant_path is not None else None
    plant = _held_against(p0, plant_file, config_path)
    signals = plant_file.signals if plant_file is not None else None
    rec = load_recording_for(recording, None if signals is None else SignalMap.from_table(signals, plant_file.source))
    if plant.input_unit != rec.command_unit:       # the command (in the unit its signal map gave) is not the input
        what = "the valve voltage, V or mV" if plant.family == "eha" else f"input_unit = {plant.input_unit!r}"
        raise ConfigError(f"{plant_path}: [signals] command is in {rec.command_unit}: the {plant.family} plant's "
                          f"input is {what}")
    kinds = OUTPUT_KINDS.get("eha" if plant.family == "eha" else plant.output) \
        if plant.family != "transfer_function" else None          # a transfer function's output is anything
    if kinds is not None and rec.output_kind not in kinds:
        what = ("the piston position" if plant.family == "eha" else
                f"the axis's {plant.output} (output = {plant.output!r} in [plant])")
        raise ConfigError(f"{plant_path}: [signals] the measured output is in {rec.output_unit} ({rec.output_kind}), "
                          f"but the {plant.family} plant's output is {what}")
    check_plausible(rec)
    return Subject(rec, plant, plant.describe() if plant_path is not None else plant.source)

"""The plant file's signal map: another lab's recording (CSV, MATLAB .mat, HDF5) read as it is.

A plant file (TOML, docs/PLANT.md) has a `[signals]` table saying which column (CSV) or variable (.mat, HDF5
dataset path) holds time, the command, the position and, optionally, the acceleration and the closed loop's
reference, with a scale factor and a unit each. `SignalMap.from_table` checks the table (ConfigError: one line
naming the plant file and the key); `load_mapped` reads the data file through it into a `Recording` in SI units
(RecordingError: one line naming the data file and the key). The file is read by the one reader
(rig/recordings/files.py); the recording rules themselves (finite, uniform, long enough) are
rig/recordings/recording.py's `validated`, with the messages naming the file's own variables.

Column numbers are 0-based, as in Python: MATLAB's `data(:, 3)` is `data[:, 2]`.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.errors import ConfigError, RecordingError
from rig.recordings.files import (FORMATS, csv_text, file_format, open_hdf5, read_bytes, read_mat, read_table)
from rig.recordings.recording import UNIFORM_TOL, Recording, validated
from rig.recordings.rigformat import load_recording

SIGNALS = ("time", "command", "position", "acceleration", "reference")
# the measured output is `position` (a length or an angle), or `output` for any other quantity a sensor gives (a
# speed, a voltage, a pressure, a sensor's own units): one of the two
OUTPUT_KEYS = ("position", "output")
KEYS = SIGNALS + ("output", "format", "sample_rate_hz", "closed_loop", "start_s", "stop_s", "csv")
SIGNAL_KEYS = ("name", "column", "scale", "unit")
CSV_KEYS = ("delimiter", "skip_rows", "header", "comment")
SCALE_RANGE = (1e-12, 1e12)          # |scale|: beyond it a unit is wrong, not a sensor
RATE_RANGE_HZ = (1e-3, 1e7)

# unit -> (kind, factor to the kind's SI unit)
UNITS = {
    "s": ("time", 1.0), "ms": ("time", 1e-3), "us": ("time", 1e-6),
    "m": ("length", 1.0), "mm": ("length", 1e-3), "um": ("length", 1e-6), "µm": ("length", 1e-6),
    "nm": ("length", 1e-9),
    "rad": ("angle", 1.0), "mrad": ("angle", 1e-3), "deg": ("angle", math.pi / 180),
    "V": ("voltage", 1.0), "mV": ("voltage", 1e-3),
    "N": ("force", 1.0), "kN": ("force", 1e3),
    "A": ("current", 1.0), "mA": ("current", 1e-3),
    "Nm": ("torque", 1.0), "N m": ("torque", 1.0), "mNm": ("torque", 1e-3),
    "m/s^2": ("acceleration", 1.0), "mm/s^2": ("acceleration", 1e-3), "g": ("acceleration", 9.80665),
    "rad/s^2": ("angular acceleration", 1.0), "deg/s^2": ("angular acceleration", math.pi / 180),
    "m/s": ("velocity", 1.0), "mm/s": ("velocity", 1e-3),
    "rad/s": ("angular velocity", 1.0), "deg/s": ("angular velocity", math.pi / 180),
    "rpm": ("angular velocity", 2 * math.pi / 60),
    "Pa": ("pressure", 1.0), "kPa": ("pressure", 1e3), "MPa": ("pressure", 1e6), "bar": ("pressure", 1e5),
    "1": ("sensor units", 1.0),
}
SI_UNIT = {"time": "s", "length": "m", "angle": "rad", "voltage": "V", "force": "N", "current": "A",
           "torque": "N m", "acceleration": "m/s^2", "angular acceleration": "rad/s^2", "velocity": "m/s",
           "angular velocity": "rad/s", "pressure": "Pa", "sensor units": "1"}
KINDS = {"time": ("time",), "command": ("voltage", "force", "current", "torque"), "position": ("length", "angle"),
         "reference": ("length", "angle"), "acceleration": ("acceleration", "angular acceleration"),
         "output": ("length", "angle", "velocity", "angular velocity", "voltage", "current", "pressure",
                    "sensor units")}
ACCEL_OF = {"length": "acceleration", "angle": "angular acceleration"}
DEFAULT_UNIT = {"time": "s", "command": "V", "position": "m", "reference": "m", "acceleration": "m/s^2",
                "output": "1"}
_INDEXED = re.compile(r"^(?P<name>.+?)\s*\[\s*:\s*,\s*(?P<col>\d+)\s*\]$")      # data[:, 2]


def _units_of(key: str) -> str:
    return ", ".join(u for u, (kind, _) in UNITS.items() if kind in KINDS[key])


@dataclass(frozen=True)
class Signal:
    """One mapped signal: where it is in the file and how it becomes SI (value * scale, in unit)."""
    key: str                      # time, command, position, acceleration, reference
    name: str | None = None       # CSV header name, .mat variable (a.b for a struct field), HDF5 dataset path
    column: int | None = None     # 0-based: a matrix's column, or (CSV without names) the column's index
    scale: float = 1.0
    unit: str = ""

    @property
    def kind(self) -> str:
        return UNITS[self.unit][0]

    @property
    def si_unit(self) -> str:
        return SI_UNIT[self.kind]

    @property
    def factor(self) -> float:
        """File value -> SI."""
        return self.scale * UNITS[self.unit][1]

    def where(self) -> str:
        if self.name is None:
            return f"column {self.column}"
        return repr(self.name) + ("" if self.column is None else f"[:, {self.column}]")

    def label(self) -> str:
        return f"{self.where()} ([signals] {self.key})"

    def describe(self) -> dict:
        return {"name": self.name, "column": self.column, "scale": self.scale, "unit": self.unit,
                "si_unit": self.si_unit}


@dataclass(frozen=True)
class CsvOptions:
    delimiter: str | None = None   # None: detected (",", ";", tab, else whitespace); "whitespace": spaces/tabs
    skip_rows: int = 0             # preamble lines before the names (or the data)
    header: bool | None = None     # None: detected (a first line that is not all numbers names the columns)
    comment: str = "#"


@dataclass(frozen=True)
class SignalMap:
    """The `[signals]` table of a plant file, checked."""
    source: str                   # the plant file (for messages)
    command: Signal
    position: Signal
    time: Signal | None = None
    acceleration: Signal | None = None
    reference: Signal | None = None
    sample_rate_hz: float | None = None
    format: str | None = None
    closed_loop: str = ""
    start_s: float | None = None
    stop_s: float | None = None
    csv: CsvOptions = field(default_factory=CsvOptions)

    @property
    def signals(self) -> tuple[Signal, ...]:
        return tuple(s for s in (self.time, self.command, self.position, self.acceleration, self.reference) if s)

    @classmethod
    def from_table(cls, table: dict, source: str) -> "SignalMap":
        """Check a `[signals]` table; every problem is one ConfigError line naming `source` and the key."""
        where = f"{source}: [signals]"
        _check_keys(table, KEYS, f"{where}:", "a table")
        if "command" not in table:
            raise ConfigError(f"{where}: command missing (the column or variable holding the plant's command)")
        given = [k for k in OUTPUT_KEYS if k in table]
        if len(given) != 1:
            raise ConfigError(f"{where}: " + ("position and output both given (the measured output is one of them: "
                                             "position for a length or an angle, output for any other quantity)"
                                             if given else "position missing (the column or variable holding the "
                                             "measured position; or output = ... for another quantity: a speed, "
                                             "a voltage, a pressure)"))
        out_key = given[0]
        pos = _signal(out_key, table[out_key], where, DEFAULT_UNIT[out_key])
        if pos.kind not in ACCEL_OF and any(k in table for k in ("reference", "acceleration")):
            k = next(k for k in ("reference", "acceleration") if k in table)
            raise ConfigError(f"{where} {k}: given with an output in {pos.unit} ({pos.kind}); a {k} goes with a "
                              f"position (a length or an angle)")
        # a rotary axis (position in rad or deg): its reference and acceleration are angular too
        want = {"reference": pos.kind, "acceleration": ACCEL_OF.get(pos.kind)}
        sig = {k: pos if k == out_key else _signal(k, table[k], where, SI_UNIT.get(want.get(k), DEFAULT_UNIT[k]))
               for k in SIGNALS + ("output",) if k in table}
        for key, kind in want.items():
            if key in sig and sig[key].kind != kind:
                raise ConfigError(f"{where} {key}.unit = {sig[key].unit!r}: a unit of {sig[key].kind}, but the "
                                  f"position is {'an angle' if pos.kind == 'angle' else 'a length'} (expected {kind})")
        fs = table.get("sample_rate_hz")
        if fs is not None:
            fs = _number(fs, f"{where} sample_rate_hz", lo=RATE_RANGE_HZ[0], hi=RATE_RANGE_HZ[1], unit=" Hz")
        if "time" not in sig and fs is None:
            raise ConfigError(f"{where}: neither time nor sample_rate_hz (name the time column or variable, or give "
                              f"the sample rate when the file has no time vector)")
        fmt = table.get("format")
        if fmt is not None and fmt not in FORMATS:
            raise ConfigError(f"{where} format = {fmt!r}: expected one of {', '.join(FORMATS)} (or leave it out: "
                              f"the format is read from the file)")
        closed = table.get("closed_loop", "")
        if isinstance(closed, bool):
            closed = "stated closed loop in the plant file" if closed else ""
        if not isinstance(closed, str):
            raise ConfigError(f"{where} closed_loop: expected text (why the command depends on the output), "
                              f"got {closed!r}"[:200])
        start, stop = (_number(table[k], f"{where} {k}", unit=" s") if k in table else None
                       for k in ("start_s", "stop_s"))
        if start is not None and stop is not None and not stop > start:
            raise ConfigError(f"{where} stop_s = {stop:g}: expected > start_s = {start:g}")
        return cls(source=source, command=sig["command"], position=pos, time=sig.get("time"),
                   acceleration=sig.get("acceleration"), reference=sig.get("reference"), sample_rate_hz=fs,
                   format=fmt, closed_loop=closed.strip(), start_s=start, stop_s=stop,
                   csv=_csv_options(table.get("csv", {}), where))


def _check_keys(value, valid: tuple[str, ...], what: str, expected: str) -> None:
    if not isinstance(value, dict):
        raise ConfigError(f"{what} expected {expected}, got {value!r}"[:200])
    unknown = [k for k in value if k not in valid]
    if unknown:
        raise ConfigError(f"{what} unknown key {str(unknown[0])[:40]!r} (valid: {', '.join(valid)})")


def _number(v, what: str, *, lo: float | None = None, hi: float | None = None, unit: str = "") -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{what}: expected a number{unit and ' in' + unit}, got {v!r}"[:200])
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(f"{what} = {v:g}: expected {lo:g} to {hi:g}{unit}")
    return float(v)


def _signal(key: str, value, where: str, default_unit: str) -> Signal:
    """A signal given as "name", "data[:, 2]", a column index (CSV without names) or a table."""
    what = f"{where} {key}"
    if isinstance(value, str) or (isinstance(value, int) and not isinstance(value, bool)):
        value = {"name": value} if isinstance(value, str) else {"column": value}
    _check_keys(value, SIGNAL_KEYS, what + ":", "a name, a column number or a table { name = ..., scale = ..., "
                "unit = ... }")
    name, column = value.get("name"), value.get("column")
    if name is not None:
        if not isinstance(name, str) or not name.strip():
            raise ConfigError(f"{what}.name: expected the column or variable name as text, got {name!r}"[:200])
        m = _INDEXED.match(name.strip())
        if m:
            if column is not None:
                raise ConfigError(f"{what}: column given twice ({name!r} and column = {column!r})"[:200])
            name, column = m["name"], int(m["col"])
        name = name.strip()
    if column is not None and (isinstance(column, bool) or not isinstance(column, int) or not 0 <= column < 100_000):
        raise ConfigError(f"{what}.column: expected a 0-based column number, got {column!r}"[:200])
    if name is None and column is None:
        raise ConfigError(f"{what}: needs name (column or variable) or column (a number)")
    scale = value.get("scale", 1.0)
    scale = _number(scale, f"{what}.scale")
    if not SCALE_RANGE[0] <= abs(scale) <= SCALE_RANGE[1]:
        raise ConfigError(f"{what}.scale = {scale:g}: expected a magnitude of {SCALE_RANGE[0]:g} to "
                          f"{SCALE_RANGE[1]:g} (negative to invert the sign)")
    unit = value.get("unit", default_unit)
    if not isinstance(unit, str) or unit not in UNITS:
        raise ConfigError(f"{what}.unit = {unit!r}: unknown unit (valid for {key}: {_units_of(key)})"[:300])
    if UNITS[unit][0] not in KINDS[key]:
        raise ConfigError(f"{what}.unit = {unit!r}: a unit of {UNITS[unit][0]}, not of the {key} "
                          f"(valid: {_units_of(key)})")
    return Signal(key, name, column, scale, unit)


def _csv_options(value, where: str) -> CsvOptions:
    what = f"{where} csv"
    _check_keys(value, CSV_KEYS, what + ":", "a table { delimiter = ..., skip_rows = ..., header = ... }")
    d = value.get("delimiter")
    if d == " ":
        d = "whitespace"
    if d is not None and d != "whitespace" and (not isinstance(d, str) or len(d) != 1 or d.isalnum()
                                                or d in "\r\n\"'.+-#"):
        raise ConfigError(f"{what}.delimiter: expected one character (\",\", \";\", \"\\t\") or \"whitespace\", "
                          f"got {d!r}"[:200])
    skip = value.get("skip_rows", 0)
    if isinstance(skip, bool) or not isinstance(skip, int) or not 0 <= skip <= 1_000_000:
        raise ConfigError(f"{what}.skip_rows: expected a line count >= 0, got {skip!r}"[:200])
    header = value.get("header")
    if header is not None and not isinstance(header, bool):
        raise ConfigError(f"{what}.header: expected true (the first line names the columns) or false, got "
                          f"{header!r}"[:200])
    comment = value.get("comment", "#")
    if not isinstance(comment, str) or not comment.strip() or comment != comment.strip():
        raise ConfigError(f"{what}.comment: expected the characters that start a comment line, got {comment!r}"[:200])
    return CsvOptions(d, skip, header, comment)


# ---- reading the data file ----------------------------------------------------------------------------------

def _vector(a, sig: Signal, source: str, plant: str) -> np.ndarray:
    """The signal's samples from what the file holds: a vector (any orientation) or a matrix's column."""
    a = np.asarray(a)
    what = f"{source}: {sig.label()} of {plant}"
    if a.ndim == 2 and sig.column is not None:
        if not 0 <= sig.column < a.shape[1]:
            raise RecordingError(f"{what}: no column {sig.column} in a {a.shape[0]} x {a.shape[1]} matrix (columns "
                                 f"are 0-based: 0 to {a.shape[1] - 1})")
        return a[:, sig.column]
    if sig.column is not None and a.ndim != 2:
        raise RecordingError(f"{what}: a column asked but the variable has shape {a.shape}, not a matrix")
    if a.ndim == 2 and 1 in a.shape:
        return a.ravel()
    if a.ndim != 1:
        raise RecordingError(f"{what}: shape {a.shape}, expected a vector; for a matrix's column give "
                             f"name = \"{sig.name}[:, 0]\" (0-based)")
    return a


def _missing(sig: Signal, source: str, plant: str, have: list[str], what: str = "variable") -> RecordingError:
    few = ", ".join(have[:8]) + (f", ... ({len(have)} in all)" if len(have) > 8 else "")
    return RecordingError(f"{source}: no {what} {sig.name!r} ([signals] {sig.key} of {plant}); the file has: "
                          f"{few or 'none'}"[:400])


def _read_csv(text: str, source: str, smap: SignalMap) -> dict[str, np.ndarray]:
    opts, plant = smap.csv, smap.source
    table = read_table(text, source, delimiter=opts.delimiter, skip_rows=opts.skip_rows, comment=opts.comment,
                       header=opts.header, expected=f"([signals] csv.delimiter of {plant})")
    names = table.names
    cols = {}
    for sig in smap.signals:
        if sig.name is not None and sig.column is not None:
            raise RecordingError(f"{source}: a CSV file, but {sig.label()} of {plant} names a matrix's column "
                                 f"(a CSV column is named or numbered, not both)")
        if sig.name is not None:
            if names is None:
                raise RecordingError(f"{source}: no header row names the columns ([signals] {sig.key} = "
                                     f"{sig.name!r} of {plant}): give its column number, {sig.key} = N")
            if sig.name not in names:
                raise _missing(sig, source, plant, names, "column")
            if names.count(sig.name) > 1:
                raise RecordingError(f"{source}: column {sig.name!r} ([signals] {sig.key}) appears "
                                     f"{names.count(sig.name)} times in the header")
            cols[sig.key] = names.index(sig.name)
        else:
            if sig.column >= len(table.first):
                raise RecordingError(f"{source}: {sig.label()} of {plant}: the file has {len(table.first)} columns "
                                     f"(0-based)")
            cols[sig.key] = sig.column
    use = sorted(set(cols.values()))
    data = table.columns(use)
    return {key: data[:, use.index(c)] for key, c in cols.items()}


def _read_mat(raw: bytes, source: str, smap: SignalMap) -> dict[str, np.ndarray]:
    m = read_mat(raw, source)
    have = [k for k in m if not k.startswith("__")]
    out = {}
    for sig in smap.signals:
        if sig.name is None:
            raise RecordingError(f"{source}: a MATLAB file, but {sig.label()} of {smap.source} has no name (give "
                                 f"the variable)")
        cur, parts = m, re.split(r"[./]", sig.name.strip("/"))
        for i, part in enumerate(parts):          # a.b: field b of struct a
            fields = list(cur) if isinstance(cur, dict) else list(cur.dtype.names or ())
            if part not in fields or (not isinstance(cur, dict) and cur.size != 1):
                raise _missing(sig, source, smap.source, have if i == 0 else fields)
            cur = cur[part] if isinstance(cur, dict) else cur[part].flat[0]
        out[sig.key] = _vector(cur, sig, source, smap.source)
    return out


def _read_hdf5(path: Path, source: str, smap: SignalMap, matlab: bool) -> dict[str, np.ndarray]:
    import h5py          # lazy: h5py is loaded only for HDF5 files
    out = {}
    with open_hdf5(path, source) as f:
        for sig in smap.signals:
            if sig.name is None:
                raise RecordingError(f"{source}: an HDF5 file, but {sig.label()} of {smap.source} has no name "
                                     f"(give the dataset path)")
            ds = f.get(sig.name) if sig.name in f else f.get(sig.name.replace(".", "/"))
            if not isinstance(ds, h5py.Dataset):
                have = []
                f.visititems(lambda n, o: have.append(n) if isinstance(o, h5py.Dataset) else None)
                raise _missing(sig, source, smap.source, have, "dataset")
            a = np.asarray(ds[()])
            # MATLAB v7.3 stores column-major: an n x k matrix is a (k, n) dataset
            out[sig.key] = _vector(a.T if matlab and a.ndim == 2 else a, sig, source, smap.source)
    return out


def _window(cols: dict[str, np.ndarray], smap: SignalMap, source: str) -> dict[str, np.ndarray]:
    if smap.start_s is None and smap.stop_s is None:
        return cols
    t = cols["time_s"]
    with np.errstate(invalid="ignore"):
        inside = np.flatnonzero((t >= (smap.start_s if smap.start_s is not None else -np.inf)) &
                                (t <= (smap.stop_s if smap.stop_s is not None else np.inf)))
    if inside.size == 0:
        span = " and ".join(f"{k} = {v:g} s" for k, v in (("start_s", smap.start_s), ("stop_s", smap.stop_s))
                            if v is not None)
        raise RecordingError(f"{source}: no samples within {span} ([signals] of {smap.source}); the time runs "
                             f"{np.nanmin(t):.6g} to {np.nanmax(t):.6g} s")
    sel = slice(int(inside[0]), int(inside[-1]) + 1)
    return {k: (a[sel] if a.shape[:1] == t.shape else a) for k, a in cols.items()}


def load_mapped(path, smap: SignalMap) -> Recording:
    """Read a data file through a signal map into a Recording in SI units (command in its own SI unit,
    `command_unit`). Raises RecordingError (the data) or ConfigError (a map that cannot apply to this file)."""
    path = Path(path)
    source = str(path)
    raw = read_bytes(path)
    fmt = file_format(raw, path, smap.format, f"[signals] format = {smap.format!r} of {smap.source}")
    if fmt == "csv":
        got = _read_csv(csv_text(raw, source, path), source, smap)
    elif fmt == "mat":
        got = _read_mat(raw, source, smap)
    else:
        got = _read_hdf5(path, source, smap, matlab=fmt == "mat73")
    by_key = {s.key: s for s in smap.signals}
    for key, a in got.items():
        if a.dtype.kind not in "iuf" and a.dtype != np.bool_:
            raise RecordingError(f"{source}: {by_key[key].label()} is not numeric (dtype {a.dtype})")
    si = {key: np.asarray(a, dtype=float) * by_key[key].factor for key, a in got.items()}
    n = si["command"].shape[0]
    time_label = (smap.time.label() if smap.time else
                  f"the time base of [signals] sample_rate_hz = {smap.sample_rate_hz:g}")
    cols = {"time_s": si["time"] if smap.time else np.arange(n) / smap.sample_rate_hz,
            "valve_cmd_V": si["command"], "position_m": si[smap.position.key],
            "accel_mps2": si.get("acceleration", np.zeros(n))}
    if smap.reference:
        cols["reference"] = si["reference"]
    cols = _window(cols, smap, source)
    labels = {"time_s": time_label, "valve_cmd_V": smap.command.label(), "position_m": smap.position.label(),
              "accel_mps2": smap.acceleration.label() if smap.acceleration else "acceleration (zeros)"}
    ref = cols.pop("reference", None)
    rec = validated(cols, source, labels)
    if ref is not None:        # checked as a signal, and mended as the signals were
        ref = validated({**cols, "accel_mps2": ref}, source,
                         {**labels, "accel_mps2": smap.reference.label()}).accel_mps2
    if smap.time and smap.sample_rate_hz and abs(rec.fs_hz / smap.sample_rate_hz - 1) > UNIFORM_TOL:
        raise RecordingError(f"{source}: {smap.time.label()} gives {rec.fs_hz:.6g} Hz but [signals] sample_rate_hz "
                             f"= {smap.sample_rate_hz:g} in {smap.source}: inconsistent (leave one out)")
    rec.command_unit = smap.command.si_unit
    rec.output_unit = smap.position.si_unit
    rec.output_kind = smap.position.kind
    rec.accel_present = smap.acceleration is not None
    rec.reference_m = ref
    rec.closed_loop = smap.closed_loop or (f"a loop following the reference {smap.reference.where()} "
                                           f"([signals] reference of {smap.source})" if ref is not None else "")
    rec.meta = {"signal_map": {
        "plant_file": smap.source, "format": fmt, "fs_hz": rec.fs_hz,
        "time": smap.time.describe() if smap.time else {"sample_rate_hz": smap.sample_rate_hz},
        **{s.key: s.describe() for s in smap.signals if s.key != "time"},
        "window_s": [smap.start_s, smap.stop_s], "closed_loop": rec.closed_loop}}
    return rec


# ---- what the commands read ---------------------------------------------------------------------------------

def load_recording_for(path, smap: SignalMap | None = None) -> Recording:
    """The recording REC as a command reads it: through its plant file's signal map when it has one, else rig's
    own formats (rig.recordings.rigformat.load_recording). The plant file is read by rig.plant.file."""
    if smap is not None:
        return load_mapped(path, smap)
    return load_recording(path)

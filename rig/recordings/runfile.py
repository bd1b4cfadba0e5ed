"""A run recording of the four-mount rig, read as docs/RUN_RECORDING.md describes it (and nothing else).

The layout is what `rig run --record` and `rig hil` write: HDF5, root attribute rate_hz, one float64 dataset per
channel with its unit as the attribute `unit`, four-wide per-mount channels in MOUNTS order (their `labels`
attribute may name the mounts). Read: time_s, accel_mps2, stroke_m, valve_cmd_V; optional floor_accel_mps2,
lifecycle_state, isolation_on, feedforward_on. Rows missing from time_s are mended as every reader of rig does
(rig.recordings.recording.mend_gaps: short gaps bridged, else the longest stretch). Every problem is one line naming the
file and the dataset or attribute (RecordingError).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.config import MOUNTS
from rig.errors import RecordingError
from rig.recordings.files import check_file, open_hdf5
from rig.recordings.recording import PLAUSIBLE_ABS, mend_gaps

REQUIRED = ("time_s", "accel_mps2", "stroke_m", "valve_cmd_V")
OPTIONAL = ("floor_accel_mps2", "lifecycle_state", "isolation_on", "feedforward_on")
PER_MOUNT = ("accel_mps2", "stroke_m", "valve_cmd_V", "floor_accel_mps2")
# accepted units of each channel and their factor to SI (a dataset without `unit` is taken as SI)
UNITS = {"time_s": {"s": 1.0},
         "accel_mps2": {"m/s^2": 1.0, "m/s2": 1.0, "g": 9.80665, "mm/s^2": 1e-3},
         "floor_accel_mps2": {"m/s^2": 1.0, "m/s2": 1.0, "g": 9.80665, "mm/s^2": 1e-3},
         "stroke_m": {"m": 1.0, "mm": 1e-3, "um": 1e-6},
         "position_m": {"m": 1.0, "mm": 1e-3, "um": 1e-6},            # a chirp's transducer (rig chirp)
         "valve_cmd_V": {"V": 1.0, "mV": 1e-3}}
MIN_SECONDS = 5.0            # shorter: too little of the floor's 1 Hz band for any claim
STATE_ACTIVE, STATE_INACTIVE = 2.0, 1.0       # lifecycle_state codes (0 UNCONFIGURED, 1 INACTIVE, 2 ACTIVE, 3 FAULT)
MODES = ("off", "feedback", "feedback_feedforward")


@dataclass
class RunRecording:
    """The signals of one run, SI units, one row per loop period (rows mended), mounts in MOUNTS order."""
    source: str
    fs_hz: float
    t_s: np.ndarray
    accel_mps2: np.ndarray            # (n, 4) machine at each mount, absolute
    stroke_m: np.ndarray              # (n, 4) piston relative to housing
    valve_cmd_V: np.ndarray           # (n, 4) command written at each row
    floor_accel_mps2: np.ndarray | None = None     # (n, 4) when floor accelerometers were fitted
    mode: np.ndarray | None = None    # per row: 0 off, 1 feedback, 2 feedback + feedforward, -1 fault (None: unknown)
    attrs: dict = field(default_factory=dict)
    gaps: str = ""                    # what was done about rows missing ("" when none were)

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def duration_s(self) -> float:
        return self.n / self.fs_hz

    @property
    def floor_measured(self) -> bool:
        return self.floor_accel_mps2 is not None

    def mode_seconds(self) -> dict[str, float]:
        """Seconds of each isolation mode (and of fault rows), from the recorded flags."""
        if self.mode is None:
            return {}
        out = {m: float(np.sum(self.mode == k)) / self.fs_hz for k, m in enumerate(MODES)}
        out["fault"] = float(np.sum(self.mode < 0)) / self.fs_hz
        return {k: v for k, v in out.items() if v > 0}


def is_run_recording(path) -> bool:
    """Whether `path` is an HDF5 file with the four-mount channels of docs/RUN_RECORDING.md."""
    import h5py
    try:
        with h5py.File(path, "r") as f:
            return all(k in f and f[k].ndim == 2 and f[k].shape[1] == len(MOUNTS)
                       for k in ("accel_mps2", "stroke_m", "valve_cmd_V"))
    except (OSError, ValueError):
        return False


def _unit_factor(ds, name: str, where: str) -> float:
    return unit_factor(ds.attrs.get("unit", None), name, where)


def unit_factor(unit, name: str, where: str) -> float:
    """The factor from dataset `name`'s unit attribute to SI (none or "": SI); RecordingError for one not in UNITS."""
    if unit is None or unit == "" or unit == b"":
        return 1.0
    unit = unit.decode() if isinstance(unit, bytes) else str(unit)
    table = UNITS.get(name, {})
    if table and unit not in table:
        raise RecordingError(f"{where}: dataset {name}: unit {unit!r} (expected one of {', '.join(table)})")
    return table.get(unit, 1.0)


def _dataset(f, name: str, where: str) -> np.ndarray:
    ds = f[name]
    v = np.asarray(ds[()], dtype=float) * _unit_factor(ds, name, where)
    if name in PER_MOUNT and (v.ndim != 2 or v.shape[1] != len(MOUNTS)):
        raise RecordingError(f"{where}: dataset {name}: expected shape (rows, {len(MOUNTS)}) (one column per mount: "
                             f"{', '.join(MOUNTS)}), got {v.shape}")
    if name not in PER_MOUNT and v.ndim != 1:
        raise RecordingError(f"{where}: dataset {name}: expected one value per row, got shape {v.shape}")
    labels = ds.attrs.get("labels")
    if name in PER_MOUNT and labels is not None:
        got = [x.decode() if isinstance(x, bytes) else str(x) for x in labels]
        if got != list(MOUNTS):
            raise RecordingError(f"{where}: dataset {name}: columns labelled {got}, expected {list(MOUNTS)}")
    return v


def _modes(cols: dict) -> np.ndarray | None:
    """Per row 0 off, 1 feedback, 2 feedback + feedforward, -1 fault or unconfigured (rig/report.py's rule)."""
    if "lifecycle_state" not in cols or "isolation_on" not in cols:
        return None
    life = cols["lifecycle_state"]
    iso = cols["isolation_on"] > 0.5
    ff = cols["feedforward_on"] > 0.5 if "feedforward_on" in cols else np.zeros_like(iso)
    active = np.abs(life - STATE_ACTIVE) < 0.5
    code = np.where(active & iso, np.where(ff, 2, 1), 0)
    ok = (np.abs(life - STATE_INACTIVE) < 0.5) | active
    return np.where(ok, code, -1)


def read_run(path) -> RunRecording:
    """The run recording at `path` (RecordingError naming the file and what is wrong)."""
    p = Path(path)
    where = str(p)
    check_file(p, "no such recording")
    with open_hdf5(p, where, "run recording (docs/RUN_RECORDING.md)") as f:
        missing = [k for k in REQUIRED if k not in f]
        if missing:
            raise RecordingError(f"{where}: no dataset {', '.join(missing)} (a run recording of the four-mount rig "
                                 f"has {', '.join(REQUIRED)}: docs/RUN_RECORDING.md)")
        fs = f.attrs.get("rate_hz")
        try:
            fs = float(fs)
        except (TypeError, ValueError):
            fs = math.nan
        if not (math.isfinite(fs) and fs > 0):
            raise RecordingError(f"{where}: attribute rate_hz missing or not a positive number (the loop rate, Hz)")
        cols = {k: _dataset(f, k, where) for k in REQUIRED + OPTIONAL if k in f}
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()
                 if isinstance(v, (str, bytes, int, float, np.generic))}
    return _assemble(cols, fs, where, attrs)


def _check_time(t: np.ndarray, fs: float, where: str) -> None:
    """time_s increases, by the period of the rate_hz attribute (its median step within 1 %)."""
    dt = np.diff(t)
    if len(dt) == 0:
        return
    if not (dt > 0).all():
        k = int(np.argmax(~(dt > 0))) + 1
        raise RecordingError(f"{where}: dataset time_s: not increasing at row {k} ({t[k - 1]:.6g} then {t[k]:.6g} s)")
    step = float(np.median(dt))
    if abs(step * fs - 1.0) > 0.01:
        raise RecordingError(f"{where}: attribute rate_hz = {fs:g} Hz, but time_s steps by {step:.6g} s "
                             f"({1.0 / step:.6g} Hz): one of them was changed")


def _assemble(cols: dict, fs: float, where: str, attrs: dict) -> RunRecording:
    n = min(len(v) for v in cols.values())
    cols = {k: v[:n] for k, v in cols.items()}            # a run cut short: the rows every channel has
    flat = {"time_s": cols["time_s"]}
    for k, v in cols.items():
        if k != "time_s":
            for j in range(v.shape[1] if v.ndim == 2 else 1):
                flat[f"{k}#{j}"] = v[:, j] if v.ndim == 2 else v
    flat, gaps = mend_gaps(flat, where)
    out = {}
    for k, v in cols.items():
        if k == "time_s":
            out[k] = np.asarray(flat["time_s"])
        elif v.ndim == 2:
            out[k] = np.column_stack([flat[f"{k}#{j}"] for j in range(v.shape[1])])
        else:
            out[k] = np.asarray(flat[f"{k}#0"])
    for k, like in (("accel_mps2", "accel_mps2"), ("stroke_m", "position_m"), ("valve_cmd_V", "valve_cmd_V"),
                    ("floor_accel_mps2", "accel_mps2")):
        if k in out and not np.all(np.isfinite(out[k])):
            bad = int(np.argmax(~np.all(np.isfinite(out[k]), axis=1)))
            raise RecordingError(f"{where}: dataset {k}: not a finite number at row {bad} (t = {out['time_s'][bad]:.6g} "
                                 f"s): cut the recording before it")
        if k in out and (np.abs(out[k]) > PLAUSIBLE_ABS[like]).any():          # the one-channel readers' limits
            bad = int(np.argmax((np.abs(out[k]) > PLAUSIBLE_ABS[like]).any(axis=1)))
            raise RecordingError(f"{where}: dataset {k}: {np.abs(out[k][bad]).max():.6g} at row {bad}: not a "
                                 f"plausible value (expected below {PLAUSIBLE_ABS[like]:g}); check its unit")
    _check_time(out["time_s"], fs, where)
    m = len(out["time_s"])
    if m / fs < MIN_SECONDS:
        raise RecordingError(f"{where}: {m / fs:.2f} s of rows; the diagnosis of a run needs at least "
                             f"{MIN_SECONDS:g} s (the floor's 1 Hz band)")
    for k in ("lifecycle_state", "isolation_on", "feedforward_on"):
        if k in out:
            out[k] = np.rint(out[k])
    return RunRecording(where, fs, out["time_s"], out["accel_mps2"], out["stroke_m"], out["valve_cmd_V"],
                        out.get("floor_accel_mps2"), _modes(out), attrs, gaps)

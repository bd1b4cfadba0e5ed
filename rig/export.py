"""A recording for MATLAB and spreadsheets (`rig export REC --to mat|csv`): every dataset with its unit, its
description and its column labels (the mounts, the controller states), the file's attributes and the events.

Read from the HDF5 of the rig's recorder (`rig run --record`, `rig chirp`, `rig hil`, a console recording) by
rig.runtime.recorder.read_recording (a file cut short by a crash: the rows every dataset has), plus each
dataset's `labels` and `description` attributes.

- .mat (MATLAB v5, scipy.io.savemat): one variable per dataset under its own name (rows are periods, a column
  per label: `plot(time_s, accel_mps2)`), and the struct `meta`: source, attrs (the file's attributes), units,
  descriptions and labels per dataset, events (time_s, text). A chirp's variables carry the names rig's own
  loader reads (time_s, valve_cmd_V, position_m, accel_mps2): `rig identify X.mat` takes the export.
- .csv (or .csv.gz): one header line, a column per dataset column named `dataset` or `dataset.label`
  (the datasets' names carry their units: accel_mps2, stroke_m, valve_cmd_V, time_s, wake_latency_us), one
  row per period, 12 significant digits, NaN as `nan`. Beside it `FILE.meta.json` (the columns with their
  dataset, label, unit and description; the attributes; the events) and `FILE.events.csv` (time_s,text).
"""
from __future__ import annotations

import csv
import gzip
import io
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.errors import RecordingError
from rig.recordings.files import check_file, open_hdf5
from rig.runtime.recorder import read_recording

FORMATS = ("mat", "csv")
MAT_VARIABLE_MAX_BYTES = 2 ** 31 - 1      # MATLAB v5: a variable's size field is 32 bits
CSV_DIGITS = 12
CSV_CHUNK_ROWS = 20000


@dataclass
class Exported:
    """A recording as exported: datasets (rows = periods), and what describes them."""
    source: str
    data: dict[str, np.ndarray]
    units: dict[str, str]
    descriptions: dict[str, str]
    labels: dict[str, list[str]]
    attrs: dict
    events: list[tuple[float, str]] = field(default_factory=list)

    @property
    def rows(self) -> int:
        return len(self.data["time_s"])

    def columns(self) -> list[dict]:
        """Every dataset column: {name, dataset, label, unit, description}, in the file's dataset order."""
        out = []
        for name, a in self.data.items():
            labels = self.labels.get(name) or []
            width = 1 if a.ndim == 1 else a.shape[1]
            if a.ndim == 1 or width == 1 and not labels:
                out.append({"name": name, "dataset": name, "label": labels[0] if labels else "",
                            "unit": self.units[name], "description": self.descriptions[name]})
                continue
            for i in range(width):
                lab = labels[i] if len(labels) == width else str(i)
                out.append({"name": f"{name}.{lab}", "dataset": name, "label": lab, "unit": self.units[name],
                            "description": self.descriptions[name]})
        return out

    def table(self, a: int = 0, b: int | None = None) -> np.ndarray:
        """Rows a..b of every column, as the CSV has them (float64)."""
        parts = [np.asarray(x[a:b], dtype=float).reshape(len(x[a:b]), -1) for x in self.data.values()]
        return np.concatenate(parts, axis=1)


def load(path) -> Exported:
    """The recording at `path` (RecordingError, one line naming the file, when it is not one of the rig's)."""
    p = Path(path)
    check_file(p, "no such recording (expected the HDF5 file of rig run --record, rig chirp or rig hil)")
    try:
        r = read_recording(p)
    except RecordingError as e:                  # h5py's reasons run over several lines: the first says it
        raise RecordingError(str(e).splitlines()[0]) from None
    if "time_s" not in r:
        raise RecordingError(f"{p}: no time_s dataset (expected a recording of rig run --record, rig chirp or "
                             f"rig hil)")
    skip = ("attrs", "units", "events")
    # time first, then the recorder's channel order, then any other dataset
    order = ["time_s"] + [c for c in r["attrs"].get("channels", []) if c in r] + sorted(r)
    data = {k: np.asarray(r[k]) for k in dict.fromkeys(order) if k not in skip}
    bad = [k for k, v in data.items() if v.dtype.kind not in "fiub" or v.ndim > 2]
    if bad:
        raise RecordingError(f"{p}: dataset {bad[0]} is not a column of numbers (expected a recording of rig run "
                             f"--record, rig chirp or rig hil)")
    labels, descriptions = {}, {}
    with open_hdf5(p, str(p), "recording") as f:       # the one reader of files: says if the writer did not close it
        for k in data:
            a = f[k].attrs
            labels[k] = [_text(x) for x in np.atleast_1d(a["labels"])] if "labels" in a else []
            descriptions[k] = _text(a.get("description", ""))
    return Exported(str(p), data, {k: _text(r["units"].get(k, "")) for k in data}, descriptions, labels,
                    r["attrs"], list(r["events"]))


def _text(x) -> str:
    return x.decode() if isinstance(x, bytes) else str(x)


# ---- MATLAB ----------------------------------------------------------------------------------------------
def _field(name: str) -> str:
    """A MATLAB struct field name for `name` (a letter first, letters, digits and _, at most 63)."""
    f = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return (f if f[:1].isalpha() else "x" + f)[:63]


def _cell(strings) -> np.ndarray:
    """A column cell array of strings."""
    out = np.empty((len(strings), 1), dtype=object)
    for i, s in enumerate(strings):
        out[i, 0] = s
    return out


def _mat_value(v):
    if isinstance(v, (list, tuple)):
        return _cell([str(x) for x in v]) if any(isinstance(x, str) for x in v) else np.asarray(v, dtype=float)
    if v is None:
        return np.empty((0, 0))
    return v


def write_mat(exp: Exported, path) -> Path:
    """The .mat file: a variable per dataset and the struct `meta` (module docstring)."""
    import scipy.io
    path = Path(path)
    big = [k for k, a in exp.data.items() if a.nbytes > MAT_VARIABLE_MAX_BYTES]
    if big:
        raise RecordingError(f"{exp.source}: dataset {big[0]} holds {exp.data[big[0]].nbytes / 2 ** 30:.1f} GiB, "
                             f"more than a .mat (v5) variable can (2 GiB): export --to csv")
    if "meta" in exp.data:
        raise RecordingError(f"{exp.source}: a dataset is named meta, the name of the export's metadata struct")
    names = list(exp.data)
    meta = {"source": exp.source, "exported_by": "rig export", "rows": exp.rows,
            "datasets": _cell(names),
            "attrs": {_field(k): _mat_value(v) for k, v in exp.attrs.items()},
            "units": {_field(k): exp.units[k] for k in names},
            "descriptions": {_field(k): exp.descriptions[k] for k in names},
            "labels": {_field(k): _cell(exp.labels[k]) for k in names if exp.labels[k]},
            "events": {"time_s": np.array([t for t, _ in exp.events], dtype=float).reshape(-1, 1),
                       "text": _cell([x for _, x in exp.events])}}
    scipy.io.savemat(path, {**{_field(k): exp.data[k] for k in names}, "meta": meta}, oned_as="column",
                     long_field_names=True, do_compression=True)
    return path


# ---- CSV ---------------------------------------------------------------------------------------------------
def sidecars(path) -> tuple[Path, Path]:
    """The CSV export's metadata and events files beside it."""
    path = Path(path)
    stem = path.name[:-3] if path.name.lower().endswith(".gz") else path.name
    stem = stem[:-4] if stem.lower().endswith(".csv") else stem
    return path.with_name(stem + ".meta.json"), path.with_name(stem + ".events.csv")


def write_csv(exp: Exported, path, progress=None) -> list[Path]:
    """The CSV (gzip if it ends in .gz) and its two sidecars; progress(rows done, rows) between chunks.
    Returns the files written."""
    path = Path(path)
    cols = exp.columns()
    fmt = f"%.{CSV_DIGITS}g"
    opener = gzip.open if path.suffix.lower() == ".gz" else open
    with opener(path, "wt", newline="") as f:
        f.write(",".join(c["name"] for c in cols) + "\n")
        for a in range(0, exp.rows, CSV_CHUNK_ROWS):
            buf = io.StringIO()
            np.savetxt(buf, exp.table(a, a + CSV_CHUNK_ROWS), delimiter=",", fmt=fmt)
            f.write(buf.getvalue())
            if progress is not None:
                progress(min(a + CSV_CHUNK_ROWS, exp.rows), exp.rows)
    meta_path, events_path = sidecars(path)
    meta = {"source": exp.source, "exported_by": "rig export", "csv": path.name, "rows": exp.rows,
            "columns": cols, "attrs": exp.attrs,
            "events": [{"time_s": t, "text": x} for t, x in exp.events]}
    meta_path.write_text(json.dumps(meta, indent=2, default=_json_default))
    with open(events_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "text"])
        w.writerows([(repr(float(t)), x) for t, x in exp.events])
    return [path, meta_path, events_path]


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return str(v)

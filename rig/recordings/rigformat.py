"""Rig's own recording formats: the loader for CSV, CSV.gz, HDF5 and MATLAB .mat (through the one reader,
rig/recordings/files.py), and the writers.

Formats (all carry the same four signals, sampled uniformly at fs_hz):
- CSV / CSV.gz (the shared recordings' format): header `time_s,valve_cmd_V,position_m,accel_mps2`
  (column order free, extra columns ignored), one row per sample.
- HDF5 (`save_recording_h5`, and what rig.runtime.recorder writes for a chirp run): 1-D float64 datasets /time_s,
  /valve_cmd_V, /position_m, /accel_mps2 at the root; root attributes fs_hz (rig.runtime.recorder: rate_hz) and source.
  2-D datasets (n, n_mounts) are accepted; `mount` picks the column (index, or name from the "labels" attr).
  A file with attribute complete = False (a run cut short) is read up to the rows every channel has, and said
  in a warning line (rig/recordings/files.py, open_hdf5).
  A recording may also sit in a group (e.g. /stand or /mounts/front_left): pass `group=`.
  An operated run of the stand layout (`rig run --layout prototype`, datasets mode, reference_m,
  tracking_error_m) is read over its longest stretch in `track` mode while ACTIVE: closed-loop data
  (Recording.closed_loop, with the reference the loop followed in Recording.reference_m).
  Any other `rig run` / `rig hil` recording (isolation_on and lifecycle_state beside the signals) is closed
  loop with no external excitation: its valve command was computed from the measured signals alone;
  `closed_loop` says so and reference_m is None (identification refuses it).
- MATLAB .mat: variables of the same names (row or column vectors); v5/v7 with scipy.io.loadmat, v7.3 (HDF5
  with a 512-byte MATLAB header) with h5py.

Every problem with a file raises RecordingError with one line naming the file and the problem.
"""

from __future__ import annotations

import gzip
import io
from pathlib import Path

import numpy as np

from rig.errors import RecordingError
from rig.recordings.files import csv_text, file_format, open_hdf5, read_bytes, read_mat, read_table, vector
from rig.recordings.recording import COLUMNS, Recording, validated
from rig.recordings.runfile import unit_factor


def load_recording(path, *, group: str | None = None, mount: int | str = 0) -> Recording:
    """Read a recording (format from the content's magic bytes, then the name). Raises RecordingError."""
    path = Path(path)
    source = str(path)
    raw = read_bytes(path)
    fmt = file_format(raw, path)
    if fmt in ("hdf5", "mat73"):                      # MATLAB v7.3 = HDF5 with a user block
        return _read_h5(path, source, group=group, mount=mount)
    if fmt == "mat":
        return _read_mat(raw, source)
    return _parse_csv(csv_text(raw, source, path), source)


def _parse_csv(text: str, source: str) -> Recording:
    if not text.strip():
        raise RecordingError(f"{source}: empty file")
    table = read_table(text, source, delimiter=",", header=True, quoted=False,
                       expected=f"columns {','.join(COLUMNS)} (another separator: a plant file's [signals] with "
                                f"csv = {{ delimiter = ... }}, docs/PLANT.md)")
    header = table.names
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise RecordingError(f"{source}: wrong columns: header is {','.join(header)[:120]!r}, "
                             f"expected {','.join(COLUMNS)} (missing {', '.join(missing)})")
    if len(set(header)) != len(header):
        raise RecordingError(f"{source}: wrong columns: repeated column name in header {','.join(header)[:120]!r}")
    data = table.columns([header.index(name) for name in COLUMNS], every_row=len(header))
    return validated({name: data[:, j] for j, name in enumerate(COLUMNS)}, source)


def _read_mat(raw: bytes, source: str) -> Recording:
    m = read_mat(raw, source)
    missing = [c for c in COLUMNS if c not in m]
    if missing:
        have = ", ".join(k for k in m if not k.startswith("__"))[:120]
        raise RecordingError(f"{source}: wrong variables: missing {', '.join(missing)} (has: {have or 'none'})")
    return validated({c: vector(m[c]) for c in COLUMNS}, source)


def _read_h5(path: Path, source: str, *, group: str | None = None, mount: int | str = 0) -> Recording:
    import h5py          # lazy: h5py is loaded only for HDF5 files
    with open_hdf5(path, source, "recording") as f:
        g = f[group] if group else f
        if not isinstance(g, h5py.Group):
            raise RecordingError(f"{source}: {group} is not a group")
        names = {c: c for c in COLUMNS}
        if "position_m" not in g and "stroke_m" in g:
            names["position_m"] = "stroke_m"      # a rig.runtime.loop recording: the transducer is stroke_m
        missing = [c for c in COLUMNS if names[c] not in g or not isinstance(g[names[c]], h5py.Dataset)]
        if missing:
            have = ", ".join(sorted(g.keys()))[:120]
            raise RecordingError(f"{source}: wrong datasets: missing {', '.join(missing)} (has: {have or 'none'})")
        cols = {}
        for c in COLUMNS:
            a = np.asarray(g[names[c]][()])
            if a.ndim == 2 and 1 in a.shape:
                a = a.ravel()                      # MATLAB v7.3 stores vectors as (n, 1) or (1, n)
            if a.ndim == 2 and c != "time_s":
                idx = _mount_index(g[names[c]], mount, source)
                if not 0 <= idx < a.shape[1]:
                    raise RecordingError(f"{source}: mount {mount} not in {c} ({a.shape[1]} columns)")
                a = a[:, idx]
            cols[c] = a * unit_factor(g[names[c]].attrs.get("unit"), names[c], source) if a.dtype.kind in "fiu" else a
        if not bool(f.attrs.get("complete", True)):
            # rig.runtime.recorder marks a run cut short (crash, kill): keep the rows every channel has
            n = min(a.shape[0] for a in cols.values())
            cols = {c: a[:n] for c, a in cols.items()}
        meta = {}
        for k, v in f.attrs.items():
            if isinstance(v, bytes):
                v = v.decode(errors="replace")
            if isinstance(v, (str, int, float, bool, np.integer, np.floating, np.bool_)):
                meta[str(k)] = v.item() if hasattr(v, "item") else v
            elif isinstance(v, np.ndarray) and v.ndim == 1 and v.size <= 64:
                meta[str(k)] = [x.decode(errors="replace") if isinstance(x, bytes) else
                                (x.item() if hasattr(x, "item") else x) for x in v]
        track = _track_rows(g, mount, source) if "mode" in g and "reference_m" in g else None
        if track is not None:
            sel, ref = track
            cols = {c: a[sel] for c, a in cols.items()}
        closed = _feedback_rows(g, f.attrs.get("command", "the loop"))
    rec = validated(cols, source)
    rec.meta = meta
    rec.closed_loop = closed
    if track is not None:
        if rec.gaps:                 # the reference mended as the signals were (recorded samples kept as they are)
            ref = np.interp(rec.t_s, np.asarray(cols["time_s"], dtype=float), np.asarray(ref, dtype=float))
        rec.closed_loop, rec.reference_m = "an operated run in track mode", ref
    return rec


def _feedback_rows(g, command) -> str:
    """Why the valve command of a loop recording is closed loop: rows ACTIVE under a feedback controller (the
    isolation law or the stroke centring: the valve follows the measured accel and stroke). '' otherwise."""
    if "lifecycle_state" not in g or "isolation_on" not in g:
        return ""                                   # a chirp (playback) or a foreign file: open loop
    active = np.asarray(g["lifecycle_state"][()]).ravel() == 2      # rig.runtime.lifecycle.State.ACTIVE
    if not active.any():
        return ""
    return (f"recorded by {command} with the feedback controller driving the valves in {int(active.sum())} of "
            f"{active.size} rows")


TRACK_MODE = 2            # controllers/modes.py: off, hold, track, isolate
def _track_rows(g, mount, source):
    """An operated run: (slice of the longest stretch in track mode while ACTIVE, its reference)."""
    def col(name):
        a = np.asarray(g[name][()], dtype=float)
        return a[:, _mount_index(g[name], mount, source)] if a.ndim == 2 and a.shape[1] > 1 else a.ravel()
    mode = col("mode")
    ok = mode == TRACK_MODE
    if "lifecycle_state" in g:
        ok &= np.asarray(g["lifecycle_state"][()]).ravel()[:len(ok)] == 2
    if not ok.any():
        raise RecordingError(f"{source}: an operated run without a stretch in track mode (identification needs "
                             f"the valve driven: record a track run, e.g. a chirp reference)")
    edges = np.flatnonzero(np.diff(np.concatenate(([0], ok.astype(np.int8), [0]))))
    starts, ends = edges[::2], edges[1::2]
    k = int(np.argmax(ends - starts))
    sel = slice(int(starts[k]), int(ends[k]))
    return sel, col("reference_m")[sel]


def _mount_index(ds, mount, source) -> int:
    if isinstance(mount, int):
        return mount
    names = ds.attrs.get("labels", ds.attrs.get("mounts"))     # rig.runtime.recorder writes "labels"
    if names is None:
        raise RecordingError(f"{source}: mount {mount!r} asked but the datasets have no 'labels' attribute")
    names = [n.decode() if isinstance(n, bytes) else str(n) for n in np.atleast_1d(names)]
    if mount not in names:
        raise RecordingError(f"{source}: mount {mount!r} not recorded (have {', '.join(names)})")
    return names.index(mount)


# ---- writers ----------------------------------------------------------------------------------------

def save_recording_h5(rec: Recording, path, *, attrs: dict | None = None) -> Path:
    """Write the HDF5 layout described above (float64, gzip-compressed datasets)."""
    import h5py          # lazy: h5py is loaded only for HDF5 files
    path = Path(path)
    with h5py.File(path, "w") as f:
        for name, a in zip(COLUMNS, (rec.t_s, rec.valve_cmd_V, rec.position_m, rec.accel_mps2)):
            f.create_dataset(name, data=np.asarray(a, dtype=float), compression="gzip", compression_opts=4)
        f.attrs["fs_hz"] = float(rec.fs_hz)
        f.attrs["source"] = str(rec.source)
        f.attrs["format"] = "rig recording v1"
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
    return path


def save_recording_csv(rec: Recording, path) -> Path:
    """Write the shared CSV format (gzip-compressed when the name ends in .gz)."""
    return save_columns_csv({"time_s": rec.t_s, "valve_cmd_V": rec.valve_cmd_V, "position_m": rec.position_m,
                             "accel_mps2": rec.accel_mps2}, path)


def save_columns_csv(cols: dict, path) -> Path:
    """The shared CSV format from the four columns as they are (e.g. a chirp's rows as recorded, any rows the
    recorder dropped left out, not invented)."""
    path = Path(path)
    buf = io.StringIO()
    buf.write(",".join(COLUMNS) + "\n")
    data = np.column_stack([np.asarray(cols[c], dtype=float) for c in COLUMNS])
    # time with enough digits for uniform steps at any fs up to 1 MHz; signals with 9 significant digits
    np.savetxt(buf, data, delimiter=",", fmt=["%.9f", "%.9g", "%.9g", "%.9g"])
    text = buf.getvalue().encode()
    if path.suffix.lower() == ".gz":
        with gzip.open(path, "wb", compresslevel=6) as f:
            f.write(text)
    else:
        path.write_bytes(text)
    return path


def save_recording_mat(rec: Recording, path) -> Path:
    """Write a MATLAB v5 .mat with the same variable names."""
    import scipy.io      # lazy: scipy.io is loaded only for .mat files
    path = Path(path)
    scipy.io.savemat(path, {"time_s": rec.t_s, "valve_cmd_V": rec.valve_cmd_V, "position_m": rec.position_m,
                            "accel_mps2": rec.accel_mps2, "fs_hz": rec.fs_hz}, oned_as="column")
    return path

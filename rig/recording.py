"""Chirp/run recordings: one dataclass, a loader for CSV, CSV.gz, HDF5 and MATLAB .mat, and writers.

Formats (all carry the same four signals, sampled uniformly at fs_hz):
- CSV / CSV.gz (the shared recordings' format): header `time_s,valve_cmd_V,position_m,accel_mps2`
  (column order free, extra columns ignored), one row per sample.
- HDF5 (`save_recording_h5`, and what rig.runtime.recorder writes for a chirp run): 1-D float64 datasets /time_s,
  /valve_cmd_V, /position_m, /accel_mps2 at the root; root attributes fs_hz (rig.runtime.recorder: rate_hz) and source.
  2-D datasets (n, n_mounts) are accepted; `mount` picks the column (index, or name from the "labels" attr).
  A file with attribute complete = False (a run cut short) is read up to the rows every channel has.
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
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.errors import RecordingError

COLUMNS = ("time_s", "valve_cmd_V", "position_m", "accel_mps2")
MIN_SAMPLES = 100            # fewer cannot hold even one period of the chirp's lowest useful frequency
UNIFORM_TOL = 0.05           # a step may differ from the median step by 5 % (clock jitter, 6-digit rounding)
# Rows missing (a real-clock run whose writer fell behind drops rows and leaves whole steps out of time_s): a gap
# of at most this many samples is bridged by linear interpolation (at the rig's rates a few samples are far
# shorter than any dynamics the fits resolve); a longer one splits the recording, and its longest stretch is used
BRIDGE_MAX_SAMPLES = 3

_GZIP_MAGIC = b"\x1f\x8b"
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_MAT_MAGIC = b"MATLAB"


@dataclass
class Recording:
    t_s: np.ndarray
    valve_cmd_V: np.ndarray
    position_m: np.ndarray
    accel_mps2: np.ndarray
    fs_hz: float
    source: str = "<memory>"
    meta: dict = field(default_factory=dict)     # the file's attributes (HDF5: e.g. command = "rig run")
    # why the valve command depends on the measurement (feedback), "" if open loop. In an operated track run
    # the position's noise and disturbances reach the command too; reference_m is the external excitation the
    # loop followed (None: feedback alone, nothing to identify from)
    closed_loop: str = ""
    reference_m: np.ndarray | None = None
    # another rig's recording (a plant file's signal map): the command's unit ("V", "N", "A"); valve_cmd_V
    # then holds the command in that unit. accel_present False: the file has no accelerometer (accel zeros)
    command_unit: str = "V"
    accel_present: bool = True
    # what the reader did about rows missing from the file (one line: gaps bridged, or the stretch it kept);
    # "" when the file's time base was whole
    gaps: str = ""

    @property
    def command(self) -> np.ndarray:
        """The plant's input, in command_unit (the valve command in V on this rig)."""
        return self.valve_cmd_V

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def duration_s(self) -> float:
        return self.n / self.fs_hz

    @classmethod
    def from_arrays(cls, t_s, valve_cmd_V, position_m, accel_mps2=None, *, source: str = "<memory>") -> "Recording":
        """Build and validate from arrays (accel may be None: zeros)."""
        t = np.asarray(t_s, dtype=float)
        acc = np.zeros_like(t) if accel_mps2 is None else accel_mps2
        cols = {"time_s": t, "valve_cmd_V": valve_cmd_V, "position_m": position_m, "accel_mps2": acc}
        return _validated(cols, source)

    @classmethod
    def from_signals(cls, valve_cmd_V, position_m, accel_mps2=None, *, fs_hz: float,
                     source: str = "<memory>") -> "Recording":
        n = np.asarray(valve_cmd_V).shape[0]
        return cls.from_arrays(np.arange(n) / fs_hz, valve_cmd_V, position_m, accel_mps2, source=source)


# ---- validation -------------------------------------------------------------------------------------

def mend_gaps(cols: dict[str, np.ndarray], source: str, time_label: str = "time_s") -> tuple[dict, str]:
    """Rows missing from a recording (whole steps left out of time_s): bridge gaps of at most
    BRIDGE_MAX_SAMPLES samples by linear interpolation, and keep the longest stretch between longer ones.
    Every column of `cols` (same length as time_s) is mended alike; the samples recorded stay as they are.
    Returns (cols, one line saying what was done, "" if nothing was). A time base that is irregular in any
    other way is left for _validated to name."""
    try:
        t = np.asarray(cols["time_s"], dtype=float)
        arrays = {k: np.asarray(v, dtype=float) for k, v in cols.items()}
    except (TypeError, ValueError):
        return cols, ""
    n = t.shape[0]
    if t.ndim != 1 or n < 3 or any(a.shape != (n,) for a in arrays.values()):
        return cols, ""
    dt = np.diff(t)
    if not np.isfinite(dt).all() or not (dt > 0).all():
        return cols, ""
    step = float(np.median(dt))
    ratio = dt / step
    whole = np.rint(ratio)
    gap = (whole >= 2) & (np.abs(ratio - whole) <= UNIFORM_TOL * whole)
    if not gap.any() or (np.abs(dt - step) > UNIFORM_TOL * step)[~gap].any():
        return cols, ""
    missing = whole.astype(np.int64) - 1
    missing[~gap] = 0
    cuts = np.flatnonzero(missing > BRIDGE_MAX_SAMPLES) + 1          # a long gap starts a new stretch here
    bounds = np.concatenate(([0], cuts, [n]))
    spans = [t[b - 1] - t[a] for a, b in zip(bounds[:-1], bounds[1:])]
    k = int(np.argmax(spans))
    a, b = int(bounds[k]), int(bounds[k + 1])
    idx = np.concatenate(([0], np.cumsum(missing[a:b - 1] + 1)))      # each recorded sample's slot
    m = int(idx[-1]) + 1
    if m < MIN_SAMPLES:
        raise RecordingError(
            f"{source}: rows missing: {int(gap.sum())} gaps in {time_label}, and the longest stretch without a gap "
            f"over {BRIDGE_MAX_SAMPLES} samples holds {m} samples, need at least {MIN_SAMPLES}: record again "
            f"(rows are dropped when the recorder falls behind the real clock: free the CPU or lower --rate)")
    holes = np.setdiff1d(np.arange(m), idx)
    out = {}
    for key, v in arrays.items():
        seg = v[a:b]
        full = np.empty(m)
        full[idx] = seg
        full[holes] = np.interp(holes, idx, seg)
        out[key] = full
    bridged = missing[a:b - 1]
    nb, nbs = int((bridged > 0).sum()), int(bridged.sum())
    first = f"first at t = {t[a + int(np.argmax(bridged > 0))]:.6g} s" if nb else ""
    if len(bounds) == 2:
        note = (f"{nb} gap{'s' * (nb != 1)} of at most {int(bridged.max())} sample{'s' * bool(bridged.max() != 1)} "
                f"bridged by linear interpolation ({nbs} of {m} samples, {first})")
    else:
        left = int(missing.sum() - nbs)
        note = (f"used the longest stretch without a gap over {BRIDGE_MAX_SAMPLES} samples: t = {t[a]:.6g} to "
                f"{t[b - 1]:.6g} s ({m} of {n + int(missing.sum())} samples; {len(bounds) - 2} longer "
                f"gap{'s' * (len(bounds) != 3)} ({left} samples) left out"
                + (f"; {nb} short gap{'s' * (nb != 1)} of {nbs} samples bridged, {first})" if nb else ")"))
    return out, f"{source}: rows missing in {time_label}: {note}"


def _validated(cols: dict[str, np.ndarray], source: str, labels: dict[str, str] | None = None) -> Recording:
    """The one set of rules every recording passes. labels: how the messages name each column (a plant file's
    signal map names the file's own variables, rig/signalmap.py). Rows missing from the time base are mended
    first (mend_gaps: bridged or the longest stretch kept; the Recording's `gaps` says which)."""
    lab = {c: c for c in COLUMNS} | (labels or {})
    cols, gaps = mend_gaps({c: cols[c] for c in COLUMNS}, source, lab["time_s"])
    arrays = {}
    for name in COLUMNS:
        a = np.asarray(cols[name])
        if a.dtype.kind not in "iuf" and a.dtype != np.bool_:
            raise RecordingError(f"{source}: column {lab[name]} is not numeric (dtype {a.dtype})")
        a = np.ascontiguousarray(a, dtype=float)
        if a.ndim != 1:
            raise RecordingError(f"{source}: column {lab[name]} has shape {a.shape}, expected one value per sample")
        arrays[name] = a
    n = arrays["time_s"].shape[0]
    for name, a in arrays.items():
        if a.shape[0] != n:
            raise RecordingError(f"{source}: column {lab[name]} has {a.shape[0]} samples, {lab['time_s']} has {n}")
    if n == 0:
        raise RecordingError(f"{source}: no samples")
    for name, a in arrays.items():
        bad = ~np.isfinite(a)
        if bad.any():
            k = int(np.argmax(bad))
            raise RecordingError(f"{source}: {lab[name]} is {a[k]} (not a finite number) at sample {k}")
    if n < MIN_SAMPLES:
        raise RecordingError(f"{source}: too short: {n} samples, need at least {MIN_SAMPLES}")
    t = arrays["time_s"]
    dt = np.diff(t)
    if not (dt > 0).all():
        k = int(np.argmax(dt <= 0)) + 1
        raise RecordingError(f"{source}: {lab['time_s']} not increasing at sample {k} ({t[k - 1]!r} then {t[k]!r})")
    step = float(np.median(dt))
    off = np.abs(dt - step) > UNIFORM_TOL * step
    if off.any():
        k = int(np.argmax(off)) + 1
        if dt[k - 1] > step:
            # a gap: one line naming the first one (segments are not stitched: the plant's state across the gap
            # is unknown, so each side would need its own start transient)
            missing = int(round(dt[k - 1] / step)) - 1
            more = int(off.sum()) - 1
            raise RecordingError(
                f"{source}: {lab['time_s']} not uniform at sample {k}: a gap of {dt[k - 1]:.6g} s after "
                f"t = {t[k - 1]:.6g} s (about {missing} samples missing, expected steps of {step:.6g} s"
                f"{f'; {more} more irregular steps after it' if more else ''}): split the recording at the gap")
        raise RecordingError(f"{source}: {lab['time_s']} not uniform at sample {k}: step {dt[k - 1]:.6g} s, "
                             f"expected {step:.6g} s")
    # the sample rate from the whole span (robust to per-step rounding of printed times)
    fs = (n - 1) / (t[-1] - t[0])
    if not np.isfinite(fs) or fs <= 0:
        raise RecordingError(f"{source}: cannot determine a sample rate from {lab['time_s']}")
    return Recording(t_s=t, valve_cmd_V=arrays["valve_cmd_V"], position_m=arrays["position_m"],
                     accel_mps2=arrays["accel_mps2"], fs_hz=float(fs), source=source, gaps=gaps)


# Magnitudes no recording of this kind can hold (they break the arithmetic, not just the physics): a value
# beyond them is a wrong unit or a corrupt file.
PLAUSIBLE_ABS = {"valve_cmd_V": 1e4, "position_m": 1e3, "accel_mps2": 1e6}
# another rig's command (a plant file's signal map), by its unit: a press's force reaches MN
PLAUSIBLE_COMMAND = {"V": 1e4, "N": 1e8, "A": 1e4, "N m": 1e7}


def check_plausible(rec: Recording) -> None:
    """One clear line for a value no sensor or command of a rig can have (e.g. 1e300 from a corrupt export)."""
    for name, lim in PLAUSIBLE_ABS.items():
        a = getattr(rec, name)
        if name == "valve_cmd_V":
            lim = PLAUSIBLE_COMMAND.get(rec.command_unit, lim)
        bad = np.abs(a) > lim
        if bad.any():
            k = int(np.argmax(bad))
            raise RecordingError(f"{rec.source}: {name} is {a[k]:.6g} at sample {k} (t = {rec.t_s[k]:.6g} s): not a "
                                 f"plausible value (expected |{name}| < {lim:g}); check the column's units")


# ---- readers ----------------------------------------------------------------------------------------

def csv_text(raw: bytes, source: str) -> str:
    """A CSV or text file's content as text; binary data: RecordingError."""
    if b"\x00" in raw:
        raise RecordingError(f"{source}: binary data, not a CSV recording")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise RecordingError(f"{source}: binary data, not a CSV recording (byte {e.start} is not text)") from None


def _parse_csv(raw: bytes, source: str) -> Recording:
    if not raw.strip():
        raise RecordingError(f"{source}: empty file")
    lines = csv_text(raw, source).splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise RecordingError(f"{source}: empty file")
    header = [h.strip().strip('"').strip() for h in lines[first].split(",")]   # spreadsheet exports quote names
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise RecordingError(f"{source}: wrong columns: header is {','.join(header)[:120]!r}, "
                             f"expected {','.join(COLUMNS)} (missing {', '.join(missing)})")
    if len(set(header)) != len(header):
        raise RecordingError(f"{source}: wrong columns: repeated column name in header {lines[first][:120]!r}")
    body = [ln for ln in lines[first + 1:] if ln.strip()]
    if not body:
        raise RecordingError(f"{source}: no data rows after the header")
    ncol = len(header)
    # Fast path: numpy's C parser; on failure find the offending row ourselves for a clear message.
    try:
        data = np.loadtxt(io.StringIO("\n".join(body)), delimiter=",", ndmin=2, dtype=float, comments=None)
        if data.shape[1] != ncol:
            raise ValueError("column count")
    except (ValueError, OverflowError):
        raise _first_bad_row(lines, first, ncol, source) from None
    cols = {name: data[:, header.index(name)] for name in COLUMNS}
    return _validated(cols, source)


def _first_bad_row(lines: list[str], first: int, ncol: int, source: str) -> RecordingError:
    for i in range(first + 1, len(lines)):
        ln = lines[i]
        if not ln.strip():
            continue
        cells = ln.split(",")
        if len(cells) != ncol:
            return RecordingError(f"{source}: line {i + 1} has {len(cells)} fields, expected {ncol}: {ln[:80]!r}")
        for c in cells:
            try:
                float(c)
            except ValueError:
                return RecordingError(f"{source}: line {i + 1} is not numeric: {ln[:80]!r}")
    return RecordingError(f"{source}: could not parse the numeric rows")


def _read_gzip(raw: bytes, source: str) -> bytes:
    try:
        return gzip.decompress(raw)
    except EOFError:
        raise RecordingError(f"{source}: truncated gzip file (compressed stream ends early)") from None
    except (gzip.BadGzipFile, zlib.error, OSError) as e:
        raise RecordingError(f"{source}: corrupt gzip file ({e})") from None


def _read_h5(path: Path, source: str, *, group: str | None = None, mount: int | str = 0) -> Recording:
    try:
        import h5py
    except ImportError:  # pragma: no cover - h5py is a dependency
        raise RecordingError(f"{source}: h5py is not installed, cannot read HDF5") from None
    try:
        with h5py.File(path, "r") as f:
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
                cols[c] = a
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
    except RecordingError:
        raise
    except Exception as e:   # h5py raises OSError/KeyError/ValueError/TypeError for damaged files
        raise RecordingError(f"{source}: not a readable HDF5 recording ({type(e).__name__}: {e})"[:300]) from None
    rec = _validated(cols, source)
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
CLOSED_LOOP_NOTE = (
    "closed-loop data (an operated run in track mode): the valve command was computed from the measured "
    "position, so the transducer's noise and any disturbance reach the command as well as the position. The "
    "valve -> position response estimated from command and position is the actuator's only where the "
    "reference's excitation dominates them (the reference's band, where the coherence is high); where it does "
    "not, the estimate drifts towards minus the inverse of the controller. Excite the band of interest with "
    "the reference (a chirp), and read the fit over that band only. The command recorded in a period acts "
    "from the next one (the loop's computation), which the fit sees as one period of transport delay.")


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


def _read_mat(raw: bytes, source: str) -> Recording:
    try:
        import scipy.io
        m = scipy.io.loadmat(io.BytesIO(raw), squeeze_me=False)
    except Exception as e:   # scipy raises MatReadError/ValueError/TypeError/... on damaged files
        raise RecordingError(f"{source}: not a readable MATLAB file ({type(e).__name__}: {e})"[:300]) from None
    missing = [c for c in COLUMNS if c not in m]
    if missing:
        have = ", ".join(k for k in m if not k.startswith("__"))[:120]
        raise RecordingError(f"{source}: wrong variables: missing {', '.join(missing)} (has: {have or 'none'})")
    cols = {}
    for c in COLUMNS:
        a = np.asarray(m[c])
        if a.ndim == 2 and 1 in a.shape:
            a = a.ravel()
        cols[c] = a
    return _validated(cols, source)


def read_bytes(path: Path) -> bytes:
    """A recording file's content; missing, unreadable or empty: RecordingError."""
    source = str(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise RecordingError(f"{source}: is a directory, expected a recording file") from None
    except OSError as e:
        raise RecordingError(f"{source}: cannot read ({e.strerror or e})") from None
    if not raw:
        raise RecordingError(f"{source}: empty file")
    return raw


def load_recording(path, *, group: str | None = None, mount: int | str = 0) -> Recording:
    """Read a recording (format from the content's magic bytes, then the name). Raises RecordingError."""
    path = Path(path)
    source = str(path)
    raw = read_bytes(path)
    if raw.startswith(_HDF5_MAGIC) or path.suffix.lower() in (".h5", ".hdf5"):
        if not raw.startswith(_HDF5_MAGIC):
            raise RecordingError(f"{source}: not an HDF5 file (no HDF5 signature)")
        return _read_h5(path, source, group=group, mount=mount)
    if raw.startswith(_MAT_MAGIC) and raw[512:520] == _HDF5_MAGIC:
        return _read_h5(path, source, group=group, mount=mount)      # MATLAB v7.3 = HDF5 with a user block
    if raw.startswith(_MAT_MAGIC) or path.suffix.lower() == ".mat":
        return _read_mat(raw, source)
    if raw.startswith(_GZIP_MAGIC) or path.suffix.lower() == ".gz":
        raw = _read_gzip(raw, source)
        if raw.startswith(_GZIP_MAGIC):
            raise RecordingError(f"{source}: gzip inside gzip, expected one compressed CSV")
    return _parse_csv(raw, source)


# ---- writers ----------------------------------------------------------------------------------------

def save_recording_h5(rec: Recording, path, *, attrs: dict | None = None) -> Path:
    """Write the HDF5 layout described above (float64, gzip-compressed datasets)."""
    import h5py
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
    import scipy.io
    path = Path(path)
    scipy.io.savemat(path, {"time_s": rec.t_s, "valve_cmd_V": rec.valve_cmd_V, "position_m": rec.position_m,
                            "accel_mps2": rec.accel_mps2, "fs_hz": rec.fs_hz}, oned_as="column")
    return path

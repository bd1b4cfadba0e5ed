"""A recording and the rules every recording passes, whatever file it came from.

`Recording`: the four signals sampled uniformly at fs_hz (time, the command, the position, the acceleration),
where they came from, and what the reader found (closed loop, the command's unit, rows mended). `validated` is the
one set of rules (the same length, finite, at least MIN_SAMPLES, time increasing and uniform within 5 %, rows
missing mended by `mend_gaps`); `check_plausible` refuses values no rig can have.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rig.errors import RecordingError

COLUMNS = ("time_s", "valve_cmd_V", "position_m", "accel_mps2")
MIN_SAMPLES = 100            # fewer cannot hold even one period of the chirp's lowest useful frequency
UNIFORM_TOL = 0.05           # a step may differ from the median step by 5 % (clock jitter, 6-digit rounding)
# Rows missing (a real-clock run whose writer fell behind drops rows and leaves whole steps out of time_s): a gap
# of at most this many samples is bridged by linear interpolation (at the rig's rates a few samples are far
# shorter than any dynamics the fits resolve); a longer one splits the recording, and its longest stretch is used
BRIDGE_MAX_SAMPLES = 3


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
    # the measured output: a position in m (rad on a rotary axis), or what a plant file's [signals] output maps
    # (a speed, a voltage, a pressure, a sensor's own units "1"), held in position_m in its SI unit
    output_unit: str = "m"
    output_kind: str = "length"
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
        return validated(cols, source)

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
    other way is left for validated to name."""
    if any(np.asarray(v).dtype.kind not in "iufb" for v in cols.values()):
        return cols, ""                        # complex, text: validated names the column
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


def validated(cols: dict[str, np.ndarray], source: str, labels: dict[str, str] | None = None) -> Recording:
    """The one set of rules every recording passes. labels: how the messages name each column (a plant file's
    signal map names the file's own variables, rig/recordings/signalmap.py). Rows missing from the time base are mended
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
        raise RecordingError(f"{source}: {lab['time_s']} not increasing at sample {k} ({t[k - 1]:.9g} s then {t[k]:.9g} s)")
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
PLAUSIBLE_OUTPUT = 1e10


def check_plausible(rec: Recording) -> None:
    """One clear line for a value no sensor or command of a rig can have (e.g. 1e300 from a corrupt export)."""
    for name, lim in PLAUSIBLE_ABS.items():
        a = getattr(rec, name)
        if name == "valve_cmd_V":
            lim = PLAUSIBLE_COMMAND.get(rec.command_unit, lim)
        elif name == "position_m" and rec.output_unit not in ("m", "rad"):
            lim = PLAUSIBLE_OUTPUT          # another quantity (a pressure in Pa reaches 1e8)
        bad = np.abs(a) > lim
        if bad.any():
            k = int(np.argmax(bad))
            raise RecordingError(f"{rec.source}: {name} is {a[k]:.6g} at sample {k} (t = {rec.t_s[k]:.6g} s): not a "
                                 f"plausible value (expected |{name}| < {lim:g}); check the column's units")


CLOSED_LOOP_NOTE = (
    "closed-loop data (an operated run in track mode): the valve command was computed from the measured "
    "position, so the transducer's noise and any disturbance reach the command as well as the position. The "
    "valve -> position response estimated from command and position is the actuator's only where the "
    "reference's excitation dominates them (the reference's band, where the coherence is high); where it does "
    "not, the estimate drifts towards minus the inverse of the controller. Excite the band of interest with "
    "the reference (a chirp), and read the fit over that band only. The command recorded in a period acts "
    "from the next one (the loop's computation), which the fit sees as one period of transport delay.")

"""The vibration-criterion (VC) report of a run recording (`rig run --record`, `rig hil`): one-third-octave rms
velocity of the machine at its mounts per isolation mode, against the VC-A..G and ISO lines, and the class met.

What the rig measures is used: the mount accelerometers (the machine's absolute motion where it stands on the
actuators: where vibration criteria are taken for a machine on isolators) and, when fitted, the floor
accelerometers ([sensors] floor_accel). The table and the tool point are not measured on the rig (the
simulated plant knows them: `rig demo` reports those).

The recording is split into its modes by the recorded flags: off (INACTIVE, or ACTIVE with isolation off),
feedback, feedback_feedforward (the feedforward_on column of a loop with floor accelerometers); FAULT rows are
left out. Each mode's longest stretch is used, less settle_s at its start (the switching fade and the
filters' transient). A mode the run never switched to is said to be absent (`absent_modes`), not too short:
a run that never switched isolation off has no baseline (only the INACTIVE settle before activation), and
its classes are of isolation on alone. The modes of one run see different stretches of the floor: with floor accelerometers the
report also gives the transmissibility mount / floor per band, which takes the floor's own level out.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from controllers.vibration_criteria import band_velocity_rms, plot_vc, vc_class
from rig.errors import RecordingError
from rig.recordings.files import check_file, open_hdf5
from rig.recordings.runfile import unit_factor
from rig.runtime.lifecycle import State
from rig.runtime.recorder import read_recording

MODES = ("off", "feedback", "feedback_feedforward")
MIN_SECONDS = 2.0            # below this the 1 Hz band holds less than two cycles: no report for the mode


def _mode_codes(r: dict) -> np.ndarray:
    """Per row: 0 off, 1 feedback, 2 feedback_feedforward, -1 FAULT or unconfigured."""
    life = np.asarray(r["lifecycle_state"])
    iso = np.asarray(r["isolation_on"]) > 0.5
    ff = np.asarray(r["feedforward_on"]) > 0.5 if "feedforward_on" in r else np.zeros_like(iso)
    active = life == float(State.ACTIVE)
    code = np.where(active & iso, np.where(ff, 2, 1), 0)
    ok = (life == float(State.INACTIVE)) | active
    return np.where(ok, code, -1)


def _longest(mask: np.ndarray) -> tuple[int, int]:
    """[start, stop) of the longest run of True (0, 0 if none)."""
    if not mask.any():
        return 0, 0
    d = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    k = int(np.argmax(stops - starts))
    return int(starts[k]), int(stops[k])


def _numbers(path, r: dict, key: str) -> np.ndarray | None:
    """Dataset `key` as finite floats (None when absent); RecordingError naming the dataset and row else."""
    if key not in r:
        return None
    try:
        v = np.asarray(r[key], dtype=float)
    except (TypeError, ValueError):
        raise RecordingError(f"{path}: dataset {key}: expected numbers, got {np.asarray(r[key]).dtype}") from None
    bad = ~np.isfinite(v)
    if bad.any():
        row = int(np.argmax(bad.reshape(len(v), -1).any(axis=1)))
        raise RecordingError(f"{path}: dataset {key}: not a finite number at row {row}: cut the recording before it")
    return v * unit_factor(r["units"].get(key), key, str(path))       # an accelerometer written in g, say


def vc_of_recording(path, *, settle_s: float = 1.0) -> dict:
    """The report of one recording as JSON-ready values (RecordingError for a file that is not a loop
    recording, one line naming the file and what is missing)."""
    check_file(path, "no such recording (expected the HDF5 file of rig run --record or rig hil)")
    try:
        r = read_recording(path)
    except RecordingError as e:                     # h5py's reasons run over several lines: the first says it
        raise RecordingError(str(e).splitlines()[0]) from None
    for key in ("time_s", "accel_mps2", "lifecycle_state", "isolation_on"):
        if key not in r:
            raise RecordingError(f"{path}: no {key} dataset (expected a recording of rig run or rig hil)")
    try:
        fs = float(r["attrs"].get("rate_hz", 0.0))
    except (TypeError, ValueError):
        fs = math.nan
    if not (math.isfinite(fs) and fs > 0):
        raise RecordingError(f"{path}: attribute rate_hz missing or not a positive number (the loop rate, Hz)")
    acc, floor = _numbers(path, r, "accel_mps2"), _numbers(path, r, "floor_accel_mps2")
    for key in ("lifecycle_state", "isolation_on", "feedforward_on"):      # the mode flags: numbers too
        _numbers(path, r, key)
    acc = acc[:, None] if acc.ndim == 1 else acc
    code = _mode_codes(r)
    skip = int(round(settle_s * fs))
    names = _labels(path, acc.shape[1]) or [f"mount{i}" for i in range(acc.shape[1])]
    out = {"recording": str(path), "rate_hz": fs, "measured": "mount accelerometers (machine at its mounts)"
           + (" and floor accelerometers" if floor is not None else ""), "segments": {}, "skipped_modes": {},
           "absent_modes": {}, "mounts": {}, "vc_class": {}}
    if floor is not None:
        out.update(floor={}, vc_class_floor={}, transmissibility_db={})
    t = np.asarray(r["time_s"], dtype=float)
    if len(t) < 2 or not t[-1] > t[0]:           # a loop stepped by hand (no scheduler): its row count
        t = np.arange(len(t)) / fs
    active = np.asarray(r["lifecycle_state"]) == float(State.ACTIVE)
    for k, mode in enumerate(MODES):
        a, b = _longest(code == k)
        a += skip
        if (b - a) / fs < MIN_SECONDS:
            why = _absent(mode, code == k, active, fs)
            if why:
                out["absent_modes"][mode] = why
            elif b > 0:
                out["skipped_modes"][mode] = f"{max(b - a, 0) / fs:.1f} s after settling, at least {MIN_SECONDS:g} s"
            continue
        out["segments"][mode] = {"t0_s": float(t[a]), "t1_s": float(t[b - 1]), "seconds": (b - a) / fs,
                                 "resolution_hz": fs / (b - a)}
        bands = [band_velocity_rms(acc[a:b, i], fs, kind="acceleration") for i in range(acc.shape[1])]
        fc = bands[0][0]
        v = np.array([x[1] for x in bands]) * 1e6                      # (mounts, bands) um/s
        out["band_hz"] = [float(x) for x in fc]
        worst = v.max(axis=0)
        out["mounts"][mode] = {"velocity_um_s_worst_mount": [float(x) for x in worst],
                               "vc_class_per_mount": {n: vc_class(v[i], fc) for i, n in enumerate(names)}}
        out["vc_class"][mode] = vc_class(worst, fc)
        if floor is not None:
            g = np.array([band_velocity_rms(floor[a:b, i], fs, kind="acceleration")[1]
                          for i in range(floor.shape[1])]) * 1e6
            gw = g.max(axis=0)
            out["floor"][mode] = {"velocity_um_s_worst_mount": [float(x) for x in gw]}
            out["vc_class_floor"][mode] = vc_class(gw, fc)
            out["transmissibility_db"][mode] = [float(20 * math.log10(x / y)) if y > 0 and x > 0 else None
                                                for x, y in zip(v.mean(axis=0), g.mean(axis=0))]
    if not out["segments"]:
        raise RecordingError(f"{path}: no mode lasted {MIN_SECONDS + settle_s:g} s (a VC report needs seconds of "
                             f"one mode for its 1 Hz band)")
    return out


def _absent(mode: str, rows: np.ndarray, active: np.ndarray, fs: float) -> str:
    """Why `mode` is absent from the run, "" when it was there, however briefly (called when too short).
    Isolation off: never switched off while ACTIVE; the INACTIVE rows (valves at null, counted as off) are
    then only the settle before activation."""
    if mode == "off":
        if (rows & active).any():
            return ""
        settle = f" (only the {rows.sum() / fs:.2g} s INACTIVE before activation)" if rows.any() else ""
        return (f"no isolation-off stretch: the run never switched isolation off{settle}, so there is no baseline "
                f"and the classes here are of isolation on alone, not a comparison (record a stretch with "
                f"isolation off: rig run --isolation off, SIGUSR1 or --control)")
    if rows.any():
        return ""
    return f"the run never used {mode.replace('_', ' + ')}"


def _labels(path, n: int) -> list[str] | None:
    """The accel_mps2 dataset's column labels (mount names), if recorded (read through the one reader of files,
    which says when the recording was not closed by its writer)."""
    try:
        with open_hdf5(Path(path), str(path), "recording") as f:
            lab = f["accel_mps2"].attrs.get("labels")
            if lab is not None and len(lab) == n:
                return [x.decode() if isinstance(x, bytes) else str(x) for x in lab]
    except RecordingError:
        return None
    return None


def summary(rep: dict) -> str:
    """One line: the class met per mode (machine at its mounts; the floor's with floor accelerometers)."""
    def classes(by_mode):       # "off = workshop (ISO), feedback = VC-A": a mode and its class read as a pair
        return ", ".join(f"{m.replace('_', ' + ')} = {c}" for m, c in by_mode)
    text = "VC class, machine at its mounts (worst mount, 1-100 Hz): " + classes(
        (m, rep["vc_class"][m]) for m in MODES if m in rep["vc_class"])
    if "off" in rep.get("absent_modes", {}):
        text += " (no isolation-off stretch to compare with)"
    if rep.get("vc_class_floor"):
        text += "; floor: " + classes(rep["vc_class_floor"].items())
    return text


def plot(path: Path, rep: dict) -> None:
    """The report's curves (worst mount per mode, and the floor) against the criteria, one figure."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    curves = {f"machine, {m.replace('_', ' + ')}": rep["mounts"][m]["velocity_um_s_worst_mount"]
              for m in MODES if m in rep["mounts"]}
    classes = {f"machine, {m.replace('_', ' + ')}": rep["vc_class"][m] for m in MODES if m in rep["mounts"]}
    for m, fl in rep.get("floor", {}).items():
        curves[f"floor during {m.replace('_', ' + ')}"] = fl["velocity_um_s_worst_mount"]
        classes[f"floor during {m.replace('_', ' + ')}"] = rep["vc_class_floor"][m]
    fig, ax = plt.subplots(figsize=(9, 6))
    plot_vc(ax, {"band_hz": rep["band_hz"], "velocity_um_s": curves, "vc_class": classes},
            title=f"{Path(rep['recording']).name}: one-third-octave rms velocity (worst mount) by isolation mode")
    if "off" in rep.get("absent_modes", {}):
        ax.text(0.01, 0.01, "no isolation-off stretch in this run: isolation on alone, no baseline to compare with",
                transform=ax.transAxes, fontsize=8, color="0.3", va="bottom")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

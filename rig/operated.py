"""Recordings of operated runs (the stand layout's modes): the mode, reference and tracking error channels,
read back per segment, with the figures an operator asks for and the plot of reference, position and error.

A segment starts at each mode request the run recorded (events `<mount>: mode ...`) and at activation; its
figures skip the first `settle_s` (the move to the reference's offset, a waveform's fade-in) and say:
  every mode     peak valve command, share of periods the limiter acted, rms of the load's acceleration,
                 and the load's and the floor's motion in 1-100 Hz (`load_and_floor_m`: the accelerometer on
                 the moving part integrated twice in that band; compare isolate with hold under the same floor).
                 These are the rms of the very curves the plot draws, over the segment less its settle_s (the
                 plot shades what they leave out and writes them beside each segment): one figure, one function.
  track / hold   rms and max tracking error, the reference's amplitude (half its peak-to-peak) and the rms
                 error in % of it
  isolate / off  rms of the transducer (isolating: the stroke the loop moved against the floor)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.signal

from rig.errors import RecordingError

LOAD_BAND_HZ = (1.0, 100.0)
TAPER_S = 0.2                  # the band filter's fade at each end of a record: a fifth of the band's longest period

MODE_NAMES = ("off", "hold", "track", "isolate")


@dataclass
class OperatedRun:
    """One mount of an operated recording (arrays per period) and the run's events."""
    source: str
    mount: str
    t_s: np.ndarray
    mode: np.ndarray
    reference_m: np.ndarray
    error_m: np.ndarray
    position_m: np.ndarray
    accel_mps2: np.ndarray
    valve_cmd_V: np.ndarray
    limited: np.ndarray
    active: np.ndarray
    events: list = field(default_factory=list)      # (t_s, text)
    floor_accel_mps2: np.ndarray | None = None      # the floor accelerometer, when fitted


def load_operated(path, mount: int | str = 0) -> OperatedRun:
    """Read an operated run (rig run on the stand layout) from its HDF5 recording; RecordingError (one line)
    when the file is not one."""
    import h5py
    p = Path(path)
    try:
        with h5py.File(p, "r") as f:
            if "mode" not in f or "tracking_error_m" not in f:
                raise RecordingError(f"{p}: not an operated run (no mode / tracking_error_m datasets: record a "
                                     f"run on the stand layout)")
            labels = [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(f["mode"].attrs.get(
                "labels", ["mount0"]))]
            m = labels.index(mount) if isinstance(mount, str) and mount in labels else mount
            if not isinstance(m, int) or not 0 <= m < len(labels):
                raise RecordingError(f"{p}: mount {mount!r} not recorded (have {', '.join(labels)})")

            def col(name):
                a = np.asarray(f[name][()], dtype=float)
                return a[:, m] if a.ndim == 2 else a
            n = min(len(f[k]) for k in ("time_s", "mode", "stroke_m", "valve_cmd_V"))
            ev = []
            if "events" in f:
                ev = [(float(t), x.decode() if isinstance(x, bytes) else str(x))
                      for t, x in zip(f["events/time_s"][()], f["events/text"][()])]
            run = OperatedRun(str(p), labels[m], col("time_s")[:n], col("mode")[:n], col("reference_m")[:n],
                              col("tracking_error_m")[:n], col("stroke_m")[:n], col("accel_mps2")[:n],
                              col("valve_cmd_V")[:n], col("cmd_limited")[:n], col("lifecycle_state")[:n] == 2, ev,
                              col("floor_accel_mps2")[:n] if "floor_accel_mps2" in f else None)
    except RecordingError:
        raise
    except (OSError, KeyError, ValueError) as e:
        raise RecordingError(f"{p}: not a readable operated run ({type(e).__name__}: {e})"[:300]) from None
    return run


def segments(run: OperatedRun) -> list[tuple[float, float, str]]:
    """(start s, end s, what) for each stretch between this mount's mode requests while ACTIVE."""
    act = np.flatnonzero(run.active)
    if not len(act):
        return []
    t0, t1 = float(run.t_s[act[0]]), float(run.t_s[act[-1]])
    marks = [(t0, _mode_at(run, t0))]
    for t, text in run.events:
        if text.startswith(f"{run.mount}: mode ") and t0 < t < t1:
            marks.append((t, text.split(": mode ", 1)[1]))
    ends = [t for t, _ in marks[1:]] + [t1]
    return [(a, b, w) for (a, w), b in zip(marks, ends) if b > a]


def _mode_at(run: OperatedRun, t: float) -> str:
    k = min(int(np.searchsorted(run.t_s, t)), len(run.t_s) - 1)
    return MODE_NAMES[int(run.mode[k])] if math.isfinite(run.mode[k]) else "?"


def figures(run: OperatedRun, settle_s: float = 0.5) -> list[dict]:
    """The figures of each segment (module docstring), skipping its first settle_s."""
    out = []
    motion = None
    for a, b, what in segments(run):
        skip = min(settle_s, 0.5 * (b - a))
        sel = (run.t_s >= a + skip) & (run.t_s < b) & run.active
        mode = _mode_at(run, a + 1e-9 + skip)
        d = {"from_s": round(a, 4), "to_s": round(b, 4), "request": what, "mode": mode, "periods": int(sel.sum())}
        if sel.sum() < 2:
            out.append(d)
            continue
        u = run.valve_cmd_V[sel]
        d["peak_command_V"] = float(np.max(np.abs(u)))
        d["accel_rms_mps2"] = float(np.std(run.accel_mps2[sel]))
        if motion is None:
            motion = load_and_floor_m(run)
            whole = untapered(len(run.t_s), 1.0 / float(np.median(np.diff(run.t_s))))
        if np.any(sel & whole):        # not when the segment lies in the record's faded end (no 1 Hz figure there)
            d["load_motion_um"], d["floor_motion_um"] = (rms_um(x, sel & whole) for x in motion[:2])
            d["motion_s"] = [float(run.t_s[sel & whole][0]), float(run.t_s[sel & whole][-1])]
        d["limited_pct"] = float(100 * np.mean(run.limited[sel] > 0))
        if mode in ("hold", "track"):
            e = run.error_m[sel]
            r = run.reference_m[sel]
            amp = 0.5 * float(np.max(r) - np.min(r))
            rms = float(np.sqrt(np.mean(e ** 2)))
            d.update(rms_error_um=rms * 1e6, max_error_um=float(np.max(np.abs(e))) * 1e6,
                     reference_amplitude_um=amp * 1e6,
                     rms_error_pct=100 * rms / amp if amp > 1e-9 else None)
        else:
            d.update(position_rms_um=float(np.std(run.position_m[sel])) * 1e6)
        out.append(d)
    return out


def rms_um(x_m, sel) -> float:
    """The rms of a displacement over the periods `sel`, in um: every motion figure, printed or plotted."""
    return float(np.sqrt(np.mean(np.asarray(x_m)[sel] ** 2))) * 1e6 if np.any(sel) else math.nan


def _taper_n(n: int, fs_hz: float) -> int:
    """Periods faded at each end of a record before the band filter: 5 % of it, at most TAPER_S."""
    return max(1, min(int(0.05 * n), int(TAPER_S * fs_hz)))


def untapered(n: int, fs_hz: float) -> np.ndarray:
    """The periods of a record of n that the band filter's end tapers leave whole (a motion figure's window)."""
    k = _taper_n(n, fs_hz)
    keep = np.zeros(n, dtype=bool)
    keep[k:n - k] = True
    return keep


def _in_band(x, fs_hz: float, gain) -> np.ndarray:
    """x through a zero-phase filter given by gain(f) (complex), LOAD_BAND_HZ only: the record's ends tapered
    (Tukey, `_taper_n` periods each) and the FFT zero-padded to four times its length, so that neither end wraps
    onto the other. The tapered ends read low: figures leave them out (`untapered`)."""
    x = np.asarray(x, dtype=float)
    x = np.where(np.isfinite(x), x, 0.0)
    n = len(x)
    if n < 3:
        return np.zeros(n)
    X = np.fft.rfft((x - x.mean()) * scipy.signal.windows.tukey(n, 2 * _taper_n(n, fs_hz) / n), 4 * n)
    f = np.fft.rfftfreq(4 * n, 1.0 / fs_hz)
    sel = (f >= LOAD_BAND_HZ[0]) & (f <= LOAD_BAND_HZ[1])
    Y = np.zeros_like(X)
    Y[sel] = X[sel] * gain(f[sel])
    return np.fft.irfft(Y, 4 * n)[:n]


def band_displacement_m(accel_mps2, fs_hz: float) -> np.ndarray:
    """The displacement in LOAD_BAND_HZ from an absolute acceleration, in time: x = -a / (2 pi f)^2."""
    return _in_band(accel_mps2, fs_hz, lambda f: -1.0 / (2 * np.pi * f) ** 2)


def load_and_floor_m(run: OperatedRun) -> tuple[np.ndarray, np.ndarray, str]:
    """(load, floor, how the floor was had) displacements in LOAD_BAND_HZ: the load from its accelerometer;
    the floor from the floor accelerometer when fitted, else the load less the transducer (the piston's
    stroke relative to the housing, which stands on the floor)."""
    fs = 1.0 / float(np.median(np.diff(run.t_s)))
    load = band_displacement_m(run.accel_mps2, fs)
    if run.floor_accel_mps2 is not None:
        return load, band_displacement_m(run.floor_accel_mps2, fs), "floor accelerometer"
    return load, load - _in_band(run.position_m, fs, lambda f: 1.0), "load - transducer"


def _motion_text(d: dict) -> str:
    if "load_motion_um" not in d:
        return f"load not judged (in the recording's last {TAPER_S:g} s, where its {LOAD_BAND_HZ[0]:g} Hz edge fades)"
    return f"load {d['load_motion_um']:.3f} um rms in {LOAD_BAND_HZ[0]:g}-{LOAD_BAND_HZ[1]:g} Hz"


def figures_text(figs: list[dict]) -> str:
    """One line per segment."""
    lines = []
    for d in figs:
        head = f"{d['from_s']:7.2f}-{d['to_s']:7.2f} s  {d['request']:<36s}"
        if "rms_error_um" in d:
            pct = f" ({d['rms_error_pct']:.2f} % of {d['reference_amplitude_um']:.2f} um)" \
                if d.get("rms_error_pct") is not None else ""
            lines.append(f"{head} tracking error rms {d['rms_error_um']:.4f} um{pct}, max {d['max_error_um']:.3f} um, "
                         f"command peak {d['peak_command_V']:.2f} V, limited {d['limited_pct']:.1f} %, "
                         f"{_motion_text(d)}")
        elif "position_rms_um" in d:
            lines.append(f"{head} {_motion_text(d)} (from the accelerometer), "
                         f"transducer rms {d['position_rms_um']:.3f} um, command peak {d['peak_command_V']:.2f} V")
        else:
            lines.append(f"{head} (too short)")
    return "\n".join(lines)


def plot(run: OperatedRun, png, figs: list[dict] | None = None) -> Path:
    """The run's figure (`figure`) as a PNG."""
    import matplotlib.pyplot as plt
    fig = figure(run, figs)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return Path(png)


def figure(run: OperatedRun, figs: list[dict] | None = None):
    """Reference and position; the tracking error (when a segment held or tracked); the load's and the floor's
    motion in 1-100 Hz (what isolating is judged by); the valve command. The segments marked, the error
    figures in the title lines. A matplotlib Figure (the caller closes it)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figs = figures(run) if figs is None else figs
    t = run.t_s
    tracked = bool(np.isfinite(run.error_m).any())
    ratios = [3, 2, 2, 1.5] if tracked else [3, 2, 1.5]
    fig, axes = plt.subplots(len(ratios), 1, figsize=(10, 2.2 * len(ratios) + 1), sharex=True,
                             gridspec_kw={"height_ratios": ratios})
    a1, a3 = axes[0], axes[-1]
    a1.plot(t, run.position_m * 1e6, color="tab:blue", lw=0.8, label="position (transducer)")
    if np.isfinite(run.reference_m).any():
        a1.plot(t, run.reference_m * 1e6, color="tab:orange", lw=1.0, ls="--", label="reference")
    a1.set_ylabel("position [um]")
    a1.legend(loc="upper right", fontsize=8)
    if tracked:
        axes[1].plot(t, run.error_m * 1e6, color="tab:red", lw=0.8)
        axes[1].set_ylabel("tracking error [um]")
    am = axes[-2]
    load, floor, how = load_and_floor_m(run)
    am.plot(t, floor * 1e6, color="0.55", lw=0.7, label=f"floor ({how})")
    am.plot(t, load * 1e6, color="tab:green", lw=0.8, label="load (accelerometer)")
    am.set_ylabel(f"motion {LOAD_BAND_HZ[0]:g}-{LOAD_BAND_HZ[1]:g} Hz [um]")
    for i, d in enumerate(f for f in figs if "load_motion_um" in f):
        # the printed figures, written over the stretch they cover (unshaded: the segment less its settling
        # and the recording's faded ends)
        lo, hi = d["motion_s"]
        for x0, x1 in ((d["from_s"], lo), (hi, d["to_s"])):
            if x1 > x0:
                am.axvspan(x0, x1, color="0.88", lw=0, zorder=0)
        am.text(lo, 0.97 - 0.2 * (i % 2), f"load {d['load_motion_um']:.3f}\nfloor {d['floor_motion_um']:.3f} um",
                transform=am.get_xaxis_transform(), fontsize=6.5, va="top", color="tab:green",
                bbox={"facecolor": "white", "alpha": 0.8, "lw": 0, "pad": 1})
    am.legend(loc="lower right", fontsize=7, title="rms per segment as printed (shaded: not counted)",
              title_fontsize=7)
    a3.plot(t, run.valve_cmd_V, color="0.3", lw=0.6)
    a3.set_ylabel("valve [V]")
    a3.set_xlabel("time [s]")
    for i, d in enumerate(figs):
        for a in axes:
            a.axvline(d["from_s"], color="0.6", lw=0.6, ls=":")
        # two rows of labels: a short segment's label does not run into the next one's
        a1.text(d["from_s"], 1.0 + 0.05 * (i % 2), f" {d['request']}", transform=a1.get_xaxis_transform(),
                fontsize=7, va="bottom", rotation=0)
    lines = [f"{d['request']}: rms error {d['rms_error_um']:.3f} um = {d['rms_error_pct']:.2f} %"
             for d in figs if d.get("rms_error_pct") is not None]
    fig.suptitle("\n".join([f"{Path(run.source).name} ({run.mount})"] + lines[:3]), fontsize=9)
    for a in axes:
        a.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig

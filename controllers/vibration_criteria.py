"""Vibration criterion (VC) curves: one-third-octave rms velocity of a motion record against the generic
criteria users judge isolation by (Ungar & Gordon; IEST-RP-CC012), and the class a record meets.

- Bands: base-10 one-third octaves (IEC 61260), exact centres 10^(n/10) Hz, edges centre x 10^(+-1/20),
  labelled by their nominal centres (1, 1.25, 1.6, 2, 2.5, 3.15, 4, 5, 6.3, 8, 10, ..., 80, 100 Hz).
- Band rms velocity: the Welch PSD of the velocity (Hann window, linear detrend; a displacement record is
  differentiated in the frequency domain, |V| = 2 pi f |X|, an acceleration record integrated,
  |V| = |A| / (2 pi f)) integrated over the frequency bins whose centre falls in the band. Brick-wall bands, so
  a sine at a band's centre gives exactly its rms in that band.
- Criteria (rms velocity per one-third octave band):
    ISO lines (ISO 2631-2 base curve for vertical vibration, times 1 / 2 / 4 / 8 for operating theatre /
    residential (day) / office / workshop): 100 um/s from 8 Hz up; below 8 Hz constant acceleration
    (5 mm/s^2, velocity ~ 1/f) down to 4 Hz, then acceleration ~ f^-1/2 (velocity ~ f^-3/2) to 1 Hz.
    VC-A 50, VC-B 25, VC-C 12.5, VC-D 6.25, VC-E 3.12, VC-F 1.56, VC-G 0.78 um/s, flat from 1 Hz.
  The criteria are defined up to 80 Hz; the 100 Hz band is held to the 80 Hz value (the rig reports 1-100 Hz).
- The class met: the most stringent criterion that no band exceeds ("VC-D"); "above workshop" if none.
"""
from __future__ import annotations

import math

import numpy as np

NOMINAL_HZ = (1.0, 1.25, 1.6, 2.0, 2.5, 3.15, 4.0, 5.0, 6.3, 8.0, 10.0, 12.5, 16.0, 20.0, 25.0, 31.5, 40.0, 50.0,
              63.0, 80.0, 100.0)

# name -> velocity level above 8 Hz in um/s, and whether it follows the ISO base curve's shape below 8 Hz;
# least to most stringent
CRITERIA = (("workshop (ISO)", 800.0, True), ("office (ISO)", 400.0, True), ("residential day (ISO)", 200.0, True),
            ("operating theatre (ISO)", 100.0, True), ("VC-A", 50.0, False), ("VC-B", 25.0, False),
            ("VC-C", 12.5, False), ("VC-D", 6.25, False), ("VC-E", 3.12, False), ("VC-F", 1.56, False),
            ("VC-G", 0.78, False))
NONE_MET = "above workshop (ISO)"


def third_octave_bands(f_lo_hz: float = 1.0, f_hi_hz: float = 100.0):
    """(nominal centres, exact centres, lower edges, upper edges) in Hz of the bands from f_lo_hz to f_hi_hz."""
    n = np.arange(round(10 * math.log10(f_lo_hz)), round(10 * math.log10(f_hi_hz)) + 1)
    fc = 10.0 ** (n / 10.0)
    nominal = np.array([NOMINAL_HZ[int(k) % 10] * 10.0 ** (int(k) // 10) for k in n])
    return nominal, fc, fc * 10 ** (-1 / 20), fc * 10 ** (1 / 20)


def criterion_um_s(name: str, f_hz) -> np.ndarray:
    """A criterion's rms velocity limit (um/s) at the band centres f_hz."""
    for n, level, iso in CRITERIA:
        if n == name:
            break
    else:
        raise ValueError(f"criterion {name!r}: expected one of {', '.join(c[0] for c in CRITERIA)}")
    f = np.minimum(np.asarray(f_hz, dtype=float), 80.0)
    if not iso:
        return np.full_like(f, level)
    # ISO 2631-2 base curve shape, scaled to `level` above 8 Hz
    v = np.where(f >= 8.0, 1.0, np.where(f >= 4.0, 8.0 / f, 2.0 * (4.0 / f) ** 1.5))
    return level * v


def band_velocity_rms(x, fs_hz: float, *, kind: str = "displacement", f_lo_hz: float = 1.0,
                      f_hi_hz: float = 100.0, segment_s: float | None = None):
    """(nominal band centres Hz, rms velocity per band m/s) of a record x sampled at fs_hz.

    kind: "displacement" (m), "velocity" (m/s) or "acceleration" (m/s^2, e.g. an accelerometer's record).
    segment_s: Welch segment length (default: the whole record, which resolves the 1 Hz band best; it needs
    at least ~5 s for 1 Hz: a shorter one gives its window's smoothed spectrum there, never an empty band)."""
    import scipy.signal
    if kind not in ("displacement", "velocity", "acceleration"):
        raise ValueError(f"kind {kind!r}: expected displacement, velocity or acceleration")
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or len(x) < 16:
        raise ValueError(f"expected a 1-D record of at least 16 samples, got shape {x.shape}")
    nper = len(x) if segment_s is None else min(len(x), int(round(segment_s * fs_hz)))
    # a segment shorter than ~9 s / f_lo leaves the lowest band (0.23 f_lo wide) one bin or none, read as a
    # measured zero: the FFT is zero-padded then until it holds four (the same spectrum, sampled finer)
    nominal, _, lo, hi = third_octave_bands(f_lo_hz, f_hi_hz)
    width = float(hi[0] - lo[0])
    nfft = nper if fs_hz / nper <= width / 2 else int(math.ceil(4 * fs_hz / width))
    f, S = scipy.signal.welch(x, fs=fs_hz, window="hann", nperseg=nper, nfft=nfft, detrend="linear",
                              scaling="density")
    if kind == "displacement":
        S = S * (2 * np.pi * f) ** 2
    elif kind == "acceleration":
        S = np.divide(S, (2 * np.pi * f) ** 2, out=np.zeros_like(S), where=f > 0)
    df = f[1] - f[0]
    rms = np.array([math.sqrt(float(np.sum(S[(f >= a) & (f < b)])) * df) for a, b in zip(lo, hi)])
    return nominal, rms


def vc_class(band_um_s, f_hz) -> str:
    """The most stringent criterion that every band (rms velocity in um/s at nominal centres f_hz) meets."""
    met = NONE_MET
    v = np.asarray(band_um_s, dtype=float)
    for name, _, _ in CRITERIA:
        if np.all(v <= criterion_um_s(name, f_hz) * (1 + 1e-9)):
            met = name
        else:
            break
    return met


def vc_report(records: dict, fs_hz: float, *, kind: str = "displacement", f_lo_hz: float = 1.0,
              f_hi_hz: float = 100.0) -> dict:
    """For {label: record}: the band centres, each record's band rms velocity (um/s) and the class met, as
    JSON-ready lists: {"band_hz": [...], "velocity_um_s": {label: [...]}, "vc_class": {label: "VC-D"}}."""
    out = {"band_hz": None, "velocity_um_s": {}, "vc_class": {}}
    for label, x in records.items():
        fc, v = band_velocity_rms(x, fs_hz, kind=kind, f_lo_hz=f_lo_hz, f_hi_hz=f_hi_hz)
        out["band_hz"] = [float(c) for c in fc]
        out["velocity_um_s"][label] = [float(u) for u in v * 1e6]
        out["vc_class"][label] = vc_class(v * 1e6, fc)
    return out


def plot_vc(ax, report: dict, title: str = "", criteria=None):
    """Draw a vc_report's curves (one-third-octave rms velocity, log-log) over the criterion lines on a
    matplotlib Axes. criteria: names to draw (default: all that fall in the plotted range)."""
    fc = np.asarray(report["band_hz"], dtype=float)
    ff = np.geomspace(fc[0], fc[-1], 200)
    curves = report["velocity_um_s"]
    shown = [x for v in curves.values() for x in v if x is not None and x > 0 and math.isfinite(x)]
    lo, hi = (min(shown), max(shown)) if shown else (1.0, 1.0)
    names = criteria or [n for n, lvl, _ in CRITERIA if lo / 3 <= lvl <= hi * 30]
    for name in names:
        y = criterion_um_s(name, ff)
        ax.loglog(ff, y, color="0.6", lw=0.8, ls="--")
        ax.text(ff[-1], y[-1], " " + name, fontsize=7, color="0.4", va="center")
    styles = ("k-o", "b-s", "g-^", "r-d", "m-v", "c-x", "y-*", "k:.")
    for (label, v), st in zip(curves.items(), styles):
        ax.loglog(fc, v, st, ms=3, lw=1.2, label=f"{label}: {report['vc_class'][label]}")
    ax.set_xlabel("one-third octave band centre [Hz]")
    ax.set_ylabel("rms velocity [um/s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    return ax


def band_velocity_rms_from_psd(f_hz, psd_m2_per_hz, *, kind: str = "displacement", f_lo_hz: float = 1.0,
                               f_hi_hz: float = 100.0):
    """(nominal band centres Hz, rms velocity per band m/s) from a one-sided PSD on a frequency grid
    (a model's prediction rather than a record): the velocity PSD integrated over each band (trapezoid on the
    grid, clipped at the band edges)."""
    f = np.asarray(f_hz, dtype=float)
    S = np.asarray(psd_m2_per_hz, dtype=float)
    if kind == "displacement":
        S = S * (2 * np.pi * f) ** 2
    elif kind != "velocity":
        raise ValueError(f"kind {kind!r}: expected displacement or velocity")
    nominal, _, lo, hi = third_octave_bands(f_lo_hz, f_hi_hz)
    out = []
    for a, b in zip(lo, hi):
        g = np.unique(np.concatenate([[a, b], f[(f > a) & (f < b)]]))
        out.append(math.sqrt(max(0.0, float(np.trapezoid(np.interp(g, f, S), g)))))
    return nominal, np.array(out)

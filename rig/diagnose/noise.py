"""The measurement noise of a recording, from a model residual: its spectrum, its rms, and the converter step.

The noise floor is taken as the median over time of the residual's short-time power spectrum, bin by bin, then
median-smoothed across frequency. A swept excitation leaves its model error in a few windows of each bin (the
sweep passes once) and a spectral line in a few bins, so neither moves the medians; coloured noise (a filter before
the converter, a 1/f part) keeps its shape, and its rms is the integral of that floor. A transducer's converter
step q adds q^2/12 of white noise, which the floor then contains.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter


@dataclass
class NoiseFloor:
    freqs_hz: np.ndarray
    psd: np.ndarray             # one-sided power spectral density, m^2/Hz
    rms_m: float                # sqrt of its integral (the noise the residual should reach)
    white_rms_m: float          # the rms a white noise with the high-band level would have (for comparison)

    def asd_at(self, f_hz) -> np.ndarray:
        return np.sqrt(np.interp(f_hz, self.freqs_hz, self.psd))

    @property
    def colour_db(self) -> float:
        """How far the floor departs from white: 10 log10 of the max/min of its smoothed level in the band
        that holds 95 % of the power (0 dB for white noise)."""
        p = median_filter(self.psd, size=max(3, (len(self.psd) // 20) | 1), mode="nearest")
        sel = p > 0
        return float(10 * math.log10(np.max(p[sel]) / np.min(p[sel]))) if sel.sum() > 2 else 0.0


def floor(resid: np.ndarray, fs: float, mask: np.ndarray | None = None, win_s: float = 1.0) -> NoiseFloor:
    """Noise floor of a residual (mask: samples to use; windows with masked samples are left out)."""
    r = np.asarray(resid, float)
    n = len(r)
    nw = int(min(max(64, round(win_s * fs)), max(16, n // 4)))
    hop = nw // 2
    starts = np.arange(0, n - nw + 1, hop)
    if mask is not None:
        bad = np.r_[0, np.cumsum(~np.asarray(mask, bool))]
        starts = starts[(bad[starts + nw] - bad[starts]) == 0]
    if len(starts) < 3:                     # too short or too masked: one periodogram of what there is
        starts = np.arange(0, max(1, n - nw + 1), max(1, hop))[:max(1, len(starts))]
    w = np.hanning(nw)
    seg = r[starts[:, None] + np.arange(nw)[None, :]]
    seg = seg - seg.mean(axis=1, keepdims=True)
    P = np.abs(np.fft.rfft(seg * w, axis=1)) ** 2 * (2.0 / (fs * np.sum(w ** 2)))
    f = np.fft.rfftfreq(nw, 1.0 / fs)
    med = np.median(P, axis=0) / math.log(2.0) if len(starts) > 2 else np.mean(P, axis=0)
    psd = median_filter(med, size=11, mode="nearest")
    psd[0] = psd[1]
    df = fs / nw
    hi = (f > 0.6 * fs / 2) & (f < 0.95 * fs / 2)
    white = math.sqrt(float(np.median(psd[hi])) * fs / 2) if hi.any() else math.sqrt(float(np.sum(psd)) * df)
    return NoiseFloor(freqs_hz=f, psd=psd, rms_m=math.sqrt(float(np.sum(psd[1:]) * df)), white_rms_m=white)


def quantisation_step(x: np.ndarray, min_fraction: float = 0.995) -> float:
    """The converter step of a quantised channel, or 0.0: nearly every sample on a grid offset + k q, with q the
    common spacing of neighbouring distinct values (a CSV's printing precision is relative, not a grid)."""
    x = np.asarray(x, float)
    u = np.unique(x)
    if len(u) < 8 or len(u) > 0.5 * len(x):
        return 0.0
    d = np.diff(u)
    scale = float(np.max(np.abs(u))) or 1.0
    d = d[d > 1e-12 * scale]
    if len(d) == 0:
        return 0.0
    q = float(np.percentile(d, 5))
    if q <= 1e-9 * scale:
        return 0.0
    k = (x - u[0]) / q
    on = np.abs(k - np.round(k)) < 0.02
    return q if on.mean() >= min_fraction else 0.0

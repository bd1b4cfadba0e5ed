"""The measurement noise of a recording, from a model residual: its spectrum, its rms, and the converter step.

The noise floor is the residual's power spectrum with the command's response taken out, median-smoothed across
frequency (so that a spectral line does not count), and its rms is the integral of that floor: coloured noise (a
filter before the converter, a 1/f part) keeps its shape. How the response is taken out depends on the command:
  sweep       the median over time of the short-time spectra, bin by bin: the sweep passes each bin once, so
              its model error sits in a few windows and does not move the median;
  multisine   the residual minus its average period: what repeats is the response (linear or not), the rest noise;
  broadband   (noise, steps) the part of the residual coherent with the command is removed, S_rr (1 - coh^2).
A transducer's converter step q adds q^2/12 of white noise, which the floor then contains.
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


def _windows(r: np.ndarray, fs: float, mask, win_s: float):
    n = len(r)
    nw = int(min(max(64, round(win_s * fs)), max(16, n // 4)))
    hop = nw // 2
    starts = np.arange(0, n - nw + 1, hop)
    if mask is not None:
        bad = np.r_[0, np.cumsum(~np.asarray(mask, bool))]
        starts = starts[(bad[starts + nw] - bad[starts]) == 0]
    if len(starts) < 3:                     # too short or too masked: what there is
        starts = np.arange(0, max(1, n - nw + 1), max(1, hop))[:max(1, len(starts))]
    return nw, starts


def _spectra(x: np.ndarray, nw: int, starts: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    w = np.hanning(nw)
    seg = x[starts[:, None] + np.arange(nw)[None, :]]
    seg = seg - seg.mean(axis=1, keepdims=True)
    X = np.fft.rfft(seg * w, axis=1) * math.sqrt(2.0 / (fs * np.sum(w ** 2)))
    return np.fft.rfftfreq(nw, 1.0 / fs), X


def deperiodize(resid: np.ndarray, period: int, mask: np.ndarray | None = None
                ) -> tuple[np.ndarray, float, np.ndarray | None]:
    """The residual minus its average over whole periods (a periodic command's response, linear or not, is the
    same in every period; the noise is not), the variance factor P / (P - 1) that restores the noise, and the
    mask of the samples that were deperiodized (the rest of the record still holds the response)."""
    r = np.asarray(resid, float).copy()
    n = len(r)
    i0 = int(np.argmax(mask)) if mask is not None and np.any(mask) else 0
    k = (n - i0) // period
    if period <= 0 or k < 2:
        return r, 1.0, mask
    blk = r[i0:i0 + k * period].reshape(k, period)
    blk -= blk.mean(axis=0, keepdims=True)
    r[i0:i0 + k * period] = blk.ravel()
    done = np.zeros(n, bool)
    done[i0:i0 + k * period] = True
    return r, k / (k - 1.0), done if mask is None else (done & np.asarray(mask, bool))


def floor(resid: np.ndarray, fs: float, mask: np.ndarray | None = None, *, win_s: float = 1.0, period: int = 0,
          cmd: np.ndarray | None = None) -> NoiseFloor:
    """Noise floor of a residual (mask: samples to use; windows with masked samples are left out).

    period > 0 (a periodic command): the residual's part that repeats every period is the command's response
    and is removed first. cmd given (a broadband command, noise or steps, whose response is in every window):
    the part coherent with the command is removed, S_rr (1 - coherence^2). Otherwise (a sweep) the median over
    time of the short-time spectra."""
    r = np.asarray(resid, float)
    factor = 1.0
    if period:
        r, factor, mask = deperiodize(r, period, mask)
    nw, starts = _windows(r, fs, mask, win_s)
    f, X = _spectra(r, nw, starts, fs)
    P = np.abs(X) ** 2
    if cmd is not None and len(starts) > 2:
        _, U = _spectra(np.asarray(cmd, float), nw, starts, fs)
        Suu = np.mean(np.abs(U) ** 2, axis=0)
        Srr = np.mean(P, axis=0)
        Sur = np.mean(np.conj(U) * X, axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            coh = np.where(Suu * Srr > 0, np.abs(Sur) ** 2 / (Suu * Srr), 0.0)
        med = Srr * np.clip(1.0 - coh, 0.0, 1.0)
    else:
        med = np.median(P, axis=0) / math.log(2.0) if len(starts) > 2 else np.mean(P, axis=0)
    psd = median_filter(med * factor, size=11, mode="nearest")
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


@dataclass(frozen=True)
class Roughness:
    """What the measured output's own sample-to-sample roughness allows the noise to be: for white noise of rms s
    the k-th difference has rms s sqrt(C(2k, k)), and a response smooth at the sample rate adds to it, so each
    order k gives an upper bound; the least of k = 1..MAX_ORDER is kept (the order that took the response out)."""
    rms: float
    order: int


ROUGHNESS_MAX_ORDER = 5


def roughness(y: np.ndarray, mask: np.ndarray | None = None) -> Roughness:
    """The noise rms the output's own differences allow (mask: the samples to use; a difference counts only where
    every sample it spans is used)."""
    y = np.asarray(y, float)
    ok = np.ones(len(y), bool) if mask is None else np.asarray(mask, bool)
    best = Roughness(math.inf, 0)
    for k in range(1, ROUGHNESS_MAX_ORDER + 1):
        if len(y) <= k + 10:
            break
        d = np.diff(y, k)
        spans = np.convolve(ok.astype(int), np.ones(k + 1, int), "valid") == k + 1
        if spans.sum() < 10:
            break
        s = math.sqrt(float(np.mean(d[spans] ** 2)) / math.comb(2 * k, k))
        if s < best.rms:
            best = Roughness(s, k)
    return best

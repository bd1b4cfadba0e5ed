"""Frequency-response estimate of a chirp recording: H1 = S_uy / S_uu with coherence (Welch, scipy.signal),
the excited band of the chirp, and the paper's second-order Savitzky-Golay smoothing of magnitude and phase.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal as ss

from rig.errors import RecordingError
from rig.recordings.recording import Recording

SEGMENT_S = 4.0          # Welch segment length: 0.25 Hz resolution, >= 12 averages in 100 s at 75 % overlap
MIN_COHERENCE = 0.9      # bins below this are not used for fitting


@dataclass
class FRF:
    freqs_hz: np.ndarray
    H: np.ndarray               # H1 estimate, m/V (complex), raw
    coherence: np.ndarray       # magnitude-squared coherence, 0..1
    H_smooth: np.ndarray        # Savitzky-Golay smoothed (magnitude in dB and unwrapped phase), inside the band
    band_hz: tuple[float, float]  # the excited band of the input (chirp), from its spectrum
    use: np.ndarray             # bool mask: inside the band and coherent enough to fit
    fs_hz: float
    nperseg: int

    @property
    def w(self) -> np.ndarray:
        return 2 * np.pi * self.freqs_hz

    def as_dict(self) -> dict:
        return {"freqs_hz": self.freqs_hz.tolist(), "mag_db": (20 * np.log10(np.abs(self.H) + 1e-300)).tolist(),
                "phase_deg": np.degrees(np.angle(self.H)).tolist(), "coherence": self.coherence.tolist(),
                "band_hz": list(self.band_hz)}


def _segment(n: int, fs: float, segment_s: float) -> int:
    nper = 1 << int(round(np.log2(max(16.0, segment_s * fs))))
    return int(min(nper, max(16, n // 4)))     # at least ~7 averages at 75 % overlap


def excited_band(freqs_hz: np.ndarray, Puu: np.ndarray, rel: float = 0.1) -> tuple[float, float]:
    """Lowest and highest frequency where the input spectrum is within `rel` of its (median-filtered) peak."""
    k = min(9, (len(Puu) // 2) * 2 - 1)
    ref = float(np.max(ss.medfilt(Puu, k))) if k >= 3 else float(np.max(Puu))
    on = np.flatnonzero(Puu > rel * ref)
    if ref <= 0 or on.size == 0:
        return float(freqs_hz[0]), float(freqs_hz[-1])
    return float(freqs_hz[on[0]]), float(freqs_hz[on[-1]])


def sg_smooth(freqs_hz: np.ndarray, H: np.ndarray, mask: np.ndarray, window: int = 11) -> np.ndarray:
    """Second-order Savitzky-Golay smoothing of dB magnitude and unwrapped phase over the masked bins (paper)."""
    out = H.copy()
    idx = np.flatnonzero(mask)
    if idx.size < 5:
        return out
    win = min(window, idx.size if idx.size % 2 else idx.size - 1)
    if win < 3:
        return out
    seg = H[idx[0]:idx[-1] + 1]
    mag = ss.savgol_filter(np.log(np.abs(seg) + 1e-300), win, 2)
    ph = ss.savgol_filter(np.unwrap(np.angle(seg)), win, 2)
    out[idx[0]:idx[-1] + 1] = np.exp(mag + 1j * ph)
    return out


def frf_estimate(rec: Recording, *, segment_s: float = SEGMENT_S, overlap: float = 0.75,
                 min_coherence: float = MIN_COHERENCE, sg_window: int = 11,
                 output: str = "position_m") -> FRF:
    """H1 FRF valve_cmd_V -> position_m (or accel_mps2) with coherence and the excited band."""
    u = rec.valve_cmd_V - np.mean(rec.valve_cmd_V)
    y = getattr(rec, output) - np.mean(getattr(rec, output))
    nper = _segment(rec.n, rec.fs_hz, segment_s)
    nov = int(nper * overlap)
    kw = dict(fs=rec.fs_hz, window="hann", nperseg=nper, noverlap=nov, detrend="constant")
    f, Puu = ss.welch(u, **kw)
    _, Pyy = ss.welch(y, **kw)
    _, Puy = ss.csd(u, y, **kw)
    if not np.any(Puu[1:] > 0):
        raise RecordingError(f"{rec.source}: the valve command is constant: nothing to identify from")
    with np.errstate(divide="ignore", invalid="ignore"):
        H = np.where(Puu > 0, Puy / Puu, 0)
        coh = np.where((Puu > 0) & (Pyy > 0), np.abs(Puy) ** 2 / (Puu * Pyy), 0.0)
    f, H, coh, Puu = f[1:], H[1:], np.clip(coh[1:], 0, 1), Puu[1:]   # drop DC
    lo, hi = excited_band(f, Puu)
    inband = (f >= lo) & (f <= hi)
    use = inband & (coh >= min_coherence) & (np.abs(H) > 0)
    return FRF(freqs_hz=f, H=H, coherence=coh, H_smooth=sg_smooth(f, H, inband, sg_window), band_hz=(lo, hi),
               use=use, fs_hz=rec.fs_hz, nperseg=nper)

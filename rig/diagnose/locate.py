"""Where and how the recording differs from a model: FRF bands beyond the coherence-based uncertainty, time
windows, regimes (command magnitude, velocity sign), harmonics of a sweep's instantaneous phase (read from the
command by rig.recordings.command), and spectral lines not correlated with the command.
"""
from __future__ import annotations

import math

import numpy as np


def _merge(mask: np.ndarray, edges_lo: np.ndarray, edges_hi: np.ndarray) -> list[list[float]]:
    out: list[list[float]] = []
    for ok, lo, hi in zip(mask, edges_lo, edges_hi):
        if not ok:
            continue
        if out and abs(out[-1][1] - lo) < 1e-9:
            out[-1][1] = float(hi)
        else:
            out.append([float(lo), float(hi)])
    return out


def frf_bands(cmd_V, meas_m, models: dict[str, np.ndarray], fs: float, f_lo: float, f_hi: float, n_bands: int = 80):
    """Band-averaged FRFs (H = sum Y U* / sum |U|^2), coherence and the 1-sigma uncertainty of the measured H."""
    n = len(cmd_V)
    U = np.fft.rfft(cmd_V); Y = np.fft.rfft(meas_m)
    f = np.fft.rfftfreq(n, 1.0 / fs)
    f_lo = max(f_lo, 2 * fs / n)
    if not f_hi > 1.01 * f_lo:
        f_hi = max(0.45 * fs, 1.02 * f_lo)
    edges = np.geomspace(f_lo, f_hi, n_bands + 1)
    idx = np.searchsorted(f, edges)
    Ms = {k: np.fft.rfft(v) for k, v in models.items()}
    fc, H, coh, sig = [], [], [], []
    Hm = {k: [] for k in models}
    for a, b in zip(idx[:-1], idx[1:]):
        if b - a < 2:
            continue
        u = U[a:b]; y = Y[a:b]
        suu = float(np.sum(np.abs(u) ** 2)); syy = float(np.sum(np.abs(y) ** 2)); syu = np.sum(y * np.conj(u))
        h = syu / suu
        g2 = min(1.0 - 1e-12, abs(syu) ** 2 / (suu * syy + 1e-300))
        fc.append(float(np.sqrt(f[a] * f[b - 1]))); H.append(h); coh.append(g2)
        sig.append(abs(h) * math.sqrt((1 - g2) / (2 * (b - a) * g2)))
        for k, M in Ms.items():
            Hm[k].append(np.sum(M[a:b] * np.conj(u)) / suu)
    out = {"freqs_hz": np.array(fc), "measured": np.array(H), "coherence": np.array(coh), "sigma": np.array(sig),
           "edges_hz": edges}
    for k in models:
        out[k] = np.array(Hm[k])
    return out


def mismatch_bands(frf: dict, model_key: str, k_sigma: float = 3.0) -> list[list[float]]:
    """Bands where |H_meas - H_model| exceeds k_sigma times the coherence-based uncertainty."""
    fc = frf["freqs_hz"]
    if len(fc) == 0:                                   # no band holds two frequency bins (short or slow recording)
        return []
    err = np.abs(frf["measured"] - frf[model_key])
    bad = err > k_sigma * np.maximum(frf["sigma"], 1e-300)
    # band edges: geometric midpoints between centres
    lo = np.r_[fc[0] / 1.05, np.sqrt(fc[:-1] * fc[1:])]
    hi = np.r_[np.sqrt(fc[:-1] * fc[1:]), fc[-1] * 1.05]
    return [[round(a, 2), round(b, 2)] for a, b in _merge(bad, lo, hi)]


def mismatch_windows(resid: np.ndarray, fs: float, noise: float, win_s: float = 1.0, top: int = 3):
    """Windows where the residual rms exceeds the noise beyond chance; plus the worst windows."""
    nw = max(1, int(round(win_s * fs)))
    k = len(resid) // nw
    r = resid[: k * nw].reshape(k, nw)
    rms = np.sqrt(np.mean(r ** 2, axis=1))
    thr = noise * math.sqrt(1 + 5 * math.sqrt(2.0 / nw))
    t0 = np.arange(k) * nw / fs
    wins = [[round(a, 3), round(b, 3)] for a, b in _merge(rms > thr, t0, t0 + nw / fs)]
    worst = np.argsort(rms)[::-1][:top]
    worst_w = [{"t0_s": float(t0[i]), "t1_s": float(t0[i] + nw / fs), "rms_m": float(rms[i]),
                "over_noise": float(rms[i] / noise)} for i in worst]
    return wins, worst_w, rms


def regimes(cmd_V: np.ndarray, meas_m: np.ndarray, resid: np.ndarray, fs: float, noise: float,
            use: np.ndarray | None = None) -> dict:
    """Residual rms / noise by command magnitude tercile and by piston velocity sign (reversals apart), over the
    samples in use."""
    a = np.abs(cmd_V); peak = float(np.max(a)) or 1.0
    v = np.gradient(meas_m) * fs
    k = max(1, int(fs / 200))
    v = np.convolve(v, np.ones(k) / k, mode="same")
    vr = float(np.sqrt(np.mean(v ** 2))) or 1.0
    sel = {
        "command_low": a < peak / 3, "command_mid": (a >= peak / 3) & (a < 2 * peak / 3),
        "command_high": a >= 2 * peak / 3,
        "velocity_positive": v > 0.05 * vr, "velocity_negative": v < -0.05 * vr,
        "velocity_reversal": np.abs(v) <= 0.05 * vr,
    }
    out = {}
    for name, m in sel.items():
        if use is not None:
            m = m & use
        if m.sum() > 10:
            out[name] = {"fraction": round(float(m.mean()), 4),
                         "rms_over_noise": round(float(np.sqrt(np.mean(resid[m] ** 2)) / noise), 3)}
    return out


def harmonics(resid: np.ndarray, phase: np.ndarray, fs: float, noise: float, win_s: float = 1.0,
              orders=(1, 2, 3, 4, 5)) -> dict:
    """Residual content locked to k times the instantaneous chirp phase, as rms amplitude over its noise level.

    Hann-weighted windows (so the fundamental's leakage does not pose as a harmonic), only where a window holds
    at least 3 periods of the chirp and its harmonics stay below Nyquist."""
    nw = max(8, int(round(win_s * fs)))
    k = len(resid) // nw
    f_inst = np.gradient(phase[: k * nw]) * fs / (2 * math.pi)
    fw = np.median(f_inst.reshape(k, nw), axis=1)
    hann = np.hanning(nw); hann /= hann.sum()
    # remove the fundamental (the linear mismatch) window by window, with a linear amplitude drift, so that it
    # cannot leak into the harmonic orders
    r = resid[: k * nw].reshape(k, nw).copy()
    ph = phase[: k * nw].reshape(k, nw)
    tt = np.linspace(-1.0, 1.0, nw)
    for i in range(k):
        c, s_ = np.cos(ph[i]), np.sin(ph[i])
        X = np.c_[c, s_, tt * c, tt * s_]
        beta, *_ = np.linalg.lstsq(X, r[i], rcond=None)
        r[i] -= X @ beta
    resid_h = r.ravel()
    out = {}
    for o in orders:
        use = (fw > 3.0 / win_s) & (o * fw < 0.45 * fs)
        if not use.any():
            use = np.ones(k, bool)
        src = resid[: k * nw] if o == 1 else resid_h
        z = ((src * np.exp(-1j * o * phase[: k * nw])).reshape(k, nw) @ hann)[use]
        amp = 2 * np.abs(z)                            # amplitude of the locked component per window
        ref = 2 * noise * math.sqrt(np.sum(hann ** 2))  # its noise-only rms
        out[str(o)] = {"amplitude_rms_m": float(np.sqrt(np.mean(amp ** 2))),
                       "over_noise": float(np.sqrt(np.mean(amp ** 2)) / ref)}
    odd = max(out[str(o)]["over_noise"] for o in orders if o % 2 == 1 and o > 1)
    even = max(out[str(o)]["over_noise"] for o in orders if o % 2 == 0)
    out["odd_over_noise"] = odd
    out["even_over_noise"] = even
    return out


def spectral_lines(resid: np.ndarray, fs: float, noise: float, f_lo: float = 1.0, ratio: float = 40.0,
                   top: int = 5) -> list[dict]:
    """Lines in the residual spectrum far above the local median: output not correlated with the command."""
    n = len(resid)
    R = np.fft.rfft(resid - resid.mean())
    P = np.abs(R) ** 2 / n
    f = np.fft.rfftfreq(n, 1.0 / fs)
    half = max(25, int(1.0 * n / fs))                  # +-1 Hz local median
    from scipy.ndimage import median_filter
    med = median_filter(P, size=2 * half + 1, mode="nearest") / math.log(2)
    ok = (f > f_lo) & (f < 0.49 * fs) & (P > ratio * np.maximum(med, noise ** 2 * 0.5))
    cand = np.flatnonzero(ok)
    lines = []
    for i in cand:
        if P[i] >= P[max(0, i - 3): i + 4].max():
            lines.append((float(P[i] / max(med[i], 1e-300)), i))
    lines.sort(reverse=True)
    out = []
    for r, i in lines[:top]:
        out.append({"frequency_hz": float(f[i]), "amplitude_m": float(2 * np.abs(R[i]) / n),
                    "over_local_median": float(r)})
    return out


def refine_line(resid: np.ndarray, fs: float, f0: float) -> float:
    """Frequency of a stationary sinusoid near f0 maximising its projected power: parabolic steps on the log
    power at f and f +- a quarter bin (three projections per step, converges in a few steps to ~1e-4 bin)."""
    n = len(resid)
    t = np.arange(n) / fs
    d = fs / n

    def logpow(fq):
        return math.log(abs(np.dot(resid, np.exp(-2j * math.pi * fq * t))) ** 2 + 1e-300)
    f = float(f0)
    h = 0.25 * d
    for _ in range(4):
        a, b, c = logpow(f - h), logpow(f), logpow(f + h)
        den = a - 2 * b + c
        step = 0.5 * h * (a - c) / den if den < 0 else (h if c > a else -h)
        step = max(-1.5 * d, min(1.5 * d, step))
        f += step
        if abs(step) < 1e-3 * d:
            break
        h = max(0.05 * d, min(h, 2 * abs(step)))
    return float(min(max(f, f0 - 1.5 * d), f0 + 1.5 * d))


def multisine_lines(cmd, y: np.ndarray, use: np.ndarray, noise_psd, skip_hz: list[float]) -> dict:
    """Nonlinear distortion detector of an odd multisine: the measured position averaged over whole periods at
    the unexcited odd and the even lines of the band, rms over the noise expected there."""
    P = cmd.period
    start = int(np.argmax(use)) if use.any() else 0
    first = int(math.ceil(start / P)) * P
    k = (len(y) - first) // P
    if k < 1 or cmd.excited_lines is None:
        return {}
    seg = (y[first:first + k * P] - np.mean(y[first:first + k * P])).reshape(k, P)
    Y = np.fft.rfft(seg.mean(axis=0)) * 2.0 / P                  # line amplitudes, m
    fs = cmd.fs_hz
    freqs = np.arange(len(Y)) * fs / P
    exc = set(int(i) for i in cmd.excited_lines)
    kmin, kmax = int(min(exc)), int(max(exc))
    span = np.arange(max(1, kmin), min(len(Y) - 1, 3 * kmax) + 1)
    span = np.array([i for i in span if all(abs(freqs[i] - f) > 1.5 * fs / P for f in skip_hz)], int)
    odd = np.array([i for i in span if i % 2 == 1 and i not in exc], int)
    even = np.array([i for i in span if i % 2 == 0], int)
    # noise of PSD S (variance S fs/2 per sample) gives E|Y|^2 = 4 (S fs/2) / (P k) on a line averaged over k periods
    S = np.interp(freqs, noise_psd.freqs_hz, noise_psd.psd)
    sig = np.sqrt(2.0 * S * fs / (P * k))

    def ratio(idx):
        return np.abs(Y[idx]) ** 2 / np.maximum(sig[idx] ** 2, 1e-300)

    def over(idx):          # rms line amplitude over the noise's (1 for noise alone)
        return float(np.sqrt(np.mean(ratio(idx)))) if len(idx) else None

    def z(idx):             # how many standard errors the mean power ratio stands above 1 (noise alone: ~N(0,1))
        return float((np.mean(ratio(idx)) - 1.0) * math.sqrt(len(idx))) if len(idx) else None
    return {"odd_over_noise": over(odd), "even_over_noise": over(even), "odd_z": z(odd), "even_z": z(even),
            "periods": int(k), "odd_lines": int(len(odd)), "even_lines": int(len(even)),
            "line_spacing_hz": fs / P}

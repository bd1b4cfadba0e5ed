"""The paper's Figs. 12-13 from data: per isolation mode, mount and band, the machine's motion at the mount over
the floor's there, measured, and predicted by the model and by the diagnosed rig in closed loop.

Each isolation mode's longest stretch (the recording's flags; the first SETTLE_S left out) is taken as one
record. Measured: the power of the mount's accelerometer over the power of the floor's acceleration at that
mount, per band (floor accelerometers; without them the floor estimated bin by bin from the mounts through the
diagnosed model, which the report says). Predicted: the same ratio for the recorded floor through the closed
loop -- the configured controllers (controllers/isolation.py, controllers/feedforward.py, their frf at the loop
rate) on the model's responses (the commands' latency and the valves' delays, the sensors' gains): feedback in
the feedback modes, the floor feedforward with it, nothing else with isolation off (the centring is below 0.1
Hz). The table and the tool point are not measured on the rig: margins.py gives the model's figures for them.
"""
from __future__ import annotations

import math

import numpy as np

from rig.config import MOUNTS
from rig.diagnose.machine.rigmodel import Base, responses
from rig.recordings.runfile import MODES, RunRecording

BANDS_HZ = ((1.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0), (60.0, 100.0))
SETTLE_S = 3.0                  # the blend's and the PI's start (the feedback's slow filters) left out
MIN_SECONDS = 4.0


def _segments(run: RunRecording) -> dict[str, tuple[int, int]]:
    """Each mode's longest stretch [a, b) after SETTLE_S; the whole run as one of unknown mode when the flags
    are missing ("recorded")."""
    fs = run.fs_hz
    if run.mode is None:
        return {"recorded": (int(SETTLE_S * fs), run.n)}
    out = {}
    for k, name in enumerate(MODES):
        m = run.mode == k
        if not m.any():
            continue
        d = np.diff(np.concatenate(([0], m.astype(np.int8), [0])))
        starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
        j = int(np.argmax(stops - starts))
        a, b = int(starts[j] + SETTLE_S * fs), int(stops[j])
        if (b - a) / fs >= MIN_SECONDS:
            out[name] = (a, b)
    return out


def _closed_loop(R, w, dt, mode: str, ctrls, ffs, X) -> np.ndarray:
    """The sensors' readings (K, 8) for floor X (K, 4) with the loop closed as in `mode` (a run without
    flags, "recorded", as rig run's default: feedback)."""
    g = R.gain_out
    Hu = R.Hu * g[None, :, None]
    Hg = R.Hg * g[None, :, None]
    drive = np.einsum("kcj,kj->kc", Hg, X)
    if mode in ("off",):
        return drive
    K = np.zeros((len(w), 4, 8), dtype=complex)
    for i, c in enumerate(ctrls):
        Ka, Ks = c.frf(w)
        K[:, i, i], K[:, i, 4 + i] = Ka, Ks
    if mode == "feedback_feedforward" and ffs is not None:
        Fa = np.stack([ff.frf(w) for ff in ffs], axis=1) * R.gain_floor[None, :]
        drive = drive + np.einsum("kci,ki->kc", Hu, Fa * (-(w ** 2))[:, None] * X)
    M = np.eye(8)[None] - Hu @ K
    return np.linalg.solve(M, drive[:, :, None])[:, :, 0]


def _floor_of(run, a, b, base, th, R, sel, w, Y, U, noise) -> np.ndarray:
    if run.floor_measured:
        G = np.fft.rfft(run.floor_accel_mps2[a:b], axis=0)[sel]
        return -(G / R.gain_floor[None, :]) / (w ** 2)[:, None]
    g = R.gain_out
    sd = np.sqrt(noise[:8])
    e = (Y - np.einsum("kci,ki->kc", R.Hu * g[None, :, None], U)) / sd
    A = R.Hg * (g / sd)[None, :, None]
    AH = np.conj(np.transpose(A, (0, 2, 1)))
    return np.linalg.solve(AH @ A, AH @ e[:, :, None])[:, :, 0]


def transmissibility(run: RunRecording, base: Base, models: dict, noise: np.ndarray) -> dict:
    """{"bands_hz", "floor", "segments", "mounts": {mount: {mode: {"measured_db", model name + "_db"}}}};
    models: {"model": theta, "diagnosed": theta}."""
    dt = base.dt
    ctrls = base.controllers
    ffs = base.feedforward if run.floor_measured else None
    segs = _segments(run)
    out = {"bands_hz": [list(b) for b in BANDS_HZ], "segments": {},
           "floor": "measured" if run.floor_measured else "estimated from the mounts through the diagnosed model",
           "mounts": {m: {} for m in MOUNTS}}
    diag_th = models.get("diagnosed") or next(iter(models.values()))
    for mode, (a, b) in segs.items():
        n = b - a
        f = np.fft.rfftfreq(n, dt)
        sel = np.flatnonzero((f >= BANDS_HZ[0][0]) & (f < BANDS_HZ[-1][1]))
        w = 2 * math.pi * f[sel]
        Y = np.fft.rfft(np.hstack([run.accel_mps2[a:b], run.stroke_m[a:b]]), axis=0)[sel]
        U = np.fft.rfft(run.valve_cmd_V[a:b], axis=0)[sel]
        Rd = responses(base, diag_th, w)
        X = _floor_of(run, a, b, base, diag_th, Rd, sel, w, Y, U, noise)
        floor_pow = np.abs(X * (w ** 2)[:, None]) ** 2
        out["segments"][mode] = {"t0_s": float(run.t_s[a]), "t1_s": float(run.t_s[b - 1]), "seconds": n * dt}
        preds = {name: _closed_loop(responses(base, th, w), w, dt, mode, ctrls, ffs, X) for name, th in models.items()}
        for i, m in enumerate(MOUNTS):
            row = {"measured_db": _bands(f[sel], np.abs(Y[:, i]) ** 2, floor_pow[:, i])}
            for name, P in preds.items():
                row[f"{name}_db"] = _bands(f[sel], np.abs(P[:, i]) ** 2, floor_pow[:, i])
            out["mounts"][m][mode] = row
    return out


def _bands(f, num, den) -> list:
    out = []
    for lo, hi in BANDS_HZ:
        s = (f >= lo) & (f < hi)
        d = float(np.sum(den[s]))
        out.append(float(10 * math.log10(float(np.sum(num[s])) / d)) if s.any() and d > 0 else None)
    return out

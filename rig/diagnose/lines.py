"""The sensor terms a fit finds on the way (docs/DIAGNOSIS.md, "Sensor terms"): how many slow-wander cosines the
data support, and the lines of a residual sorted by the two sensors into pickup (a sensor term) and force (the
projected line effect's candidates)."""
from __future__ import annotations

import math

import numpy as np

from rig.recordings import command as command_mod
from rig.diagnose import locate, noise as noise_mod, sensor as sensor_mod
from rig.diagnose.problem import ModelFit, Problem

LINE_RATIO = 40.0                  # spectral line / local median for a line candidate


def choose_wander(pb: Problem, fit: ModelFit, max_terms: int) -> int:
    """Number of slow-wander cosines by BIC on the fit blocks, the physics held at `fit` (nested bases: one QR
    of the largest gives every smaller one's residual; at most 200 k fit rows, evenly spread, for the choice)."""
    if max_terms < 1:
        return 0
    rows = np.flatnonzero(pb.mfit)
    rows = rows[:: max(1, int(math.ceil(len(rows) / 200_000)))]
    rf = (pb.y - pb.physics(fit))[rows]
    n = pb.n
    cols = [np.ones(len(rows)), 2.0 * rows / max(n - 1, 1) - 1.0]
    cols += [np.cos(math.pi * k * (rows + 0.5) / n) for k in range(2, 2 + max_terms)]
    cols += [pb.basis.B[rows, j] for j in range(2 + pb.basis.wander_terms, pb.basis.m)]     # lines, if any
    order = [0, 1] + list(range(2 + max_terms, len(cols))) + list(range(2, 2 + max_terms))
    Q, _ = np.linalg.qr(np.column_stack([cols[j] for j in order]))
    proj = Q.T @ rf
    total = float(rf @ rf)
    nf = len(rf)
    base_m = len(cols) - max_terms
    best = (np.inf, 0)
    for k in sorted({0, 1, 2, 4, 8, 16, max_terms}):
        if k > max_terms:
            continue
        m = base_m + k
        rss = max(total - float(proj[:m] @ proj[:m]), 1e-300)
        bic = nf * math.log(rss) + m * math.log(nf)
        if bic < best[0]:
            best = (bic, k)
    return best[1]


def on_grid(f: float, grid_hz: float, T: float) -> int | None:
    """The grid index k when f is within one resolution bin of k grid_hz, else None."""
    if not grid_hz:
        return None
    k = int(round(f / grid_hz))
    return k if k >= 1 and abs(f - k * grid_hz) <= 1.0 / T else None


def residual_lines(pb: Problem, r: np.ndarray, acc: np.ndarray, acc_model: np.ndarray | None, check, fs: float,
           cmd_info: command_mod.Command, acc_use: np.ndarray):
    """Lines of the position residual sorted by the two sensors into pickup (sensor) and force (physics);
    plus lines the accelerometer alone shows (pickup on that channel).

    A periodic command puts its own response (linear and nonlinear) on its line grid: a line there is the
    command's, unless only the position shows it (pickup) or it stands ten times above its unexcited neighbours
    (a force that happens to fall on the grid)."""
    T = pb.n / fs
    grid = fs / cmd_info.period if cmd_info.kind == "multisine" and cmd_info.period else 0.0
    excited = set(int(k) for k in cmd_info.excited_lines) if grid else set()
    found = locate.spectral_lines(r * pb.use, fs, pb.noise, ratio=LINE_RATIO, top=12)
    a_res = None
    if check is not None and check.usable and acc_model is not None:
        a_res = acc - check.gain.real * acc_model - np.mean(acc)       # gain phase is ~0 for a real sensor
    R = np.abs(np.fft.rfft(r * pb.use)) if grid else None
    pickup, force = [], []
    for l in found:
        f = locate.refine_line(r * pb.use, fs, l["frequency_hz"])
        k = on_grid(f, grid, T)
        xa, xs = sensor_mod.line_amplitude(r, fs, f, pb.use)
        if a_res is not None:
            aa, asig = sensor_mod.line_amplitude(a_res, fs, f, acc_use)
        else:
            aa, asig = 0j, 0.0
        src, ratio, ev = sensor_mod.classify_line(f, xa, xs, aa, asig, check or sensor_mod.AccelCheck(False))
        if k is not None and k in excited and (not src.startswith("pickup") or not sensor_mod.mains_harmonic(f)):
            continue            # the command's own line: its model error (both sensors see it)
        if k is not None and src == "force":
            near = [j for j in range(max(1, k - int(5 / grid)), k + int(5 / grid) + 1)
                    if j != k and j not in excited]
            idx = [int(round(j * grid * T)) for j in near if int(round(j * grid * T)) < len(R)]
            ref = float(np.median(R[idx])) if idx else 0.0
            if R[int(round(f * T))] < 10 * ref:
                continue                         # one of the distortion lines of the periodic command
        line = sensor_mod.SensorLine(frequency_hz=f, amplitude=abs(xa), phase_rad=float(np.angle(xa)),
                                     channel="position_m", source=src, accel_ratio=ratio, evidence=ev)
        (force if src == "force" else pickup).append(line)
    acc_lines = []
    if a_res is not None:
        an = noise_mod.floor(a_res, fs, acc_use)
        for l in locate.spectral_lines(a_res * acc_use, fs, an.white_rms_m, ratio=LINE_RATIO, top=6):
            f = locate.refine_line(a_res * acc_use, fs, l["frequency_hz"])
            if any(abs(f - x.frequency_hz) < 2.0 / T for x in pickup + force):
                continue
            if on_grid(f, grid, T) is not None and not sensor_mod.mains_harmonic(f):
                continue
            aa, asig = sensor_mod.line_amplitude(a_res, fs, f, acc_use)
            xa, xs = sensor_mod.line_amplitude(r, fs, f, pb.use)
            x_pred = abs(aa) / ((2 * math.pi * f) ** 2 * abs(check.gain))
            if x_pred > 5 * xs and abs(xa) < 0.2 * x_pred:
                acc_lines.append(sensor_mod.SensorLine(
                    frequency_hz=f, amplitude=abs(aa), phase_rad=float(np.angle(aa)), channel="accel_mps2",
                    source="pickup", accel_ratio=None,
                    evidence=f"line in acceleration ({abs(aa):.3g} m/s^2) but not in position: a force would move "
                             f"the position by {x_pred:.3g} m, it shows {abs(xa):.3g} m (noise {xs:.2g})"))
    return pickup, force, acc_lines

"""The data behind each claim, in the domain where a person can check it (report.md plots them):

  gain by level          a repeated command at several levels: the measured gain of each repetition relative to
                         the linear refit (saturation loses gain at the top level, the deadband at the bottom, a
                         linear effect is the same at every level), and what the augmented model predicts
  residual by command    single level: refit residual rms against |command|
  residual by velocity   the mean refit residual against the piston velocity (friction: a step at v = 0)
  phase / magnitude      FRF of the measurement over the augmented model without the effect (delay: phase
                         -w tau; stand mode: a resonance/antiresonance pair)
  two sensors            position and acceleration spectra around a line, with what a force would show
  zero                   the measured position minus the physics, smoothed, and the fitted offset/drift/wander
  quantisation           the residual's histogram against the converter step
Each entry also carries its one-line finding.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.signal import csd, welch

from rig.diagnose import catalogue, locate


def _decimate_for_plot(t: np.ndarray, x: np.ndarray, fs: float, win_s: float = 0.5, max_pts: int = 2000):
    k = max(1, int(win_s * fs))
    m = len(x) // k
    if m < 2:
        return t, x
    xs = x[: m * k].reshape(m, k).mean(axis=1)
    ts = t[: m * k].reshape(m, k).mean(axis=1)
    step = max(1, m // max_pts)
    return ts[::step], xs[::step]


def gain_by_level(pb, cmd_info, y_clean: np.ndarray, y_lin: np.ndarray, y_aug: np.ndarray) -> dict:
    """Least-squares gain of the measurement (and of the augmented model) on the linear refit, per repetition."""
    rows = []
    for s in cmd_info.segments:
        m = np.zeros(pb.n, bool)
        m[s.i0:s.i1] = True
        m &= pb.use
        if m.sum() < 10:
            continue
        ref = y_lin[m] - y_lin[m].mean()
        den = float(np.dot(ref, ref)) or 1e-300
        g_meas = float(np.dot(y_clean[m] - y_clean[m].mean(), ref) / den)
        g_aug = float(np.dot(y_aug[m] - y_aug[m].mean(), ref) / den)
        rows.append({"t0_s": s.i0 / pb.fs, "t1_s": s.i1 / pb.fs, "peak_V": s.peak_V, "gain_measured": g_meas,
                     "gain_augmented": g_aug})
    if len(rows) < 2:
        return {}
    g = np.array([r["gain_measured"] for r in rows])
    lv = np.array([r["peak_V"] for r in rows])
    lo, hi = g[np.argmin(lv)], g[np.argmax(lv)]
    spread = float(np.max(g) - np.min(g))
    if spread < 0.01:
        finding = f"the gain is the same at every level (within {100 * spread:.1f} %): a linear effect"
    elif hi < lo - 0.005 and hi <= np.min(g) + 1e-9:
        finding = (f"the gain drops at the top level ({hi:.3f} vs {lo:.3f} at the bottom): the valve saturates "
                   f"at large command")
    elif lo < hi - 0.005 and lo <= np.min(g) + 1e-9:
        finding = (f"the gain drops at the bottom level ({lo:.3f} vs {hi:.3f} at the top): small commands lose "
                   f"flow (deadband-like)")
    else:
        finding = f"the gain varies by {100 * spread:.1f} % between levels"
    return {"rows": rows, "finding": finding}


def _binned(x: np.ndarray, y: np.ndarray, edges: np.ndarray, fn) -> tuple[np.ndarray, np.ndarray]:
    idx = np.digitize(x, edges) - 1
    c, v = [], []
    for i in range(len(edges) - 1):
        sel = idx == i
        if sel.sum() >= 20:
            c.append(0.5 * (edges[i] + edges[i + 1]))
            v.append(fn(y[sel]))
    return np.array(c), np.array(v)


def residual_by_command(pb, r_ref: np.ndarray, r_aug: np.ndarray) -> dict:
    a = np.abs(pb.cmd)
    peak = float(np.max(a)) or 1.0
    edges = np.linspace(0, peak * 1.0001, 11)
    u = pb.use
    c, v_ref = _binned(a[u], r_ref[u], edges, lambda z: float(np.sqrt(np.mean(z ** 2))))
    _, v_aug = _binned(a[u], r_aug[u], edges, lambda z: float(np.sqrt(np.mean(z ** 2))))
    if len(c) < 3:
        return {}
    top, bottom = v_ref[-1], v_ref[0]
    where = "large" if top > bottom else "small"
    finding = (f"the refit residual is {max(top, bottom) / max(min(top, bottom), 1e-300):.1f}x larger at {where} "
               f"command ({top / pb.noise:.1f}x noise at the top, {bottom / pb.noise:.1f}x at the bottom); the "
               f"augmented model brings it to {np.max(v_aug) / pb.noise:.2f}x noise or less")
    return {"command_V": c, "refit_rms_m": v_ref, "augmented_rms_m": v_aug, "noise_m": pb.noise,
            "finding": finding}


def distortion(pb, cmd_info, r_ref: np.ndarray, r_aug: np.ndarray, noise_floor) -> dict:
    """Nonlinear distortion before and after the augmented model: harmonics of a sweep's phase (orders 2-5), or
    a multisine's unexcited odd and even lines, over the noise."""
    if cmd_info.kind == "sweep" and cmd_info.phase is not None:
        h = [locate.harmonics(r * pb.use, cmd_info.phase, pb.fs, pb.noise) for r in (r_ref, r_aug)]
        orders = ["2", "3", "4", "5"]
        ref = [h[0][o]["over_noise"] for o in orders]
        aug = [h[1][o]["over_noise"] for o in orders]
        odd, even = max(ref[1], ref[3]), max(ref[0], ref[2])
        return {"kind": "harmonics", "labels": [f"order {o}" for o in orders], "refit": ref, "augmented": aug,
                "finding": f"harmonics of the sweep in the refit residual: odd orders up to {odd:.1f}x noise, even "
                           f"up to {even:.1f}x ({'odd' if odd > even else 'even'} distortion); after the augmented "
                           f"model up to {max(aug):.1f}x"}
    if cmd_info.kind == "multisine":
        m = [locate.multisine_lines(cmd_info, r, pb.use, noise_floor, []) for r in (r_ref, r_aug)]
        if not m[0]:
            return {}
        ref = [m[0]["odd_over_noise"] or 0.0, m[0]["even_over_noise"] or 0.0]
        aug = [m[1]["odd_over_noise"] or 0.0, m[1]["even_over_noise"] or 0.0]
        return {"kind": "harmonics", "labels": ["unexcited odd lines", "even lines"], "refit": ref, "augmented": aug,
                "finding": f"the multisine's unexcited odd lines hold {ref[0]:.2f}x the noise in the refit residual "
                           f"({m[0]['odd_z']:.0f} standard errors above noise alone), its even lines {ref[1]:.2f}x: "
                           f"{'odd' if (m[0]['odd_z'] or 0) > (m[0]['even_z'] or 0) else 'even'} distortion; after "
                           f"the augmented model {aug[0]:.2f}x and {aug[1]:.2f}x"}
    return {}


def _length(x_m: float, sign: str = "") -> str:
    """A length in the unit that keeps it readable (nm, um or mm)."""
    for unit, scale in (("nm", 1e9), ("um", 1e6)):
        if abs(x_m) * scale < 1000.0:
            return f"{x_m * scale:{sign}.3g} {unit}"
    return f"{x_m * 1e3:{sign}.3g} mm"


def residual_by_velocity(pb, y_lin: np.ndarray, r_ref: np.ndarray, r_aug: np.ndarray) -> dict:
    v = np.gradient(y_lin) * pb.fs
    u = pb.use
    vmax = float(np.percentile(np.abs(v[u]), 99)) or 1.0
    edges = np.linspace(-vmax, vmax, 25)
    c, m_ref = _binned(v[u], r_ref[u], edges, lambda z: float(np.mean(z)))
    _, m_aug = _binned(v[u], r_aug[u], edges, lambda z: float(np.mean(z)))
    if len(c) < 4:
        return {}
    slow_ = np.abs(c) < 0.3 * vmax                      # friction shows at low velocity
    neg, pos = m_ref[(c < 0) & slow_], m_ref[(c > 0) & slow_]
    step = float(np.mean(neg) - np.mean(pos)) if len(neg) and len(pos) else 0.0
    mover = "the piston" if pb.plant.family == "eha" else "the load"
    finding = (f"at low velocity the refit residual averages {_length(np.mean(neg), '+')} while {mover} moves "
               f"down and {_length(np.mean(pos), '+')} while it moves up: a step of {_length(abs(step))} "
               f"({abs(step) / pb.noise:.1f}x noise) at the velocity reversal, which the augmented model removes"
               if len(neg) and len(pos) else "no velocity range to compare")
    return {"velocity_mps": c, "refit_mean_m": m_ref, "augmented_mean_m": m_aug, "noise_m": pb.noise,
            "finding": finding}


def frf_ratio(pb, y_clean: np.ndarray, y_without: np.ndarray, y_aug: np.ndarray, band) -> dict:
    """Measured / model-without-the-effect and augmented / model-without-the-effect, band-averaged."""
    u = pb.use
    fr = locate.frf_bands(pb.cmd * u, y_clean * u, {"without": y_without * u, "augmented": y_aug * u}, pb.fs, *band,
                   n_bands=60)
    if len(fr["freqs_hz"]) < 3:
        return {}
    with np.errstate(divide="ignore", invalid="ignore"):
        meas = fr["measured"] / fr["without"]
        aug = fr["augmented"] / fr["without"]
    return {"freqs_hz": fr["freqs_hz"], "measured": meas, "augmented": aug,
            "sigma": fr["sigma"] / np.abs(fr["without"])}


def line_spectra(pb, r_pos: np.ndarray, acc_res: np.ndarray | None, f_hz: float, gain: complex,
                 acc_use: np.ndarray, half_width_hz: float = 2.0) -> dict:
    """Amplitude spectra of the position and the acceleration residuals around f_hz (Hann, whole record), and
    the acceleration a force would give: (2 pi f)^2 x position."""
    n = pb.n
    w = np.hanning(n)
    cg = w.sum() / 2.0
    f = np.fft.rfftfreq(n, 1.0 / pb.fs)
    sel = (f > f_hz - half_width_hz) & (f < f_hz + half_width_hz)
    X = np.abs(np.fft.rfft(r_pos * pb.use * w))[sel] / cg
    out = {"freqs_hz": f[sel], "position_m": X, "line_hz": f_hz}
    if acc_res is not None:
        A = np.abs(np.fft.rfft(acc_res * acc_use * w))[sel] / cg
        out["accel_mps2"] = A
        out["force_prediction_mps2"] = X * (2 * math.pi * f[sel]) ** 2 * abs(gain)
    return out


def signature_line(e, mismatch) -> str:
    """What a named effect's data show (its definition's signature), with the distortion the command's structure
    measured for a nonlinear one and the two-sensor finding for a line."""
    effect = catalogue.get(e.name)
    sig = effect.evidence.signature
    h = mismatch.harmonics or {}
    ms = mismatch.multisine_lines or {}
    if effect.nonlinear and h:
        sig += f"; odd harmonics {h.get('odd_over_noise', 0):.0f}x noise, even {h.get('even_over_noise', 0):.0f}x"
    if effect.nonlinear and ms and ms.get("odd_over_noise") is not None:
        sig += (f"; unexcited odd lines of the multisine {ms['odd_over_noise']:.2f}x noise rms ({ms['odd_z']:.0f} "
                f"standard errors above noise alone), even lines {ms.get('even_over_noise') or 0:.2f}x: odd "
                f"distortion" if (ms.get("odd_z") or 0) > 5 else "")
    if e.line_evidence:
        sig += f"; {e.line_evidence}"
    return sig


def collect(pb, cmd_info, refit, augmented, effects, mismatch, sensor, acc: np.ndarray, acc_use: np.ndarray,
            check, acc_model: np.ndarray | None, noise_floor) -> dict:
    """Plot data and a one-line finding for each named effect and each sensor term."""
    ev: dict = {"effects": {}, "sensor": {}}
    B = pb.basis.B
    y_clean = pb.y - B @ augmented.coef                       # the measurement without its sensor terms
    y_lin = pb.physics(refit)
    y_aug = pb.physics(augmented)
    r_ref = pb.y - pb.series(refit)
    r_aug = pb.y - pb.series(augmented)
    band = cmd_info.band_hz if cmd_info.band_hz[1] > 0 else (1.0, 0.45 * pb.fs)
    lv = gain_by_level(pb, cmd_info, y_clean, y_lin, y_aug) if cmd_info.multilevel else {}
    if lv:
        ev["levels"] = lv
    for e in effects:
        name = e.name
        effect = catalogue.get(name)
        kind = effect.evidence.kind
        if kind == "amplitude":
            # several levels: gain by level; one level: the distortion the sweep or multisine shows; else the
            # residual by command magnitude
            ev["effects"][name] = ({"kind": "levels", **lv} if lv else
                                   distortion(pb, cmd_info, r_ref, r_aug, noise_floor)
                                   or {"kind": "command", **residual_by_command(pb, r_ref, r_aug)})
        elif kind == "velocity":
            ev["effects"][name] = {"kind": "velocity", **residual_by_velocity(pb, y_lin, r_ref, r_aug)}
        elif kind == "frf":
            fx = {k: v for k, v in catalogue.simulated(augmented.fx).items() if k != name}
            y_wo = pb.model(augmented.lin, fx)
            fr = frf_ratio(pb, y_clean - (y_aug - pb.model(augmented.lin, augmented.fx)), y_wo,
                           pb.model(augmented.lin, augmented.fx), band)
            if fr:
                fr["finding"] = effect.evidence.finding(e.parameters, band)
            ev["effects"][name] = {"kind": "frf", "effect": name, **fr}
        elif kind == "line":
            f = e.parameters.get("frequency_hz", 0.0)
            a_res = acc - check.gain.real * acc_model - np.mean(acc) if (check is not None and check.usable
                                                                        and acc_model is not None) else None
            r_pos = pb.y - pb.series(augmented) + (y_aug - pb.model(augmented.lin, augmented.fx))
            ls = line_spectra(pb, r_pos, a_res, f, check.gain if check is not None else 1.0, acc_use)
            ls["finding"] = signature_line(e, mismatch)
            ev["effects"][name] = {"kind": "line", **ls}
    ev["sensor"] = sensor_evidence(pb, augmented, sensor, acc, acc_use, check, acc_model, y_aug, r_aug, band)
    return ev


def sensor_evidence(pb, augmented, sensor, acc: np.ndarray, acc_use: np.ndarray, check,
                    acc_model: np.ndarray | None, y_aug: np.ndarray, r_aug: np.ndarray, band) -> dict:
    """Plot data and a one-line finding for each sensor term: the zero line, each pickup line in both sensors,
    the converter step, the accelerometer against the position, clipped samples."""
    out: dict = {}
    B = pb.basis.B
    t = pb.t
    zero = pb.basis.zero(augmented.coef)
    ts, xs = _decimate_for_plot(t[pb.use], (pb.y - y_aug - (B @ augmented.coef - zero))[pb.use], pb.fs)
    out["offset and drift"] = {"kind": "zero", "t_s": ts, "measured_minus_physics_m": xs,
                                        "t_fit_s": t[::max(1, pb.n // 2000)],
                            "zero_m": zero[::max(1, pb.n // 2000)],
                            "finding": (f"the measured position minus the physics follows a zero line: offset "
                                        f"{sensor.offset_m * 1e6:.3g} um at t = 0, drift "
                                        f"{sensor.drift_m_per_s * 1e9:.3g} nm/s"
                                        + (f", slow wander {sensor.wander_rms_m * 1e9:.3g} nm rms "
                                           f"({sensor.wander_terms} cosines)" if sensor.wander_terms else ""))}
    a_res = None
    if check is not None and check.usable and acc_model is not None:
        a_res = acc - check.gain.real * acc_model - np.mean(acc)
    for l in sensor.lines:
        r_pos = r_aug
        if l.channel == "position_m" and l.frequency_hz in pb.basis.lines_hz:     # put the fitted line back
            j = pb.basis.n_zero + 2 * pb.basis.lines_hz.index(l.frequency_hz)
            r_pos = r_aug + B[:, j:j + 2] @ augmented.coef[j:j + 2]
        ls = line_spectra(pb, r_pos, a_res, l.frequency_hz, check.gain if check is not None else 1.0, acc_use)
        ls["finding"] = l.evidence
        out[f"{l.source} line at {l.frequency_hz:.2f} Hz on {l.channel}"] = {"kind": "line", **ls}
    if sensor.quantisation_step_m:
        q = sensor.quantisation_step_m
        h, edges = np.histogram(r_aug[pb.use], bins=60)
        out["quantisation"] = {
            "kind": "quantisation", "counts": h, "edges_m": edges, "step_m": q,
            "position_sample": pb.y[: int(min(pb.n, 0.05 * pb.fs) + 1)],
            "finding": (f"the position takes values on a grid of {q:.3g} m: its floor q/sqrt(12) = "
                        f"{q / math.sqrt(12):.3g} m rms is part of the noise ({pb.noise:.3g} m rms)")}
    if check is not None and np.ptp(acc) > 0:
        x = pb.y - B @ augmented.coef
        nper = int(min(pb.n // 4, 2 ** int(math.log2(max(64, 2 * pb.fs)))))
        f, Sxx = welch(x - x.mean(), fs=pb.fs, nperseg=nper)
        _, Sxa = csd(x - x.mean(), acc - acc.mean(), fs=pb.fs, nperseg=nper)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.abs(Sxa / Sxx) / (2 * np.pi * f) ** 2
        sel = (f >= max(1.0, band[0])) & (f <= min(0.4 * pb.fs, max(band[1], 5.0)))
        model_acc = check.gain.real * acc_model if (check.usable and acc_model is not None) else 0.0
        ts, a_off = _decimate_for_plot(t[acc_use], (acc - model_acc)[acc_use], pb.fs)
        out["accelerometer"] = {
            "kind": "accel", "gain": abs(check.gain), "usable": check.usable, "offset_mps2": sensor.accel_offset_mps2,
            "t_s": ts, "accel_minus_model_mps2": a_off, "freqs_hz": f[sel], "ratio": ratio[sel],
            "finding": ((f"accelerometer offset {sensor.accel_offset_mps2:.3g} m/s^2; " + check.note)
                        if sensor.accel_offset_mps2 is not None else check.note)}
    for c in sensor.clipped:
        if c.channel != "position_m":
            continue
        i0 = int(c.first_s * pb.fs)
        sl = slice(max(0, i0 - int(0.1 * pb.fs)), min(pb.n, i0 + int(0.1 * pb.fs)))
        out["clipped position"] = {"kind": "clip", "t_s": t[sl], "measured_m": pb.y[sl],
                                   "model_m": pb.series(augmented)[sl],
                                   "finding": f"the position sits flat at "
                                              f"{c.high if c.high is not None else c.low:.4g} m "
                                              f"while the model goes beyond: {c.samples} samples clipped, left out"}
    return out

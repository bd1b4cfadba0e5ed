"""The figures of a diagnosis (rig.diagnose.report puts them in report.md): the FRF overlay, the residual spectra,
the worst time windows, and one plot per named effect and sensor term from the data behind it
(rig.diagnose.evidence)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rig.diagnose.results import MODELS

COLORS = {"measured": "k", "nominal": "tab:red", "refit": "tab:orange", "augmented": "tab:blue"}


def _new_figure(rows: int, height: float = 3.0, width: float = 9.0):
    from matplotlib.figure import Figure
    fig = Figure(figsize=(width, height * rows), layout="constrained")
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    return fig, axes


def _shade_bands(ax, bands):
    for lo, hi in bands or []:
        ax.axvspan(lo, hi, color="tab:red", alpha=0.08, lw=0)


def _complex(h) -> np.ndarray:
    """An FRF as a complex array, from complex values, {"re": [...], "im": [...]} or [[re, im], ...]."""
    if isinstance(h, dict):
        return np.asarray(h["re"], float) + 1j * np.asarray(h["im"], float)
    a = np.asarray(h)
    if a.dtype.kind != "c" and a.ndim == 2 and a.shape[1] == 2:
        return a[:, 0] + 1j * a[:, 1]
    return a.astype(complex)


def plot_frf(path: Path, diag) -> Path | None:
    """FRF overlay: measured (+-3 sigma) vs nominal, refit, augmented (magnitude, phase) and coherence."""
    frf = diag.frf or {}
    f = frf.get("freqs_hz", frf.get("f_hz"))
    if f is None or frf.get("measured") is None:
        return None
    f = np.asarray(f, float)
    coh = frf.get("coherence")
    fig, axes = _new_figure(3 if coh is not None else 2)
    bands = diag.mismatch.bands_hz
    for key in ("measured",) + MODELS:
        h = frf.get(key)
        if h is None:
            continue
        h = _complex(h)
        lw = 0.8 if key == "measured" else 1.4
        mk = "." if key == "measured" else None
        axes[0].loglog(f, np.abs(h), color=COLORS[key], lw=lw, marker=mk, ms=3, label=key)
        axes[1].semilogx(f, np.degrees(np.unwrap(np.angle(h))), color=COLORS[key], lw=lw, marker=mk, ms=3,
                         label=key)
        if key == "measured" and frf.get("sigma") is not None:
            sg = 3 * np.asarray(frf["sigma"], float)
            axes[0].fill_between(f, np.maximum(np.abs(h) - sg, np.abs(h) * 1e-3), np.abs(h) + sg,
                                 color="0.6", alpha=0.3, lw=0, label="measured +-3 sigma")
    axes[0].set_ylabel("|x_p / v| (m/V)")
    axes[1].set_ylabel("phase (deg)")
    axes[0].legend(loc="lower left", fontsize=8)
    if coh is not None:
        axes[2].semilogx(f, np.asarray(coh, float), color="k", lw=0.8)
        axes[2].set_ylabel("coherence")
        axes[2].set_ylim(0, 1.05)
    for ax in axes:
        _shade_bands(ax, bands)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("frequency (Hz)")
    axes[0].set_title("FRF: measured and models (shaded: mismatch bands)")
    fig.savefig(path, dpi=110)
    return path


def plot_residual_spectra(path: Path, diag, rec) -> Path:
    """Welch spectra of the position residuals of the three models, with the noise floor."""
    from scipy.signal import welch
    fig, axes = _new_figure(1, height=4.0)
    ax = axes[0]
    given = (diag.frf or {}).get("residual_spectra") or {}
    nper = int(min(rec.n, 4 * rec.fs_hz))
    for m in MODELS:
        if given.get(m) is not None and given.get("freqs_hz") is not None:
            f, asd = np.asarray(given["freqs_hz"], float), np.asarray(given[m], float)
        else:
            r = rec.position_m - np.asarray(diag.series[f"{m}_m"], float)
            f, pxx = welch(r, fs=rec.fs_hz, nperseg=nper)
            asd = np.sqrt(pxx)
        ax.semilogy(f, asd, color=COLORS[m], lw=1.0, label=f"measured - {m}")
    floor = given.get("noise_asd") or (diag.noise_m * math.sqrt(2.0 / rec.fs_hz) if diag.noise_m else None)
    if floor:
        ax.axhline(floor, color="0.4", ls="--", lw=1, label=f"noise floor ({diag.noise_m:.2g} m rms)")
    _shade_bands(ax, diag.mismatch.bands_hz)
    ax.set_xlim(0, min(rec.fs_hz / 2, 250.0))
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("residual ASD (m/sqrt(Hz))")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    ax.set_title("Residual spectra")
    fig.savefig(path, dpi=110)
    return path


def worst_windows(diag, rec, k: int = 3, width_s: float = 1.0, zoom_s: float = 0.5) -> list[tuple[float, float]]:
    """The k worst windows of the refit residual (the engine's, else computed), zoomed to zoom_s around the
    largest residual so that the chirp's cycles stay readable."""
    r = rec.position_m - np.asarray(diag.series["refit_m"], float)
    worst = diag.mismatch.worst_windows.get("refit") or []
    win = [(float(w["t0_s"]), float(w["t1_s"])) for w in worst[:k] if "t0_s" in w]
    if win:
        out = []
        for a, b in sorted(win):
            sel = np.flatnonzero((rec.t_s >= a) & (rec.t_s <= b))
            if sel.size == 0:
                continue
            c = float(rec.t_s[sel[np.argmax(np.abs(r[sel]))]])
            lo = max(a, min(c - zoom_s / 2, b - zoom_s))
            out.append((lo, min(b, lo + zoom_s)))
        if out:
            return out
    m = max(1, int(width_s * rec.fs_hz))
    nwin = rec.n // m
    if nwin == 0:
        return [(float(rec.t_s[0]), float(rec.t_s[-1]))]
    rms = np.sqrt(np.mean(r[:nwin * m].reshape(nwin, m) ** 2, axis=1))
    order = np.argsort(rms)[::-1][:k]
    return [(float(rec.t_s[i * m]), float(rec.t_s[min(rec.n - 1, i * m + int(zoom_s * rec.fs_hz))]))
            for i in sorted(order)]


def plot_windows(path: Path, diag, rec, windows) -> Path:
    """Worst time windows: measured and models on top, residual before (refit) and after (augmented) below."""
    from matplotlib.figure import Figure
    n = len(windows)
    fig = Figure(figsize=(4.2 * n, 6.0), layout="constrained")
    axes = fig.subplots(2, n, squeeze=False)
    for j, (a, b) in enumerate(windows):
        sel = (rec.t_s >= a) & (rec.t_s <= b)
        t = rec.t_s[sel]
        top, bot = axes[0, j], axes[1, j]
        top.plot(t, rec.position_m[sel] * 1e6, color="k", lw=0.8, label="measured")
        for m in MODELS:
            top.plot(t, np.asarray(diag.series[f"{m}_m"])[sel] * 1e6, color=COLORS[m], lw=1.0, label=m)
        for m in ("nominal", "refit", "augmented"):
            res = (rec.position_m - np.asarray(diag.series[f"{m}_m"]))[sel] * 1e6
            bot.plot(t, res, color=COLORS[m], lw=0.8, label=f"residual {m}")
        top.set_title(f"{a:.2f}-{b:.2f} s")
        top.set_ylabel("position (um)")
        bot.set_ylabel("residual (um)")
        bot.set_xlabel("time (s)")
        for ax in (top, bot):
            ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    axes[1, 0].legend(fontsize=7)
    fig.savefig(path, dpi=110)
    return path


# ---- evidence plots: one per named effect and per sensor term ------------------------------------------
def _plot_levels(ax, d: dict) -> None:
    rows = d.get("rows") or []
    lv = [r["peak_V"] for r in rows]
    ax.plot(lv, [r["gain_measured"] for r in rows], "ko-", label="measured")
    ax.plot(lv, [r["gain_augmented"] for r in rows], "s--", color=COLORS["augmented"], label="augmented model")
    ax.axhline(1.0, color=COLORS["refit"], lw=1, label="linear refit (same at every level)")
    g = [r["gain_measured"] for r in rows] + [r["gain_augmented"] for r in rows]
    ax.set_ylim(min(0.98, min(g) - 0.005), max(1.02, max(g) + 0.005))        # a 2 % window at least
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_xlabel("command level (peak V)")
    ax.set_ylabel("gain relative to the linear refit")
    ax.legend(fontsize=8)


def _plot_command(ax, d: dict) -> None:
    ax.plot(d["command_V"], np.asarray(d["refit_rms_m"]) * 1e9, "o-", color=COLORS["refit"], label="refit residual")
    ax.plot(d["command_V"], np.asarray(d["augmented_rms_m"]) * 1e9, "s-", color=COLORS["augmented"],
            label="augmented residual")
    ax.axhline(d["noise_m"] * 1e9, color="0.4", ls="--", lw=1, label="noise")
    ax.set_xlabel("|command| (V)")
    ax.set_ylabel("residual rms (nm)")
    ax.legend(fontsize=8)


def _plot_harmonics(ax, d: dict) -> None:
    x = np.arange(len(d["labels"]))
    ax.bar(x - 0.2, d["refit"], width=0.4, color=COLORS["refit"], label="refit residual")
    ax.bar(x + 0.2, d["augmented"], width=0.4, color=COLORS["augmented"], label="augmented residual")
    ax.axhline(1.0, color="0.4", ls="--", lw=1, label="noise")
    ax.set_xticks(x, d["labels"])
    ax.set_ylabel("rms over the noise")
    ax.legend(fontsize=8)


def _plot_velocity(ax, d: dict) -> None:
    v = np.asarray(d["velocity_mps"]) * 1e3
    ax.plot(v, np.asarray(d["refit_mean_m"]) * 1e9, "o-", color=COLORS["refit"], label="refit residual (mean)")
    ax.plot(v, np.asarray(d["augmented_mean_m"]) * 1e9, "s-", color=COLORS["augmented"],
            label="augmented residual (mean)")
    ax.axvline(0.0, color="0.5", lw=0.8)
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("piston velocity (mm/s)")
    ax.set_ylabel("mean residual (nm)")
    ax.legend(fontsize=8)


def _plot_frf_ratio(fig, d: dict) -> None:
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    f = np.asarray(d["freqs_hz"])
    m, a = _complex(d["measured"]), _complex(d["augmented"])
    ax1.semilogx(f, np.abs(m), "k.", label="measured / model without the effect")
    ax1.semilogx(f, np.abs(a), color=COLORS["augmented"], label="augmented / model without the effect")
    ax1.set_ylabel("magnitude ratio")
    ax2.semilogx(f, np.degrees(np.angle(m)), "k.")
    ax2.semilogx(f, np.degrees(np.angle(a)), color=COLORS["augmented"])
    ax2.set_ylabel("phase (deg)")
    ax2.set_xlabel("frequency (Hz)")
    ax1.legend(fontsize=8)


def _plot_line(fig, d: dict) -> None:
    f = np.asarray(d["freqs_hz"])
    has_acc = d.get("accel_mps2") is not None
    axes = fig.subplots(2 if has_acc else 1, 1, sharex=True, squeeze=False)[:, 0]
    axes[0].semilogy(f, np.maximum(np.asarray(d["position_m"]), 1e-15), color="k", lw=0.8)
    axes[0].set_ylabel("position (m)")
    if has_acc:
        axes[1].semilogy(f, np.maximum(np.asarray(d["accel_mps2"]), 1e-12), color="k", lw=0.8, label="measured")
        axes[1].semilogy(f, np.maximum(np.asarray(d["force_prediction_mps2"]), 1e-12), color="tab:red", lw=1.0,
                         ls="--", label="what a force would show: (2 pi f)^2 x position")
        axes[1].set_ylabel("acceleration (m/s^2)")
        axes[1].legend(fontsize=8)
    for ax in axes:
        ax.axvline(d["line_hz"], color="0.6", lw=0.8)
    axes[-1].set_xlabel("frequency (Hz)")


def _plot_zero(ax, d: dict) -> None:
    ax.plot(d["t_s"], np.asarray(d["measured_minus_physics_m"]) * 1e6, ".", color="0.3", ms=2,
            label="measured - physics (0.5 s means)")
    ax.plot(d["t_fit_s"], np.asarray(d["zero_m"]) * 1e6, color="tab:green", lw=1.5, label="fitted zero")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position (um)")
    ax.legend(fontsize=8)


def _plot_quantisation(ax, d: dict) -> None:
    e = np.asarray(d["edges_m"]) * 1e9
    ax.bar(0.5 * (e[:-1] + e[1:]), d["counts"], width=np.diff(e), color="0.6", label="augmented residual")
    q = d["step_m"] * 1e9
    ax.axvspan(-q / 2, q / 2, color="tab:orange", alpha=0.15, label=f"one converter step ({q:.3g} nm)")
    ax.set_xlabel("residual (nm)")
    ax.set_ylabel("samples")
    ax.legend(fontsize=8)


def _plot_accel(fig, d: dict) -> None:
    ax1, ax2 = fig.subplots(2, 1)
    ax1.plot(d["t_s"], np.asarray(d["accel_minus_model_mps2"]) * 1e3, ".", color="0.3", ms=2,
             label="accelerometer - model acceleration (0.5 s means)")
    if d.get("offset_mps2") is not None:
        ax1.axhline(d["offset_mps2"] * 1e3, color="tab:green", label="fitted offset")
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("mm/s^2")
    ax1.legend(fontsize=8)
    ax2.semilogx(d["freqs_hz"], d["ratio"], "k.", ms=3, label="|accel / position| / (2 pi f)^2")
    ax2.axhline(1.0, color="tab:red", lw=1, label="a true second derivative")
    ax2.set_xlabel("frequency (Hz)")
    ax2.set_ylabel("ratio")
    ax2.legend(fontsize=8)


def _plot_clip(ax, d: dict) -> None:
    ax.plot(d["t_s"], np.asarray(d["measured_m"]) * 1e6, "k", lw=0.8, label="measured")
    ax.plot(d["t_s"], np.asarray(d["model_m"]) * 1e6, color=COLORS["augmented"], lw=1.0, label="model")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position (um)")
    ax.legend(fontsize=8)


_EVIDENCE_TITLES = {
    "levels": "gain by command level", "command": "residual by command magnitude",
    "velocity": "residual by piston velocity", "frf": "frequency response over the model without the effect",
    "line": "the line in position and in acceleration", "zero": "the transducer's zero (offset, drift, wander)",
    "quantisation": "residual against the converter step", "clip": "clipped samples",
    "accel": "the accelerometer against the position's second derivative",
    "harmonics": "nonlinear distortion the command's own structure shows",
}


def plot_evidence(out_dir: Path, diag) -> list[tuple[str, str, str]]:
    """One PNG per named effect and sensor term; returns (title, file name, one-line finding)."""
    from matplotlib.figure import Figure
    ev = diag.evidence or {}
    out = []
    items = [(f"effect: {k}", k, v) for k, v in ev.get("effects", {}).items()]
    if ev.get("levels") and not any(v.get("kind") == "levels" for v in ev.get("effects", {}).values()):
        items.append(("command levels", "levels", {"kind": "levels", **ev["levels"]}))
    items += [(f"sensor: {k}", k, v) for k, v in ev.get("sensor", {}).items()]
    for label, key, d in items:
        kind = d.get("kind") or key
        if kind not in _EVIDENCE_TITLES or (kind == "levels" and not d.get("rows")) or \
                (kind in ("command", "velocity", "frf", "harmonics") and len(d) <= 2):
            if d.get("finding"):
                out.append((label, "", d["finding"]))
            continue
        fig = Figure(figsize=(7.5, 4.2 if kind not in ("frf", "line", "accel") else 5.2), layout="constrained")
        if kind == "frf":
            _plot_frf_ratio(fig, d)
        elif kind == "line":
            _plot_line(fig, d)
        elif kind == "accel":
            _plot_accel(fig, d)
        else:
            ax = fig.subplots()
            {"levels": _plot_levels, "command": _plot_command, "velocity": _plot_velocity, "zero": _plot_zero,
             "quantisation": _plot_quantisation, "clip": _plot_clip, "harmonics": _plot_harmonics}[kind](ax, d)
        for ax in fig.axes:
            ax.grid(True, alpha=0.3)
        fig.suptitle(f"{label}: {_EVIDENCE_TITLES[kind]}", fontsize=10)
        name = "evidence_" + "_".join("".join(c if c.isalnum() or c == "." else " " for c in label).split()) + ".png"
        fig.savefig(Path(out_dir) / name, dpi=100)
        out.append((label, name, d.get("finding", "")))
    return out

"""Outputs of a diagnosis (issue 7): DIR/diagnosis.json, DIR/fit.csv, DIR/report.md with its PNGs, and the
readable summary (where the mismatch is, what physics was left out, how much better the fit gets).

The engine (rig.diagnose.engine) decides; this module only writes what it decided, in the issue's schema:
  {"effects": [{"name", "parameters": {...}, "evidence": "...", "score": ...}],
   "mismatch": {"bands_hz": [[lo, hi], ...], "windows_s": [[t0, t1], ...], ...},
   "fit": {"nominal": {"nrmse", ...}, "refit": {...}, "augmented": {...}}, "summary": "..."}
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

MODELS = ("nominal", "refit", "augmented")
FIT_COLUMNS = ("time_s", "measured_m", "nominal_m", "refit_m", "augmented_m")
COLORS = {"measured": "k", "nominal": "tab:red", "refit": "tab:orange", "augmented": "tab:blue"}


# ---- JSON --------------------------------------------------------------------------------------------
def _plain(x):
    """JSON-safe copy: numpy scalars/arrays to Python, non-finite floats to None, complex to [re, im]."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, (complex, np.complexfloating)):
        return [_plain(float(x.real)), _plain(float(x.imag))]
    if x is None or isinstance(x, str):
        return x
    return str(x)


def diagnosis_dict(diag, rec=None) -> dict:
    """The diagnosis.json document (schema of issue 7, plus groups, refit parameters and noise)."""
    effects = [{"name": e["name"], "parameters": dict(e.get("parameters", {})),
                "evidence": str(e.get("evidence", "")), "score": e.get("score")} for e in diag.effects]
    mismatch = dict(diag.mismatch or {})
    mismatch.setdefault("bands_hz", [])
    mismatch.setdefault("windows_s", [])
    fit = {m: dict((diag.fit or {}).get(m, {})) for m in MODELS}
    for m in MODELS:
        fit[m].setdefault("nrmse", None)
    doc = {"effects": effects, "mismatch": mismatch, "fit": fit, "summary": diag.summary,
           "groups": [list(g) for g in (diag.group or [])], "params_refit": dict(diag.params_refit or {}),
           "noise_m": diag.noise_m, "timing_s": getattr(diag, "timing_s", None),
           "candidates": list(getattr(diag, "candidates", None) or [])}     # every test the engine ran
    if rec is not None:
        doc["recording"] = {"source": rec.source, "fs_hz": rec.fs_hz, "samples": rec.n,
                            "duration_s": rec.duration_s}
    return _plain(doc)


# ---- fit.csv -----------------------------------------------------------------------------------------
def fit_columns(diag, rec) -> np.ndarray:
    """(n, 5) array time_s, measured_m, nominal_m, refit_m, augmented_m for every recorded instant."""
    cols = [np.asarray(rec.t_s, float), np.asarray(rec.position_m, float)]
    for m in MODELS:
        s = (diag.series or {}).get(f"{m}_m")
        if s is None:
            raise RuntimeError(f"diagnosis has no {m}_m series")
        s = np.asarray(s, float)
        if s.shape != (rec.n,):
            raise RuntimeError(f"diagnosis {m}_m series has {s.shape} samples, the recording {rec.n}")
        cols.append(s)
    return np.column_stack(cols)


def write_fit_csv(path: Path, diag, rec) -> Path:
    data = fit_columns(diag, rec)
    np.savetxt(path, data, delimiter=",", header=",".join(FIT_COLUMNS), comments="",
               fmt=["%.9f", "%.9g", "%.9g", "%.9g", "%.9g"])
    return path


# ---- text --------------------------------------------------------------------------------------------
_UNITS = {"delay_s": (1e3, "ms"), "frequency_hz": (1.0, "Hz"), "damping_ratio": (1.0, ""),
          "limit_ma": (1.0, "mA"), "width_ma": (1.0, "mA"), "force_n": (1.0, "N"), "phase_rad": (1.0, "rad"),
          "mass_kg": (1.0, "kg"), "amplitude_m": (1e9, "nm")}


def format_parameters(prm: dict) -> str:
    out = []
    for k, v in prm.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            scale, unit = _UNITS.get(k, (1.0, ""))
            name = k.rsplit("_", 1)[0] if k in _UNITS and unit else k
            out.append(f"{name} {v * scale:.4g}{(' ' + unit) if unit else ''}")
        else:
            out.append(f"{k} {v}")
    return ", ".join(out)


def _spans(xs, unit: str, limit: int = 6) -> str:
    xs = list(xs or [])
    if not xs:
        return "none"
    s = ", ".join(f"{a:.4g}-{b:.4g} {unit}" for a, b in xs[:limit])
    return s + (f" (+{len(xs) - limit} more)" if len(xs) > limit else "")


def _figure(v, spec=".4f") -> str:
    return "-" if v is None else format(v, spec)


def _fit_row(fit: dict, m: str) -> dict:
    return (fit or {}).get(m, {}) or {}


def _describe(v, limit: int = 300) -> str:
    """Short text of a mismatch item (dict/list/str) for the summary."""
    if v is None or v == [] or v == {}:
        return "none"
    if isinstance(v, str):
        return v
    if isinstance(v, dict):
        parts = []
        for k, x in v.items():
            if isinstance(x, float):
                parts.append(f"{k} {x:.3g}")
            elif isinstance(x, (dict, list)):
                parts.append(f"{k} {json.dumps(_plain(x))[:80]}")
            else:
                parts.append(f"{k} {x}")
        s = "; ".join(parts)
    else:
        s = json.dumps(_plain(v))
    return s if len(s) <= limit else s[:limit - 3] + "..."


def describe_regimes(reg) -> str:
    if not isinstance(reg, dict) or not reg:
        return _describe(reg)
    parts = []
    for k, v in reg.items():
        if isinstance(v, dict) and "rms_over_noise" in v:
            parts.append(f"{k.replace('_', ' ')} {v['rms_over_noise']:.2g}x noise")
        else:
            parts.append(f"{k} {_describe(v, 60)}")
    return "refit residual " + ", ".join(parts)


def describe_harmonics(h) -> str:
    if not isinstance(h, dict) or "odd_over_noise" not in h:
        return _describe(h)
    orders = ", ".join(f"{k}: {v['over_noise']:.2g}x" for k, v in h.items()
                       if k.isdigit() and isinstance(v, dict) and int(k) > 1)
    return (f"odd orders up to {h['odd_over_noise']:.2g}x noise, even up to {h['even_over_noise']:.2g}x "
            f"(order {orders})")


def describe_uncorrelated(u) -> str:
    if not isinstance(u, dict) or "lines" not in u:
        return _describe(u)
    lines = u.get("lines") or []
    if not lines:
        return "no spectral line outside the command's response"
    s = "lines at " + ", ".join(f"{l['frequency_hz']:.2f} Hz ({l['amplitude_m']:.2g} m)" for l in lines)
    frac = u.get("fraction_of_refit_residual_in_lines")
    if isinstance(frac, (int, float)):
        s += f"; {100 * frac:.0f} % of the refit residual power"
    return s


_DESCRIBE = {"regimes": describe_regimes, "harmonics": describe_harmonics, "uncorrelated": describe_uncorrelated}


def summary_text(diag, rec=None) -> str:
    """The readable summary for stdout: where, what, how much better."""
    mm = diag.mismatch or {}
    lines = []
    if rec is not None:
        lines.append(f"recording {rec.source}: {rec.n} samples at {rec.fs_hz:g} Hz ({rec.duration_s:g} s)")
    lines.append("WHERE the recording and the nominal model differ:")
    lines.append(f"  frequency bands: {_spans(mm.get('bands_hz'), 'Hz')}")
    lines.append(f"  time windows:    {_spans(mm.get('windows_s'), 's')}")
    after = (mm.get("after_refit") or {}).get("bands_hz")
    if after is not None:
        lines.append(f"  after refit:     {_spans(after, 'Hz')}")
    after_aug = (mm.get("after_augmented") or {}).get("bands_hz")
    if after_aug is not None:
        lines.append(f"  after augmented: {_spans(after_aug, 'Hz')}")
    for key in ("regimes", "harmonics", "uncorrelated"):
        if key in mm:
            lines.append(f"  {key + ':':16} {_DESCRIBE[key](mm[key])}")
    lines.append("WHAT physics the linear model leaves out (after refitting its six parameters):")
    if not diag.effects:
        lines.append("  none: the refit linear model explains the recording")
    for e in diag.effects:
        sc = e.get("score")
        sc_s = f" [score {sc:.4g}]" if isinstance(sc, (int, float)) else ""
        lines.append(f"  {e['name']}: {format_parameters(e.get('parameters', {}))}{sc_s}")
        if e.get("evidence"):
            lines.append(f"    evidence: {e['evidence']}")
    for g in diag.group or []:
        lines.append(f"  confounded (cannot be told apart here): {', '.join(g)}")
    lines.append("HOW MUCH BETTER (NRMSE of position; residual rms / noise rms):")
    lines.append(f"  {'model':10} {'NRMSE':>8} {'fit seg':>8} {'held-out':>8} {'resid/noise':>11}")
    for m in MODELS:
        f = _fit_row(diag.fit, m)
        lines.append(f"  {m:10} {_figure(f.get('nrmse')):>8} {_figure(f.get('nrmse_fit')):>8} "
                     f"{_figure(f.get('nrmse_holdout')):>8} {_figure(f.get('residual_over_noise'), '.2f'):>11}")
    nom, aug = _fit_row(diag.fit, "nominal").get("nrmse"), _fit_row(diag.fit, "augmented").get("nrmse")
    if nom and aug is not None and aug > 0:
        lines.append(f"  NRMSE {nom:.4f} -> {aug:.4f} ({nom / aug:.1f}x better than nominal)")
    if diag.summary:
        lines.append(f"summary: {diag.summary}")
    return "\n".join(lines)


# ---- figures -----------------------------------------------------------------------------------------
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
    bands = (diag.mismatch or {}).get("bands_hz")
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
    _shade_bands(ax, (diag.mismatch or {}).get("bands_hz"))
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
    worst = ((diag.mismatch or {}).get("worst_windows") or {}).get("refit") or []
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


# ---- report.md ---------------------------------------------------------------------------------------
def report_markdown(diag, rec, figures: dict[str, str], windows) -> str:
    mm = diag.mismatch or {}
    out = [f"# Diagnosis of {rec.source}", "",
           f"{rec.n} samples at {rec.fs_hz:g} Hz ({rec.duration_s:g} s). Position noise estimate: "
           f"{_figure(diag.noise_m, '.3g')} m rms.", "", f"**Summary:** {diag.summary or '-'}", "",
           "## Where the model and the recording differ", "",
           f"- Frequency bands (FRF error above its coherence-based uncertainty): {_spans(mm.get('bands_hz'), 'Hz', 20)}",
           f"- Time windows: {_spans(mm.get('windows_s'), 's', 20)}"]
    after = (mm.get("after_refit") or {}).get("bands_hz")
    if after is not None:
        out.append(f"- Bands still off after the linear refit: {_spans(after, 'Hz', 20)}")
    after_aug = (mm.get("after_augmented") or {}).get("bands_hz")
    if after_aug is not None:
        out.append(f"- Bands still off after the augmented fit: {_spans(after_aug, 'Hz', 20)}")
    for key in ("regimes", "harmonics", "uncorrelated"):
        if key in mm:
            out.append(f"- {key.capitalize()}: {_DESCRIBE[key](mm[key])}")
    out += ["", "## Physics left out by the linear model", ""]
    if diag.effects:
        out += ["| effect | parameters | score | evidence |", "|---|---|---|---|"]
        for e in diag.effects:
            sc = e.get("score")
            out.append(f"| {e['name']} | {format_parameters(e.get('parameters', {}))} | "
                       f"{_figure(sc, '.4g') if isinstance(sc, (int, float)) else '-'} | "
                       f"{str(e.get('evidence', '')).replace('|', '/')} |")
    else:
        out.append("None: the refit linear model explains the recording.")
    for g in diag.group or []:
        out.append(f"\nConfounded, cannot be told apart on this recording: {', '.join(g)}.")
    out += ["", "## Fit", "", "| model | NRMSE | NRMSE fit segment | NRMSE held-out | residual rms (m) | residual / noise |",
            "|---|---|---|---|---|---|"]
    for m in MODELS:
        f = _fit_row(diag.fit, m)
        out.append(f"| {m} | {_figure(f.get('nrmse'))} | {_figure(f.get('nrmse_fit'))} | "
                   f"{_figure(f.get('nrmse_holdout'))} | {_figure(f.get('residual_rms_m'), '.3g')} | "
                   f"{_figure(f.get('residual_over_noise'), '.2f')} |")
    if diag.params_refit:
        out += ["", "Refit linear parameters: " + ", ".join(f"{k} = {float(v):.4g}" for k, v in
                                                            diag.params_refit.items()
                                                            if isinstance(v, (int, float)))]
    out += ["", "## Figures", ""]
    captions = {"frf": "FRF overlay (measured, nominal, refit, augmented) with coherence",
                "residuals": "Residual spectra of the three models against the noise floor",
                "windows": "Worst time windows: " + ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in windows)
                           + " (residual before = refit, after = augmented)"}
    for key, name in figures.items():
        out += [f"### {captions.get(key, key)}", "", f"![{key}]({name})", ""]
    out += ["Data: `diagnosis.json`, `fit.csv` (time_s, measured_m, nominal_m, refit_m, augmented_m).", ""]
    return "\n".join(out)


def write_outputs(out_dir: Path, diag, rec) -> dict[str, Path]:
    """Write diagnosis.json, fit.csv, report.md and its PNGs into out_dir; returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "diagnosis.json", "csv": out_dir / "fit.csv", "report": out_dir / "report.md"}
    paths["json"].write_text(json.dumps(diagnosis_dict(diag, rec), indent=1))
    write_fit_csv(paths["csv"], diag, rec)
    figures: dict[str, str] = {}
    if plot_frf(out_dir / "frf.png", diag) is not None:
        figures["frf"] = "frf.png"
    plot_residual_spectra(out_dir / "residual_spectra.png", diag, rec)
    figures["residuals"] = "residual_spectra.png"
    windows = worst_windows(diag, rec)
    plot_windows(out_dir / "worst_windows.png", diag, rec, windows)
    figures["windows"] = "worst_windows.png"
    paths["report"].write_text(report_markdown(diag, rec, figures, windows))
    for key, name in figures.items():
        paths[key] = out_dir / name
    return paths

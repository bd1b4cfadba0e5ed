"""Outputs of a diagnosis (issues 7 and 12): DIR/diagnosis.json, DIR/fit.csv, DIR/report.md with its PNGs, and
the readable summary (where the mismatch is, what physics was left out, what the sensors added, how much better
the fit gets).

The engine (rig.diagnose.engine) decides; this module only writes what it decided, in the issues' schema:
  {"effects": [{"name", "parameters": {...}, "evidence": "...", "score": ...}],
   "mismatch": {"bands_hz": [[lo, hi], ...], "windows_s": [[t0, t1], ...], ...},
   "fit": {"nominal": {"nrmse", ...}, "refit": {...}, "augmented": {...}}, "summary": "...",
   "sensor": {"offset_m", "drift_m_per_s", "lines": [{"frequency_hz", "amplitude_m", ...}], ...},
   "verdict": {"status": explained | partly | not_described | no_claim, "text", "suggestions"},
   "command": {"kind", "description", "band_hz", ...}}
fit.csv models the measurement as recorded: each model column is physics plus that model's fitted sensor terms, so
measured_m - augmented_m is the noise where used = 1 (used = 0: clipped or start-transient samples, left out).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from rig.diagnose import catalogue

MODELS = ("nominal", "refit", "augmented")
FIT_COLUMNS = ("time_s", "measured_m", "nominal_m", "refit_m", "augmented_m", "augmented_sensor_m", "used")
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
    if getattr(diag, "plant", None):
        doc["plant"] = dict(diag.plant)
    sensor = getattr(diag, "sensor", None)
    if sensor is not None:
        doc["sensor"] = sensor.as_dict()
    verdict = getattr(diag, "verdict", None)
    if verdict is not None:
        doc["verdict"] = verdict.as_dict()
    cmd = getattr(diag, "command", None)
    if cmd is not None:
        doc["command"] = {"kind": cmd.kind, "description": cmd.describe(), "band_hz": list(cmd.band_hz),
                          "peak_V": cmd.peak_V, "levels_V": [sg.peak_V for sg in cmd.segments] if cmd.multilevel
                          else None, "period_s": cmd.period / cmd.fs_hz if cmd.period else None}
    ev = getattr(diag, "evidence", None) or {}
    if ev:
        doc["evidence"] = {"effects": {k: v.get("finding", "") for k, v in ev.get("effects", {}).items()},
                           "sensor": {k: v.get("finding", "") for k, v in ev.get("sensor", {}).items()}}
        if "levels" in ev:
            doc["evidence"]["gain_by_level"] = ev["levels"]["rows"]
    if rec is not None:
        doc["recording"] = {"source": rec.source, "fs_hz": rec.fs_hz, "samples": rec.n,
                            "duration_s": rec.duration_s}
    return _plain(doc)


# ---- fit.csv -----------------------------------------------------------------------------------------
def fit_columns(diag, rec) -> np.ndarray:
    """(n, 7) array of FIT_COLUMNS for every recorded instant."""
    cols = [np.asarray(rec.t_s, float), np.asarray(rec.position_m, float)]
    for m in MODELS + ("augmented_sensor",):
        s = (diag.series or {}).get(f"{m}_m")
        if s is None:
            if m == "augmented_sensor":
                s = np.zeros(rec.n)
            else:
                raise RuntimeError(f"diagnosis has no {m}_m series")
        s = np.asarray(s, float)
        if s.shape != (rec.n,):
            raise RuntimeError(f"diagnosis {m}_m series has {s.shape} samples, the recording {rec.n}")
        cols.append(s)
    used = getattr(diag, "used", None)
    cols.append(np.ones(rec.n) if used is None else np.asarray(used, float))
    return np.column_stack(cols)


def write_fit_csv(path: Path, diag, rec) -> Path:
    data = fit_columns(diag, rec)
    np.savetxt(path, data, delimiter=",", header=",".join(FIT_COLUMNS), comments="",
               fmt=["%.9f", "%.9g", "%.9g", "%.9g", "%.9g", "%.9g", "%d"])
    return path


# ---- text --------------------------------------------------------------------------------------------
_UNITS = catalogue.display_units()      # parameter key -> (scale, unit), from the effects' definitions


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
    cmd = getattr(diag, "command", None)
    if cmd is not None:
        lines.insert(1 if rec is not None else 0, f"command: {cmd.describe()}")
    for note in (diag.mismatch or {}).get("notes", [])[1:]:
        lines.append(f"  note: {note}")
    pl = getattr(diag, "plant", None) or {}
    free = pl.get("free_parameters") if pl.get("family", "eha") != "eha" else None
    refitted = ("its six parameters" if free is None else
                f"its free parameters {', '.join(free)}" if free else "nothing: every parameter is fixed")
    lines.append(f"WHAT physics the linear model leaves out (after refitting {refitted}):")
    verdict = getattr(diag, "verdict", None)
    if not diag.effects:
        if verdict is not None and verdict.status != "explained":
            lines.append(f"  none named: {verdict.text}")
        else:
            lines.append("  none: the refit linear model explains the recording")
    for e in diag.effects:
        sc = e.get("score")
        sc_s = f" [score {sc:.4g}]" if isinstance(sc, (int, float)) else ""
        lines.append(f"  {e['name']}: {format_parameters(e.get('parameters', {}))}{sc_s}")
        if e.get("evidence"):
            lines.append(f"    evidence: {e['evidence']}")
    for g in diag.group or []:
        lines.append(f"  confounded (cannot be told apart here): {', '.join(g)}")
    sensor = getattr(diag, "sensor", None)
    if sensor is not None:
        lines.append("SENSOR terms (fitted in every model, not physics):")
        lines += [f"  {t}" for t in sensor_lines(sensor)]
    lines.append("HOW MUCH BETTER (NRMSE of position; residual rms / noise rms):")
    lines.append(f"  {'':10} {'NRMSE':-^26} {'resid/noise':-^17}")
    lines.append(f"  {'model':10} {'whole':>8} {'fit seg':>8} {'held-out':>8} {'whole':>8} {'held-out':>8}")
    for m in MODELS:
        f = _fit_row(diag.fit, m)
        lines.append(f"  {m:10} {_figure(f.get('nrmse')):>8} {_figure(f.get('nrmse_fit')):>8} "
                     f"{_figure(f.get('nrmse_holdout')):>8} {_figure(f.get('residual_over_noise'), '.2f'):>8} "
                     f"{_figure(f.get('residual_over_noise_holdout'), '.2f'):>8}")
    nom, aug = _fit_row(diag.fit, "nominal").get("nrmse"), _fit_row(diag.fit, "augmented").get("nrmse")
    if nom and aug is not None and aug > 0:
        lines.append(f"  NRMSE {nom:.4f} -> {aug:.4f} ({nom / aug:.1f}x better than nominal)")
    if verdict is not None:
        lines.append(f"VERDICT: {verdict.text}")
        for sg in verdict.suggestions:
            lines.append(f"  {sg}")
    if diag.summary:
        lines.append(f"summary: {diag.summary}")
    return "\n".join(lines)


def sensor_lines(sensor) -> list[str]:
    """The sensor terms as readable lines (stdout and report.md)."""
    out = [f"position offset {sensor.offset_m * 1e6:.4g} um at t = 0, drift {sensor.drift_m_per_s * 1e9:.4g} nm/s"
           + (f", slow wander {sensor.wander_rms_m * 1e9:.3g} nm rms ({sensor.wander_terms} cosines)"
              if sensor.wander_terms else "")]
    for l in sensor.lines:
        amp = f"{l.amplitude * 1e9:.3g} nm" if l.channel == "position_m" else f"{l.amplitude:.3g} m/s^2"
        out.append(f"{l.source} line on {l.channel} at {l.frequency_hz:.3f} Hz, {amp}: {l.evidence}")
    if sensor.quantisation_step_m:
        out.append(f"position quantised in steps of {sensor.quantisation_step_m:.3g} m (floor "
                   f"{sensor.quantisation_step_m / math.sqrt(12):.3g} m rms)")
    if sensor.accel_quantisation_step_mps2:
        out.append(f"acceleration quantised in steps of {sensor.accel_quantisation_step_mps2:.3g} m/s^2")
    if sensor.accel_offset_mps2 is not None:
        out.append(f"accelerometer offset {sensor.accel_offset_mps2:.4g} m/s^2")
    if sensor.accel is not None and sensor.accel.note:
        out.append(sensor.accel.note)
    for c in sensor.clipped:
        lvl = c.high if c.high is not None else c.low
        out.append(f"{c.channel} clipped at {lvl:.4g} ({c.samples} samples from {c.first_s:.3f} s): left out of "
                   "the fit")
    if sensor.start_transient_s:
        out.append(f"mid-run start: the first {sensor.start_transient_s:g} s are left out (start transient)")
    return out


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
    ev = getattr(diag, "evidence", None) or {}
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


# ---- report.md ---------------------------------------------------------------------------------------
def report_markdown(diag, rec, figures: dict[str, str], windows, evidence=()) -> str:
    """report.md: the verdict, where model and recording differ, the physics named, the sensor terms, the
    evidence, the fit table and the figures, one section function each."""
    mm = diag.mismatch or {}
    verdict = getattr(diag, "verdict", None)
    out = _report_head(diag, rec, mm, verdict)
    out += _report_mismatch(diag, mm)
    out += _report_effects(diag, mm, verdict)
    out += _report_sensor_and_evidence(diag, evidence)
    out += _report_fit(diag)
    out += _report_figures(figures, windows)
    return "\n".join(out)


def _report_head(diag, rec, mm: dict, verdict) -> list[str]:
    """Title, the recording in one line, the verdict with its suggestions, the command and the notes."""
    cmd = getattr(diag, "command", None)
    out = [f"# Diagnosis of {rec.source}", "",
           f"{rec.n} samples at {rec.fs_hz:g} Hz ({rec.duration_s:g} s). Position noise estimate: "
           f"{_figure(diag.noise_m, '.3g')} m rms.", ""]
    if verdict is not None:
        out += [f"**Verdict ({verdict.status.replace('_', ' ')}):** {verdict.text}", ""]
        out += [f"- {sg}" for sg in verdict.suggestions] + ([""] if verdict.suggestions else [])
    if cmd is not None:
        out += [f"Command: {cmd.describe()}.", ""]
    for note in mm.get("notes", [])[1:]:
        out += [f"Note: {note}.", ""]
    return out


def _report_mismatch(diag, mm: dict) -> list[str]:
    """The summary and the bands, windows and patterns where the model and the recording differ."""
    out = [f"**Summary:** {diag.summary or '-'}", "", "## Where the model and the recording differ", "",
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
    return out


def _report_effects(diag, mm: dict, verdict) -> list[str]:
    """The effects named (or why none), the confounded groups and a non-eha plant's augmented parameters."""
    out = ["", "## Physics left out by the linear model", ""]
    if diag.effects:
        out += ["| effect | parameters | score | evidence |", "|---|---|---|---|"]
        for e in diag.effects:
            sc = e.get("score")
            out.append(f"| {e['name']} | {format_parameters(e.get('parameters', {}))} | "
                       f"{_figure(sc, '.4g') if isinstance(sc, (int, float)) else '-'} | "
                       f"{str(e.get('evidence', '')).replace('|', '/')} |")
    else:
        if verdict is not None and verdict.status != "explained":
            out.append(f"None named. {verdict.text}")
            for nc in mm.get("not_claimed", []):
                out.append(f"- best candidate, not claimed: {nc['name']} ({format_parameters(nc['parameters'])})")
        else:
            out.append("None: the refit linear model explains the recording.")
    for g in diag.group or []:
        out.append(f"\nConfounded, cannot be told apart on this recording: {', '.join(g)}.")
    pl = getattr(diag, "plant", None) or {}
    if pl.get("family") and pl["family"] != "eha":
        out.append(f"\nPlant: {pl['family']} (input in {pl['input_unit']}), augmented linear parameters "
                   + ", ".join(f"{k} = {v:.4g}" for k, v in pl.get("augmented_linear", {}).items())
                   + (f"; simulated in {pl['shooting']['segments']} segments from their own initial states "
                      "(multiple shooting)" if "shooting" in pl else "") + ".")
    return out


def _report_sensor_and_evidence(diag, evidence) -> list[str]:
    """The fitted sensor terms, and each evidence figure with its finding."""
    out = []
    sensor = getattr(diag, "sensor", None)
    if sensor is not None:
        out += ["", "## Sensor terms (fitted in every model, never named as effects)", ""]
        out += [f"- {t}" for t in sensor_lines(sensor)]
    if evidence:
        out += ["", "## Evidence: what convinced the tool", ""]
        for label, name, finding in evidence:
            out += [f"### {label}", "", f"{finding[:1].upper() + finding[1:] if finding else '-'}", ""]
            if name:
                out += [f"![{label}]({name})", ""]
    return out


def _report_fit(diag) -> list[str]:
    """The three models' fit figures and the refit linear parameters."""
    out = ["", "## Fit", "",
           "| model | NRMSE | NRMSE fit segment | NRMSE held-out | residual rms (m) | residual / noise "
           "| residual / noise held-out |", "|---|---|---|---|---|---|---|"]
    for m in MODELS:
        f = _fit_row(diag.fit, m)
        out.append(f"| {m} | {_figure(f.get('nrmse'))} | {_figure(f.get('nrmse_fit'))} | "
                   f"{_figure(f.get('nrmse_holdout'))} | {_figure(f.get('residual_rms_m'), '.3g')} | "
                   f"{_figure(f.get('residual_over_noise'), '.2f')} | "
                   f"{_figure(f.get('residual_over_noise_holdout'), '.2f')} |")
    if diag.params_refit:
        out += ["", "Refit linear parameters: " + ", ".join(f"{k} = {float(v):.4g}" for k, v in
                                                            diag.params_refit.items()
                                                            if isinstance(v, (int, float)))]
    return out


def _report_figures(figures: dict[str, str], windows) -> list[str]:
    """The figures with their captions, and what the data files hold."""
    out = ["", "## Figures", ""]
    captions = {"frf": "FRF overlay (measured, nominal, refit, augmented) with coherence",
                "residuals": "Residual spectra of the three models against the noise floor",
                "windows": "Worst time windows: " + ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in windows)
                           + " (residual before = refit, after = augmented)"}
    for key, name in figures.items():
        out += [f"### {captions.get(key, key)}", "", f"![{key}]({name})", ""]
    out += ["Data: `diagnosis.json`, `fit.csv` (time_s, measured_m, nominal_m, refit_m, augmented_m, "
            "augmented_sensor_m, used): each model column is the measurement as the model has it, physics plus "
            "its sensor terms, so measured_m - augmented_m is the noise where used = 1.", ""]
    return out


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
    evidence = plot_evidence(out_dir, diag)
    paths["report"].write_text(report_markdown(diag, rec, figures, windows, evidence))
    for key, name in figures.items():
        paths[key] = out_dir / name
    for label, name, _ in evidence:
        if name:
            paths[name[:-4]] = out_dir / name
    return paths

"""Outputs of a diagnosis (issues 7 and 12): DIR/diagnosis.json, DIR/fit.csv, DIR/report.md with its PNGs, and
the readable summary (where the mismatch is, what physics was left out, what the sensors added, how much better
the fit gets).

The engine (rig.diagnose.engine) decides; this module only writes what it decided, in the issues' schema:
  {"effects": [{"name", "parameters": {...}, "evidence": "...", "score": ...}],
   "mismatch": {"bands_hz": [[lo, hi], ...], "windows_s": [[t0, t1], ...], ...},
   "fit": {"nominal": {"nrmse", ...}, "refit": {...}, "augmented": {...}}, "summary": "...",
   "sensor": {"offset_m", "drift_m_per_s", "lines": [{"frequency_hz", "amplitude_m", ...}], ...},
   "verdict": {"status": explained | partly | incomplete | not_described | no_claim, "text", "suggestions"},
   "command": {"kind", "description", "band_hz", ...}}
fit.csv models the measurement as recorded: each model column is physics plus that model's fitted sensor terms, so
measured_m - augmented_m is the noise where used = 1 (used = 0: clipped or start-transient samples, left out).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from rig.diagnose import catalogue, figures as figures_mod, uncertainty, units
from rig.diagnose.evidence import signature_line
from rig.diagnose.problem import MIN_GAIN
from rig.diagnose.results import MODELS, Diagnosis, Mismatch, NamedEffect, Verdict
from rig.plant.model import EHA_REFIT_KEYS
FIT_COLUMNS = ("time_s", "measured_m", "nominal_m", "refit_m", "augmented_m", "augmented_sensor_m", "used")


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


def diagnosis_dict(diag: Diagnosis, rec=None) -> dict:
    """The diagnosis.json document (schema of issue 7, plus groups, refit parameters and noise)."""
    effects = [{"name": e.name, "parameters": dict(e.parameters), "evidence": effect_evidence(e, diag.mismatch),
                "score": e.score, "interval_95": {k: list(v) for k, v in e.interval.items()},
                "share_of_refit_holdout_residual": e.share, "holdout_lr_of_taking_it_out": e.evidence,
                "reduced_model_bias_taken_off": dict(e.bias)}
               for e in diag.effects]
    cmd = diag.command
    doc = {"effects": effects, "mismatch": diag.mismatch.as_dict(), "fit": diag.fit.as_dict(),
           "summary": summary(diag), "groups": [list(g) for g in diag.groups],
           "params_refit": dict(diag.params_refit), "noise_m": diag.noise_m, "timing_s": diag.timing_s,
           "candidates": list(diag.candidates),      # every test the engine ran
           "plant": dict(diag.plant), "sensor": diag.sensor.as_dict(),
           "verdict": {"status": diag.verdict.status, "text": verdict_text(diag.verdict),
                       "suggestions": list(diag.verdict.suggestions), "rest": list(diag.verdict.rest),
                       "noise": diag.verdict.noise},
           "interval_method": (uncertainty.METHOD + ("; the reduced model's bias, measured on the full stand "
                               "physics at the fit, taken off (rig.diagnose.reduction)"
                               if any(e.bias for e in diag.effects) else "")) if diag.effects else None,
           "command": {"kind": cmd.kind, "description": cmd.describe(), "band_hz": list(cmd.band_hz),
                       "peak_V": cmd.peak_V, "levels_V": [sg.peak_V for sg in cmd.segments] if cmd.multilevel
                       else None, "period_s": cmd.period / cmd.fs_hz if cmd.period else None}}
    ev = diag.evidence or {}
    if ev:
        doc["evidence"] = {"effects": {k: v.get("finding", "") for k, v in ev.get("effects", {}).items()},
                           "sensor": {k: v.get("finding", "") for k, v in ev.get("sensor", {}).items()}}
        if "levels" in ev:
            doc["evidence"]["gain_by_level"] = ev["levels"]["rows"]
    if rec is not None:
        doc["recording"] = {"source": rec.source, "fs_hz": rec.fs_hz, "samples": rec.n,
                            "duration_s": rec.duration_s}
    return _plain(doc)


# ---- the prose of a diagnosis ------------------------------------------------------------------------
def verdict_text(v: Verdict) -> str:
    """The verdict in one or two sentences."""
    if v.status == "no_claim":
        return f"No claim: {v.no_claim}."
    if v.status == "explained":
        if v.named:
            return f"The augmented model explains the recording (residual {v.holdout_over_noise:.2f}x noise)."
        return f"The refit of the linear parameters explains the recording (residual {v.holdout_over_noise:.2f}x noise)."
    rest = f" The rest lies in {'; '.join(v.rest)}." if v.rest else ""
    if v.status == "not_described":
        return (f"The model does not describe this recording: neither the refit ({v.refit_over_noise:.1f}x noise) "
                f"nor the catalogue effects ({v.holdout_over_noise:.1f}x noise) bring the residual near the noise, "
                f"so no effect is named.")
    if v.status == "incomplete":
        share = 1.0 - (v.holdout_over_noise / v.refit_over_noise) ** 2 if v.refit_over_noise else 0.0
        return (f"The model stays incomplete: the effects named each predict the held-out blocks and together "
                f"remove {100 * share:.0f} % of the refit's held-out residual variance ({v.refit_over_noise:.1f}x "
                f"-> {v.holdout_over_noise:.1f}x the noise), but something outside the catalogue remains far above "
                f"the noise." + rest)
    return (f"The augmented model explains the recording only in part: the residual stays "
            f"{v.holdout_over_noise:.2f}x the noise (something outside the catalogue remains)." + rest)


def effect_evidence(e: NamedEffect, mismatch: Mismatch) -> str:
    """One line: what the data show (rig.diagnose.evidence.signature_line) and the tests the effect passed."""
    st = e.stats
    return (f"{signature_line(e, mismatch)}; fit-block BIC gain {st['delta_bic_fit']:.0f} (needs > 0), held-out "
            f"log-likelihood ratio {st['lr_holdout']:.0f} (needs > {st['lr_needed']:.0f}), held-out residual "
            f"variance cut by {100 * st['holdout_gain']:.1f} % (needs > {100 * MIN_GAIN:.1f} %)")


def _with_interval(e, k: str, v: float) -> str:
    iv = e.interval.get(k)
    return f"{k}={v:.4g}" + (f" [{iv[0]:.4g}, {iv[1]:.4g}]" if iv else "")


def _summary_effects(effects) -> str:
    return ", ".join(f"{e.name} ({', '.join(_with_interval(e, k, v) for k, v in e.parameters.items())}"
                     + (f"; removes {100 * e.share:.2g} % of the refit's held-out residual" if e.share is not None
                        else "") + ")" for e in effects)


def _clip_what(c, unit: str) -> str:
    """A clip in words: the measured output's flat top at its sensor's range is an output clip, at its level."""
    if c.channel != "position_m":
        return f"{c.channel} clipped"
    lvl = c.high if c.high is not None else c.low
    return f"output clip at {units.amount(lvl, unit, '.4g')}"


def _sensor_summary(s) -> str:
    u = s.unit
    parts = [f"offset {units.amount(s.offset_m, u)}", f"drift {units.per_second(s.drift_m_per_s, u)}"] \
        if (s.offset_m or s.drift_m_per_s) else []     # none: the segment-wise initial states hold the zero
    if s.wander_terms:
        parts.append(f"slow wander {units.amount(s.wander_rms_m, u)} rms")
    for l in s.lines:
        amp = units.amount(l.amplitude, u) if l.channel == "position_m" else f"{l.amplitude * 1e3:.3g} mm/s^2"
        parts.append(f"{l.source} line {l.frequency_hz:.2f} Hz on {l.channel} ({amp})")
    if s.quantisation_step_m:
        parts.append(f"quantisation step {units.amount(s.quantisation_step_m, u)}")
    for c in s.clipped:
        parts.append(f"{_clip_what(c, u)} ({c.samples} samples)")
    return ", ".join(parts)


def summary(diag: Diagnosis) -> str:
    """The diagnosis in one paragraph: the verdict, the physics named, the held-out figures, the mismatch, the
    sensor terms and what the evidence suggests."""
    mm, fit, v = diag.mismatch, diag.fit, diag.verdict
    what = _summary_effects(diag.effects) if diag.effects else "none"
    out = (f"{verdict_text(v)} Missing physics: {what}. Held-out residual/noise nominal "
           f"{fit.nominal.residual_over_noise_holdout:.1f}, refit {fit.refit.residual_over_noise_holdout:.1f}, "
           f"augmented {fit.augmented.residual_over_noise_holdout:.2f} (noise "
           f"{units.amount(diag.noise_m, diag.sensor.unit, '.2g')}). "
           f"Mismatch vs nominal in {len(mm.bands_hz)} band(s), after refit in {len(mm.after_refit['bands_hz'])}.")
    if diag.groups and diag.effects:
        out += " Confounded: " + "; ".join(" ~ ".join(g) for g in diag.groups) + "."
    sens_txt = _sensor_summary(diag.sensor) if v.status != "not_described" else ""
    if sens_txt:
        out += f" Sensor terms (not physics): {sens_txt}."
    for sg in v.suggestions:
        out += f" {sg}"
    return out


# ---- fit.csv -----------------------------------------------------------------------------------------
def fit_columns(diag: Diagnosis, rec) -> np.ndarray:
    """(n, 7) array of FIT_COLUMNS for every recorded instant."""
    cols = [np.asarray(rec.t_s, float), np.asarray(rec.position_m, float)]
    for m in MODELS + ("augmented_sensor",):
        s = diag.series.get(f"{m}_m")
        if s is None:
            if m == "augmented_sensor":
                s = np.zeros(rec.n)
            else:
                raise RuntimeError(f"diagnosis has no {m}_m series")
        s = np.asarray(s, float)
        if s.shape != (rec.n,):
            raise RuntimeError(f"diagnosis {m}_m series has {s.shape} samples, the recording {rec.n}")
        cols.append(s)
    cols.append(np.ones(rec.n) if diag.used is None else np.asarray(diag.used, float))
    return np.column_stack(cols)


def write_fit_csv(path: Path, diag, rec) -> Path:
    data = fit_columns(diag, rec)
    np.savetxt(path, data, delimiter=",", header=",".join(FIT_COLUMNS), comments="",
               fmt=["%.9f", "%.9g", "%.9g", "%.9g", "%.9g", "%.9g", "%d"])
    return path


# ---- text --------------------------------------------------------------------------------------------
_UNITS = catalogue.display_units()      # parameter key -> (scale, unit), from the effects' definitions


def _like(bound: float, value: float) -> str:
    """An interval's bound with the decimals its estimate is printed with (402.1: 395.0 to 408.5)."""
    shown = f"{value:.4g}"
    if "e" in shown or "e" in f"{bound:.4g}":
        return f"{bound:.4g}"
    return f"{bound:.{len(shown.partition('.')[2])}f}"


def format_parameters(prm: dict, interval: dict | None = None) -> str:
    """Parameters in their display units; with an interval, each key's 95 % interval after it."""
    out = []
    for k, v in prm.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            scale, unit = _UNITS.get(k, (1.0, ""))
            name = k.rsplit("_", 1)[0] if k in _UNITS and unit else k
            iv = (interval or {}).get(k)
            ci = f" (95 %: {_like(iv[0] * scale, v * scale)} to {_like(iv[1] * scale, v * scale)})" if iv else ""
            out.append(f"{name} {v * scale:.4g}{(' ' + unit) if unit else ''}{ci}")
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
    s = "lines at " + ", ".join(f"{l['frequency_hz']:.2f} Hz ({l['amplitude_m']:.2g})" for l in lines)
    frac = u.get("fraction_of_refit_residual_in_lines")
    if isinstance(frac, (int, float)):
        s += f"; {100 * frac:.0f} % of the refit residual power"
    return s


def _mismatch_rows(mm: Mismatch, limit: int, verdict: Verdict | None = None) -> list[tuple[str, str, str]]:
    """Where the model and the recording differ, once for stdout and report.md: (short label, long label, text).
    With the verdict `explained` the augmented fit's residual as a whole is at the noise: its bands are then said
    to be within that, not "still off"."""
    after = _spans(mm.after_augmented["bands_hz"], "Hz", limit)
    if verdict is not None and verdict.status == "explained" and after != "none":
        after += (f" (the residual as a whole is at the noise, {verdict.holdout_over_noise:.2f}x: these bands' "
                  f"FRF error is within what this recording can resolve)")
        after_label = "Bands whose FRF error stays above its uncertainty after the augmented fit"
    else:
        after_label = "Bands still off after the augmented fit"
    rows = [("frequency bands", "Frequency bands (FRF error above its coherence-based uncertainty)",
             _spans(mm.bands_hz, "Hz", limit)),
            ("time windows", "Time windows", _spans(mm.windows_s, "s", limit)),
            ("after refit", "Bands still off after the linear refit", _spans(mm.after_refit["bands_hz"], "Hz", limit)),
            ("after augmented", after_label, after),
            ("regimes", "Regimes", describe_regimes(mm.regimes))]
    if mm.harmonics is not None:
        rows.append(("harmonics", "Harmonics", describe_harmonics(mm.harmonics)))
    rows.append(("uncorrelated", "Uncorrelated", describe_uncorrelated(mm.uncorrelated)))
    return rows


def _refitted_what(plant: dict) -> str:
    free = plant.get("free_parameters") if plant.get("family", "eha") != "eha" else None
    return (f"its linear parameters {', '.join(EHA_REFIT_KEYS)}" if free is None else
            f"its free parameters {', '.join(free)}" if free else "nothing: every parameter is fixed")


def summary_text(diag: Diagnosis, rec=None) -> str:
    """The readable summary for stdout: where, what, how much better."""
    mm, verdict = diag.mismatch, diag.verdict
    lines = []
    if rec is not None:
        lines.append(f"recording {rec.source}: {rec.n} samples at {rec.fs_hz:g} Hz ({rec.duration_s:g} s)")
    lines.append(f"command: {diag.command.describe()}")
    lines.append("WHERE the recording and the nominal model differ:")
    lines += [f"  {short + ':':16} {text}" for short, _, text in _mismatch_rows(mm, 6, verdict)]
    lines += [f"  note: {note}" for note in mm.notes[1:]]
    lines.append(f"WHAT physics the linear model leaves out (after refitting {_refitted_what(diag.plant)}):")
    if not diag.effects:
        if verdict.status != "explained":
            lines.append(f"  none named: {verdict_text(verdict)}")
        else:
            lines.append("  none: the refit linear model explains the recording")
    for e in diag.effects:
        lines.append(f"  {e.name}: {format_parameters(e.parameters, e.interval)} [score {e.score:.4g}]")
        if e.share is not None:
            lines.append(f"    removes {100 * e.share:.3g} % of the refit's held-out residual variance (the others "
                         f"kept); held-out log-likelihood ratio of taking it out {e.evidence:.0f}")
        lines.append(f"    evidence: {effect_evidence(e, mm)}")
        if e.bias:
            lines.append(f"    the reduced model's own bias taken off (measured on the full stand physics at the fit): "
                         f"{format_parameters(e.bias)}")
    for g in diag.groups:
        lines.append(f"  confounded (cannot be told apart here): {', '.join(g)}")
    lines.append("SENSOR terms (fitted in every model, not physics):")
    lines += [f"  {t}" for t in sensor_lines(diag.sensor)]
    lines.append("HOW MUCH BETTER (NRMSE of position; residual rms / noise rms):")
    lines.append(f"  {'':10} {'NRMSE':-^26} {'resid/noise':-^17}")
    lines.append(f"  {'model':10} {'whole':>8} {'fit seg':>8} {'held-out':>8} {'whole':>8} {'held-out':>8}")
    for m in MODELS:
        f = diag.fit.model(m)
        lines.append(f"  {m:10} {_figure(f.nrmse):>8} {_figure(f.nrmse_fit):>8} {_figure(f.nrmse_holdout):>8} "
                     f"{_figure(f.residual_over_noise, '.2f'):>8} {_figure(f.residual_over_noise_holdout, '.2f'):>8}")
    nom, aug = diag.fit.nominal.nrmse, diag.fit.augmented.nrmse
    if nom and aug is not None and aug > 0:
        lines.append(f"  NRMSE {nom:.4f} -> {aug:.4f} ({nom / aug:.1f}x better than nominal)")
    lines.append(f"VERDICT: {verdict_text(verdict)}")
    lines += [f"  {sg}" for sg in verdict.suggestions]
    lines.append(f"summary: {summary(diag)}")
    return "\n".join(lines)


def sensor_lines(sensor) -> list[str]:
    """The sensor terms as readable lines (stdout and report.md)."""
    u = sensor.unit
    out = [f"{'position' if u in ('m', 'rad') else 'output'} offset {units.amount(sensor.offset_m, u, '.4g')} at "
           f"t = 0, drift {units.per_second(sensor.drift_m_per_s, u, '.4g')}"
           + (f", slow wander {units.amount(sensor.wander_rms_m, u)} rms ({sensor.wander_terms} cosines)"
              if sensor.wander_terms else "")]
    for l in sensor.lines:
        amp = units.amount(l.amplitude, u) if l.channel == "position_m" else f"{l.amplitude:.3g} m/s^2"
        out.append(f"{l.source} line on {l.channel} at {l.frequency_hz:.3f} Hz, {amp}: {l.evidence}")
    if sensor.quantisation_step_m:
        out.append(f"output quantised in steps of {units.amount(sensor.quantisation_step_m, u)} (floor "
                   f"{units.amount(sensor.quantisation_step_m / math.sqrt(12), u)} rms)")
    if sensor.accel_quantisation_step_mps2:
        out.append(f"acceleration quantised in steps of {sensor.accel_quantisation_step_mps2:.3g} m/s^2")
    if sensor.accel_offset_mps2 is not None:
        out.append(f"accelerometer offset {sensor.accel_offset_mps2:.4g} m/s^2")
    if sensor.accel is not None and sensor.accel.note:
        out.append(sensor.accel.note)
    for c in sensor.clipped:
        out.append(f"{_clip_what(c, u)} ({c.samples} samples from {c.first_s:.4g} s): left out of the fit")
    if sensor.start_transient_s:
        out.append(f"mid-run start: the first {sensor.start_transient_s:g} s are left out (start transient)")
    return out


# ---- report.md ---------------------------------------------------------------------------------------
def report_markdown(diag: Diagnosis, rec, figures: dict[str, str], windows, evidence=()) -> str:
    """report.md: the verdict, where model and recording differ, the physics named, the sensor terms, the
    evidence, the fit table and the figures, one section function each."""
    out = _report_head(diag, rec)
    out += _report_mismatch(diag)
    out += _report_effects(diag)
    out += _report_sensor_and_evidence(diag, evidence)
    out += _report_fit(diag)
    out += _report_figures(figures, windows)
    return "\n".join(out)


def _report_head(diag: Diagnosis, rec) -> list[str]:
    """Title, the recording in one line, the verdict with its suggestions, the command and the notes."""
    verdict = diag.verdict
    out = [f"# Diagnosis of {rec.source}", "",
           f"{rec.n} samples at {rec.fs_hz:g} Hz ({rec.duration_s:g} s). Noise estimate: "
           f"{units.amount(diag.noise_m, diag.sensor.unit)} rms, {verdict.noise or 'from the residual'}.", ""]
    out += [f"**Verdict ({verdict.status.replace('_', ' ')}):** {verdict_text(verdict)}", ""]
    out += [f"- {sg}" for sg in verdict.suggestions] + ([""] if verdict.suggestions else [])
    out += [f"Command: {diag.command.describe()}.", ""]
    for note in diag.mismatch.notes[1:]:
        out += [f"Note: {note}.", ""]
    return out


def _report_mismatch(diag: Diagnosis) -> list[str]:
    """The summary and the bands, windows and patterns where the model and the recording differ."""
    return [f"**Summary:** {summary(diag) or '-'}", "", "## Where the model and the recording differ", ""] + \
        [f"- {long}: {text}" for _, long, text in _mismatch_rows(diag.mismatch, 20, diag.verdict)]


def _report_effects(diag: Diagnosis) -> list[str]:
    """The effects named (or why none), the confounded groups and a non-eha plant's augmented parameters."""
    out = ["", "## Physics left out by the linear model", ""]
    verdict = diag.verdict
    if diag.effects:
        out += ["Ranked by evidence (the held-out log-likelihood ratio of taking each out); intervals: "
                f"{uncertainty.METHOD}.", "",
                "| effect | parameters (95 % interval) | share of the refit's held-out residual | score | evidence |",
                "|---|---|---|---|---|"]
        for e in diag.effects:
            share = f"{100 * e.share:.3g} %" if e.share is not None else "-"
            out.append(f"| {e.name} | {format_parameters(e.parameters, e.interval)} | {share} | "
                       f"{_figure(e.score, '.4g')} | {effect_evidence(e, diag.mismatch).replace('|', '/')} |")
    else:
        if verdict.status != "explained":
            out.append(f"None named. {verdict_text(verdict)}")
            for nc in diag.mismatch.not_claimed:
                out.append(f"- best candidate, not claimed: {nc.name} ({format_parameters(nc.parameters)})")
        else:
            out.append("None: the refit linear model explains the recording.")
    for g in diag.groups:
        out.append(f"\nConfounded, cannot be told apart on this recording: {', '.join(g)}.")
    pl = diag.plant
    if pl.get("family") and pl["family"] != "eha":
        out.append(f"\nPlant: {pl['family']} (input in {pl['input_unit']}), augmented linear parameters "
                   + ", ".join(f"{k} = {v:.4g}" for k, v in pl.get("augmented_linear", {}).items())
                   + (f"; simulated in {pl['shooting']['segments']} segments from their own initial states "
                      "(multiple shooting)" if "shooting" in pl else "") + ".")
    return out


def _report_sensor_and_evidence(diag, evidence) -> list[str]:
    """The fitted sensor terms, and each evidence figure with its finding."""
    out = ["", "## Sensor terms (fitted in every model, never named as effects)", ""]
    out += [f"- {t}" for t in sensor_lines(diag.sensor)]
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
           f"| model | NRMSE | NRMSE fit segment | NRMSE held-out | residual rms ({units.name(diag.sensor.unit)}) "
           "| residual / noise "
           "| residual / noise held-out |", "|---|---|---|---|---|---|---|"]
    for m in MODELS:
        f = diag.fit.model(m)
        out.append(f"| {m} | {_figure(f.nrmse)} | {_figure(f.nrmse_fit)} | {_figure(f.nrmse_holdout)} | "
                   f"{_figure(f.residual_rms_m, '.3g')} | {_figure(f.residual_over_noise, '.2f')} | "
                   f"{_figure(f.residual_over_noise_holdout, '.2f')} |")
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
    if figures_mod.plot_frf(out_dir / "frf.png", diag) is not None:
        figures["frf"] = "frf.png"
    figures_mod.plot_residual_spectra(out_dir / "residual_spectra.png", diag, rec)
    figures["residuals"] = "residual_spectra.png"
    windows = figures_mod.worst_windows(diag, rec)
    figures_mod.plot_windows(out_dir / "worst_windows.png", diag, rec, windows)
    figures["windows"] = "worst_windows.png"
    evidence = figures_mod.plot_evidence(out_dir, diag)
    paths["report"].write_text(report_markdown(diag, rec, figures, windows, evidence))
    for key, name in figures.items():
        paths[key] = out_dir / name
    for label, name, _ in evidence:
        if name:
            paths[name[:-4]] = out_dir / name
    return paths

"""The grades of a blind proof (rig prove, rig prove --plant) and their tables:
  right  = the named set of effects is exactly the true set ("none" when both are empty)
  errors = relative parameter error of each true effect that was named (targets: delay 20 %, frequency 5 %);
the confusion matrix, the score against the issues' targets, the summary by habit, and the markdown and JSON.
"""
from __future__ import annotations

from dataclasses import asdict

import numpy as np

from rig.diagnose import catalogue, report
from rig.diagnose.results import MODELS

CATALOGUE = catalogue.for_proof("stand")      # the actuator's effects first in the confusion matrix
NONE = "none"
TARGETS = {"delay_s": 0.20, "frequency_hz": 0.05}   # relative error targets of issue 7


def _fit_figure(diag, model: str, key: str) -> float | None:
    v = getattr(diag.fit.model(model), key)
    return None if v is None else float(v)


LINE_FOUND = 0.05               # a reported line within 5 % of a true one is that line; none: the line was missed


def _line_grades(true_hz: list[float], diag, true_m: list[float] | None = None) -> dict:
    """Each true pickup line: reported among the sensor's position lines, and within 1 % of its frequency?
    errors: relative frequency error of the nearest reported line (None when none is within 5 %: missed)."""
    rep = [l.frequency_hz for l in diag.sensor.lines if l.channel == "position_m"]
    errs = []
    for f in true_hz:
        near = min((abs(r - f) / f for r in rep), default=None)
        errs.append(near if near is not None and near <= LINE_FOUND else None)
    missed = [{"frequency_hz": f, "amplitude_m": a} for f, a, e in zip(true_hz, true_m or [None] * len(true_hz), errs)
              if e is None]
    return {"true_hz": list(true_hz), "reported_hz": rep, "errors": errs, "n": len(true_hz),
            "found": sum(e is not None for e in errs), "within": sum(e is not None and e <= 0.01 for e in errs),
            "missed": missed}


def grade(name: str, truth: dict, diag, *, true_linear: dict | None = None, elapsed_s: float = 0.0,
          cpu_s: float | None = None, noise_m: float | None = None, pickup_hz: list[float] | None = None,
          pickup_m: list[float] | None = None, habits: list[str] | None = None, duration_s: float | None = None,
          fs_hz: float | None = None) -> dict:
    """One row of the proof table from the true effects (answers.json style) and a Diagnosis."""
    named = {e.name: dict(e.parameters) for e in diag.effects}
    errors = {}
    for eff, prm in truth.items():
        if eff not in named:
            continue
        for key, true_v in prm.items():
            est = named[eff].get(key)
            if est is None or not isinstance(true_v, (int, float)) or true_v == 0:
                continue
            errors[f"{eff}.{key}"] = abs(float(est) - float(true_v)) / abs(float(true_v))
    lin_err = None
    if true_linear and diag.params_refit:
        errs = [abs(float(diag.params_refit[k]) - v) / abs(v) for k, v in true_linear.items()
                if k in diag.params_refit and v]
        lin_err = max(errs) if errs else None
    aug_rms = _fit_figure(diag, "augmented", "residual_rms_m")
    return {
        "case": name,
        "habits": list(habits or []),
        "truth": sorted(truth),
        "named": sorted(named),
        "right": set(truth) == set(named),
        "truth_parameters": truth,
        "named_parameters": named,
        "parameter_errors": errors,
        "linear_max_error": lin_err,
        "groups": [list(g) for g in diag.groups],
        "nrmse": {m: _fit_figure(diag, m, "nrmse") for m in MODELS},
        "residual_over_noise": {m: _fit_figure(diag, m, "residual_over_noise") for m in MODELS},
        "true_noise_m": noise_m,
        "residual_over_true_noise": (aug_rms / noise_m) if (aug_rms is not None and noise_m) else None,
        "holdout_nrmse": {m: _fit_figure(diag, m, "nrmse_holdout") for m in MODELS},
        "pickup_lines": _line_grades(pickup_hz or [], diag, pickup_m),
        "verdict": diag.verdict.status,
        "elapsed_s": elapsed_s,
        "cpu_s": cpu_s,
        "duration_s": duration_s,
        "fs_hz": fs_hz,
        "summary": report.summary(diag),
    }


def confusion(rows: list[dict]) -> dict[str, dict[str, int]]:
    """Effect-level confusion, rows = truth, columns = named, "none" = no effect.

    A true effect that was named counts on the diagonal. A missed effect counts against each wrongly named
    effect of the same case (mistaken for it), or against "none" if nothing wrong was named. A wrongly named
    effect with no missed effect to explain it counts in row "none" (invented). A clean case named clean is
    (none, none).
    """
    seen = {x for r in rows for x in list(r["truth"]) + list(r["named"])}
    labels = list(CATALOGUE) + sorted(seen - set(CATALOGUE)) + [NONE]     # another plant's catalogue names too
    m = {a: {b: 0 for b in labels} for a in labels}
    for r in rows:
        truth, named = set(r["truth"]), set(r["named"])
        if not truth and not named:
            m[NONE][NONE] += 1
        missed, invented = truth - named, named - truth
        for t in truth & named:
            m[t][t] += 1
        for t in missed:
            for x in (invented or {NONE}):
                m[t][x] += 1
        if not missed:
            for x in invented:
                m[NONE][x] += 1
    return m


def _resid(r: dict) -> float | None:
    """Augmented residual over the noise: the true noise when the case knows it, else the engine's estimate."""
    v = r.get("residual_over_true_noise")
    return v if v is not None else r["residual_over_noise"]["augmented"]


def score(rows: list[dict]) -> dict:
    """Overall figures of the proof against the issues' targets."""
    n = len(rows)
    right = sum(r["right"] for r in rows)
    clean = [r for r in rows if not r["truth"]]
    invented_clean = sum(1 for r in clean if r["named"])
    def within(suffix, tol):
        errs = [e for r in rows for k, e in r["parameter_errors"].items() if k.endswith(suffix)]
        return {"n": len(errs), "within": sum(e <= tol for e in errs), "tolerance": tol,
                "worst": max(errs) if errs else None}
    ron = [_resid(r) for r in rows if _resid(r) is not None]
    times = [r["elapsed_s"] for r in rows]
    cpu = [r["cpu_s"] for r in rows if r.get("cpu_s") is not None]
    at2k = [r for r in rows if (r.get("duration_s") or 0) >= 50.0 and r.get("fs_hz") == 2000.0]
    per100 = [r["elapsed_s"] * 100.0 / r["duration_s"] for r in at2k]     # the issue's budget: 100 s at 2 kHz
    cpu100 = [r["cpu_s"] * 100.0 / r["duration_s"] for r in at2k if r.get("cpu_s") is not None]
    with_habits = [r for r in rows if r.get("habits")]
    lines = [r.get("pickup_lines") or {"n": 0, "within": 0, "errors": []} for r in rows]
    line_errs = [e for g in lines for e in g["errors"] if e is not None]
    out = {
        "cases": n, "right": right, "fraction_right": right / n if n else 0.0,
        "clean_cases": len(clean), "invented_on_clean": invented_clean,
        "delays": within(".delay_s", TARGETS["delay_s"]),
        "frequencies": within(".frequency_hz", TARGETS["frequency_hz"]),
        "residual_within_1.3_noise": {"n": len(ron), "within": sum(v <= 1.3 for v in ron),
                                      "worst": max(ron) if ron else None},
        "seconds_per_case": {"mean": float(np.mean(times)) if times else None,
                             "median": float(np.median(times)) if times else None,
                             "max": float(np.max(times)) if times else None},
        # CPU time of the case's process (its simulator threads counted): the speed targets' measure, which a
        # loaded machine's wall time is not
        "cpu_seconds_per_case": {"median": float(np.median(cpu)) if cpu else None,
                                 "max": float(np.max(cpu)) if cpu else None, "n": len(cpu)},
        "seconds_per_100s_at_2khz": {"median": float(np.median(per100)) if per100 else None,
                                     "max": float(np.max(per100)) if per100 else None,
                                     "n": len(per100),
                                     "cpu_median": float(np.median(cpu100)) if cpu100 else None,
                                     "cpu_max": float(np.max(cpu100)) if cpu100 else None,
                                     "note": "cases at 2 kHz of 50 s or more, wall and CPU time scaled to 100 s"},
    }
    if with_habits:
        out["habit_cases"] = len(with_habits)
        out["sensor_named_as_physics"] = sum(1 for r in with_habits if set(r["named"]) - set(r["truth"]))
        out["mains_lines"] = {"n": sum(g["n"] for g in lines), "found": sum(g.get("found", 0) for g in lines),
                              "within_1pct": sum(g["within"] for g in lines),
                              "worst": max(line_errs) if line_errs else None,
                              "missed": [{"case": r["case"], **m} for r in rows
                                         for m in (r.get("pickup_lines") or {}).get("missed", [])]}
        out["by_habit"] = by_habit(rows)
    return out


def _habit_key(tag: str) -> str:
    return tag.split(":")[0] if tag.startswith(("pickup", "drift")) else tag


def by_habit(rows: list[dict]) -> dict[str, dict]:
    """Per habit tag: cases, named right, invented effects, residual within 1.3 x the true noise."""
    out: dict[str, dict] = {}
    for r in rows:
        for tag in r.get("habits") or []:
            for key in {tag, _habit_key(tag)}:
                d = out.setdefault(key, {"cases": 0, "right": 0, "invented": 0, "residual_ok": 0})
                d["cases"] += 1
                d["right"] += int(r["right"])
                d["invented"] += int(bool(set(r["named"]) - set(r["truth"])))
                v = _resid(r)
                d["residual_ok"] += int(v is not None and v <= 1.3)
    return dict(sorted(out.items()))


# ---- presentation ------------------------------------------------------------------------------------
def _names(xs: list[str]) -> str:
    return " + ".join(xs) if xs else NONE


def _fmt(v, spec=".3f") -> str:
    return "-" if v is None else format(v, spec)


def _short_key(k: str) -> str:
    eff, key = k.split(".", 1)
    short = catalogue.short(eff)
    return f"{short}.{key.replace('_hz', '').replace('_s', '').replace('_ma', '').replace('_n', '')}"


def _habits_cell(r: dict) -> str:
    return ", ".join(r.get("habits") or []) or "-"


def table_markdown(rows: list[dict]) -> str:
    head = ("| case | habits | truth | named | ok | parameter errors | NRMSE nominal -> refit -> augmented "
            "| resid/noise aug | s |\n|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        errs = ", ".join(f"{_short_key(k)} {100 * e:.1f}%" for k, e in sorted(r["parameter_errors"].items())) or "-"
        nr = r["nrmse"]
        lines.append(f"| {r['case']} | {_habits_cell(r)} | {_names(r['truth'])} | {_names(r['named'])} | "
                     f"{'yes' if r['right'] else 'NO'} | {errs} | {_fmt(nr['nominal'])} -> {_fmt(nr['refit'])} -> "
                     f"{_fmt(nr['augmented'])} | {_fmt(_resid(r), '.2f')} | "
                     f"{r['elapsed_s']:.1f} |")
    return head + "\n".join(lines) + "\n"


def habits_markdown(s: dict) -> str:
    """The summary by habit: how the diagnosis fared on the cases that carried each habit."""
    bh = s.get("by_habit") or {}
    if not bh:
        return ""
    head = "| habit | cases | named right | invented effect | residual <= 1.3 x noise |\n|---|---|---|---|---|\n"
    return head + "\n".join(f"| {k} | {v['cases']} | {v['right']} | {v['invented']} | {v['residual_ok']} |"
                             for k, v in bh.items()) + "\n"


def confusion_markdown(m: dict[str, dict[str, int]]) -> str:
    labels = list(m)
    head = "| truth \\ named | " + " | ".join(labels) + " |\n|---|" + "---|" * len(labels) + "\n"
    body = "\n".join(f"| {a} | " + " | ".join(str(m[a][b]) if m[a][b] else "." for b in labels) + " |"
                     for a in labels)
    return head + body + "\n"


def score_text(s: dict) -> str:
    d, f, r = s["delays"], s["frequencies"], s["residual_within_1.3_noise"]
    sp, sp100 = s["seconds_per_case"], s.get("seconds_per_100s_at_2khz") or {}
    cpu = s.get("cpu_seconds_per_case") or {}
    out = [
        f"score: {s['right']}/{s['cases']} named right ({100 * s['fraction_right']:.0f} %, target 95 %); "
        f"invented on clean cases: {s['invented_on_clean']}/{s['clean_cases']} (target 0)",
        f"delays within 20 %: {d['within']}/{d['n']} (worst {_fmt(d['worst'] and 100 * d['worst'], '.1f')} %); "
        f"frequencies within 5 %: {f['within']}/{f['n']} (worst {_fmt(f['worst'] and 100 * f['worst'], '.1f')} %)",
        f"augmented residual <= 1.3 x noise: {r['within']}/{r['n']} (worst {_fmt(r['worst'], '.2f')}); "
        f"diagnosis time per case: median {_fmt(sp.get('median'), '.1f')} s, mean {_fmt(sp['mean'], '.1f')} s, "
        f"max {_fmt(sp['max'], '.1f')} s" + (f" wall, CPU median {_fmt(cpu['median'], '.1f')} s, max "
                                            f"{_fmt(cpu['max'], '.1f')} s" if cpu.get("n") else "")
        + (f"; per 100 s at 2 kHz ({sp100['n']} cases): median "
                                            f"{_fmt(sp100.get('median'), '.1f')} s, max {_fmt(sp100.get('max'), '.1f')} s "
                                            f"wall, CPU median {_fmt(sp100.get('cpu_median'), '.1f')} s, max "
                                            f"{_fmt(sp100.get('cpu_max'), '.1f')} s" if sp100.get("n") else ""),
    ]
    if "habit_cases" in s:
        ml = s["mains_lines"]
        missed = "; ".join(f"{m['case']} {m['frequency_hz']:.2f} Hz"
                           + (f" ({m['amplitude_m'] * 1e9:.2g} nm)" if m.get("amplitude_m") else "")
                           for m in ml.get("missed", []))
        out.append(f"habits in {s['habit_cases']} cases: sensor artefact named as physics in "
                   f"{s['sensor_named_as_physics']} (target 0); pickup lines found {ml.get('found', ml['n'])}/"
                   f"{ml['n']}, reported within 1 % of their frequency: {ml['within_1pct']}/{ml.get('found', ml['n'])}"
                   f" (worst {_fmt(ml['worst'] and 100 * ml['worst'], '.2f')} %)"
                   + (f"; missed: {missed}" if missed else ""))
    return "\n".join(out)


def report_markdown(rows: list[dict], title: str) -> str:
    s = score(rows)
    hab = habits_markdown(s)
    return (f"# {title}\n\n{table_markdown(rows)}\n## Confusion matrix (effects)\n\n"
            f"{confusion_markdown(confusion(rows))}\n" + (f"## By habit\n\n{hab}\n" if hab else "")
            + "## Score\n\n" + score_text(s).replace("\n", "\n\n") + "\n")


def report_json(rows: list[dict], title: str, cases: list | None = None) -> dict:
    out = {"title": title, "rows": rows, "confusion": confusion(rows), "score": score(rows)}
    if cases is not None:
        out["cases"] = [asdict(c) for c in cases]
    return out

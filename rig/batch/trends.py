"""How a batch's recordings of one rig (one plant file: a batch has one) move over their dates: every identified
parameter and every named effect's size, a straight line through them in time, and which changed beyond their
confidence interval.

A quantity changed when its change over the batch's span (the line's slope times the span) is more than
`T_CHANGED` times its standard error. The standard error is the larger of the scatter about the line (what the
recordings themselves say) and, where the analysis gives one, the recordings' own 1-sigma (rig identify). An
effect not named in a recording has size 0 there (a delay that appears is a change from 0). Where the
analysis gives no 1-sigma (a diagnosis's refitted parameters) a change below `MIN_RELATIVE_CHANGE` of the
parameter's size is not called one: a line through near-equal values has almost no scatter.

Outputs in the batch's folder: trends.png (one panel per quantity, the changed first, in red) and trends.csv
(quantity, unit, first and last value on the line, change, its standard error, t, changed); the one line names
what changed.
"""
from __future__ import annotations

import csv
import datetime as dt
import math
from pathlib import Path

import numpy as np

T_CHANGED = 3.0
MIN_RELATIVE_CHANGE = 0.01
MIN_RECORDINGS = 3
MAX_PANELS = 16


def _days(rows: list[dict]) -> np.ndarray:
    t = [dt.datetime.fromisoformat(r["date_utc"]).timestamp() / 86400.0 for r in rows]
    return np.asarray(t) - min(t)


def series(rows: list[dict]) -> dict[str, dict]:
    """{quantity: {"values", "std" (or None), "unit", "effect": bool}} over the rows (in their order)."""
    out: dict[str, dict] = {}
    effects = sorted({(e, k) for r in rows for e, prm in r["effects"].items() for k in prm
                      if isinstance(prm[k], (int, float)) and not isinstance(prm[k], bool)})
    for e, k in effects:
        vals = [r["effects"][e][k] if e in r["effects"] else 0.0 for r in rows]
        out[f"{e}.{k}"] = {"values": np.asarray(vals, float), "std": None, "unit": "", "effect": True}
    keys = [k for k in rows[0]["parameters"] if all(k in r["parameters"] for r in rows)]
    for k in keys:
        vals = [r["parameters"][k] for r in rows]
        std = [r["std"].get(k) for r in rows]
        out[k] = {"values": np.asarray([np.nan if v is None else v for v in vals], float),
                  "std": np.asarray(std, float) if all(s is not None for s in std) else None,
                  "unit": rows[0]["units"].get(k, ""), "effect": False}
    return out


def judge(t_days: np.ndarray, s: dict) -> dict:
    """The line through a quantity over time and whether its change over the span is beyond its uncertainty."""
    y = s["values"]
    ok = np.isfinite(y)
    x, y = t_days[ok], y[ok]
    span = float(np.ptp(x)) if len(x) else 0.0
    if len(x) < MIN_RECORDINGS or span <= 0:
        return {"first": float(y[0]) if len(y) else math.nan, "last": float(y[-1]) if len(y) else math.nan,
                "change": 0.0, "sigma": math.nan, "t": 0.0, "changed": False, "line": None}
    A = np.column_stack([np.ones_like(x), x - x.mean()])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    sxx = float(np.sum((x - x.mean()) ** 2))
    scatter = math.sqrt(float(resid @ resid) / max(len(x) - 2, 1))
    sd = scatter
    if s["std"] is not None:
        sd = max(sd, float(np.sqrt(np.mean(s["std"][ok] ** 2))))
    sigma = span * sd / math.sqrt(sxx)                      # standard error of slope x span
    change = float(coef[1]) * span
    size = float(np.max(np.abs(y)))
    big = s["effect"] or s["std"] is not None or abs(change) > MIN_RELATIVE_CHANGE * size
    tstat = abs(change) / sigma if sigma > 0 else (math.inf if change else 0.0)
    lo, hi = float(x.min()), float(x.max())
    return {"first": float(coef[0] + coef[1] * (lo - x.mean())), "last": float(coef[0] + coef[1] * (hi - x.mean())),
            "change": change, "sigma": sigma, "t": tstat, "changed": bool(big and tstat > T_CHANGED),
            "line": (lo, hi, coef, float(x.mean()))}


def analyse(rows: list[dict]) -> tuple[np.ndarray, dict, dict]:
    """(days since the first recording, the series, the judgement of each), the rows in date order."""
    ok = sorted((r for r in rows if r["status"] == "ok" and r.get("date_utc")), key=lambda r: r["date_utc"])
    if len(ok) < MIN_RECORDINGS:
        return np.zeros(0), {}, {}
    t = _days(ok)
    ser = series(ok)
    return t, ser, {q: judge(t, s) for q, s in ser.items()}


def line(judged: dict, n: int) -> str:
    changed = sorted((q for q, j in judged.items() if j["changed"]), key=lambda q: -judged[q]["t"])
    if not changed:
        return f"trends over {n} recordings: nothing changed beyond its confidence interval"
    parts = [f"{q} {judged[q]['first']:.4g} -> {judged[q]['last']:.4g} ({judged[q]['t']:.0f} sigma)" for q in changed]
    return f"trends over {n} recordings: changed beyond the confidence interval: " + "; ".join(parts)


def _plot(path: Path, t: np.ndarray, ser: dict, judged: dict, dates: list[str], title: str) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = sorted(ser, key=lambda q: (not judged[q]["changed"], -judged[q]["t"]))[:MAX_PANELS]
    cols = min(4, len(order))
    rows_n = math.ceil(len(order) / cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(3.6 * cols, 2.6 * rows_n), squeeze=False)
    for ax, q in zip(axes.flat, order):
        s, j = ser[q], judged[q]
        colour = "tab:red" if j["changed"] else "tab:blue"
        ax.errorbar(t, s["values"], yerr=s["std"], fmt="o", ms=3, color=colour, lw=0.8)
        if j["line"] is not None:
            lo, hi, coef, xm = j["line"]
            xs = np.array([lo, hi])
            ax.plot(xs, coef[0] + coef[1] * (xs - xm), color=colour, lw=1)
        unit = f" [{s['unit']}]" if s["unit"] else ""
        ax.set_title(f"{q}{unit}" + (f"\nchanged ({j['t']:.0f} sigma)" if j["changed"] else ""), fontsize=8,
                     color=colour)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(order):]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel(f"days since {dates[0][:10]}", fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write(out_root: Path, rows: list[dict]) -> dict:
    """trends.png and trends.csv into out_root (with at least MIN_RECORDINGS done recordings); {"line",
    "changed": [quantity, ...], "plot", "csv"} (empty when there are too few)."""
    t, ser, judged = analyse(rows)
    if not judged:
        return {}
    out_root = Path(out_root)
    dates = sorted(r["date_utc"] for r in rows if r["status"] == "ok" and r.get("date_utc"))
    text = line(judged, len(t))
    paths = {"plot": _plot(out_root / "trends.png", t, ser, judged, dates, text), "csv": out_root / "trends.csv"}
    with paths["csv"].open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["quantity", "unit", "first_on_line", "last_on_line", "change", "change_std_error", "t",
                    "changed"])
        for q, j in sorted(judged.items(), key=lambda qj: -qj[1]["t"]):
            w.writerow([q, ser[q]["unit"], repr(j["first"]), repr(j["last"]), repr(j["change"]), repr(j["sigma"]),
                        f"{j['t']:.3g}", int(j["changed"])])
    changed = [q for q, j in sorted(judged.items(), key=lambda qj: -qj[1]["t"]) if j["changed"]]
    return {**paths, "line": text, "changed": changed}

"""What the diagnosis of a run writes: diagnosis.json, report.md, the figures (PNG) and replay.csv.

report.md, in order: the verdict and summary; where the model and the recording differ (per mount, sensor and
band, before and after); the physics named, each with its parameters, tests, evidence and margins line; the fit
per mount; the floor; the valves' offsets; what this recording can and cannot tell (and what floor accelerometers
would add); the transmissibilities measured against predicted (the paper's Figs. 12-13 from data); rig design
on the diagnosed rig, one line per mount.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from rig.config import MOUNTS
from rig.diagnose.machine.effects import describe
from rig.diagnose.machine.result import CHANNELS, RigDiagnosis
from rig.diagnose.machine.spectra import BANDS_HZ

MODELS = ("nominal", "refit", "augmented")


def _fmt_effect(e) -> str:
    return describe(e.name, e.parameters)


def summary_text(d: RigDiagnosis) -> str:
    what = "; ".join(_fmt_effect(e) for e in d.effects) or "nothing"
    fit = d.fit
    worst = max(MOUNTS, key=lambda m: max(fit["refit"][m].values()))
    txt = (f"{d.source}: {d.duration_s:.0f} s at {d.fs_hz:g} Hz, "
           f"{'floor measured' if d.floor_measured else 'floor NOT measured (estimated from the mounts)'}; "
           f"verdict: {d.verdict}. Named: {what}. Held-out residual over expected at {worst}: accel "
           f"{fit['nominal'][worst]['accel']:.2f} -> {fit['augmented'][worst]['accel']:.2f}, stroke "
           f"{fit['nominal'][worst]['stroke']:.2f} -> {fit['augmented'][worst]['stroke']:.2f} (model -> diagnosed).")
    bad = [line.mount for line in d.margins if not line.diagnosed.holds]
    txt += (" Margins hold on every mount." if not bad else f" Margins do NOT hold at {', '.join(bad)}.")
    return txt


def console_text(d: RigDiagnosis) -> str:
    """What `rig diagnose` prints: the summary, each named effect with its margins line, the fit per mount, the
    margins per mount on the diagnosed rig and, without floor accelerometers, what the run can and cannot tell."""
    s = [summary_text(d)]
    for e in d.effects:
        s.append(f"named: {_fmt_effect(e)}")
        s += [f"  margins with it: {line}" for line in e.margins]
    s.append("fit per mount (held-out residual over expected, 1 = within the noise; model -> refit -> diagnosed):")
    f = d.fit
    s += [f"  {m}: accelerometer {f['nominal'][m]['accel']:.2f} -> {f['refit'][m]['accel']:.2f} -> "
          f"{f['augmented'][m]['accel']:.2f}, stroke {f['nominal'][m]['stroke']:.2f} -> {f['refit'][m]['stroke']:.2f} "
          f"-> {f['augmented'][m]['stroke']:.2f}" for m in MOUNTS]
    s.append("margins per mount on the diagnosed rig (rig design's loop on the refitted model):")
    s += [f"  {line.text()}" for line in d.margins]
    if not d.floor_measured:
        s.append("without floor accelerometers (the floor estimated from the mounts):")
        s += [f"  {x}" for x in _cannot_tell(d)]
        by = {}
        for x in d.detectability:
            by.setdefault(x.effect, []).append(x)
        for name, xs in by.items():
            best = min(xs, key=lambda x: x.smallest)
            s.append(f"  smallest named: {best.text()}" + (f" (at the other {len(xs) - 1} places: report.md)"
                                                          if len(xs) > 1 else ""))
    return "\n".join(s)


def _cannot_tell(d: RigDiagnosis) -> list:
    out = ["cannot be judged: a floor accelerometer's sensitivity, the floor feedforward's input; an "
           "accelerometer's sensitivity only where the floor's estimate cannot take it up"]
    if not d.valves_driven:
        out.append("cannot be told: the valves' delays and deadbands (the valves were not driven: isolation off)")
    never = [f"{x.effect} at {x.location}" for x in d.detectability if not math.isfinite(x.smallest)]
    if never:
        out.append("cannot be told at any size: " + ", ".join(never))
    return out


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def diagnosis_dict(d: RigDiagnosis) -> dict:
    out = {
        "recording": d.source, "rate_hz": d.fs_hz, "seconds": d.duration_s, "floor_measured": d.floor_measured,
        "isolation_modes_s": d.modes, "valves_driven": d.valves_driven, "verdict": d.verdict,
        "summary": summary_text(d),
        "effects": [{"name": e.name, "location": e.location, "parameters": e.parameters, "tests": e.tests,
                     "evidence": e.evidence, "margins": list(e.margins)} for e in d.effects],
        "refit": d.refit, "bands_hz": [list(b) for b in BANDS_HZ], "channels": list(CHANNELS),
        "mismatch": d.mismatch, "located": d.located, "fit": d.fit, "candidates": d.candidates,
        "floor": asdict(d.floor) | {"rocking": d.floor.rocking} if d.floor is not None else None,
        "offsets": [asdict(o) | {"stands_out": o.stands_out} for o in d.offsets], "starts_at_rest": d.starts_at_rest,
        "detectability": [asdict(x) | {"text": x.text()} for x in d.detectability],
        "transmissibility": d.transmissibility,
        "margins": [{"mount": line.mount, "text": line.text(), "trim": line.trim, "meets": line.meets,
                     "nominal": asdict(line.nominal), "diagnosed": asdict(line.diagnosed),
                     "retuned": asdict(line.retuned) if line.retuned else None} for line in d.margins],
        "notes": d.notes, "theta": d.theta, "timing_s": d.timing_s,
    }
    return _jsonable(out)


def _table(rows: list, head: list) -> str:
    out = "| " + " | ".join(head) + " |\n|" + "---|" * len(head) + "\n"
    return out + "\n".join("| " + " | ".join(str(x) for x in r) + " |" for r in rows) + "\n"


def _v(x, fmt=".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def _mismatch_md(d: RigDiagnosis) -> str:
    bands = [f"{lo:g}-{hi:g} Hz" for lo, hi in BANDS_HZ]
    out = ("Held-out residual over what the noise and the model's fidelity leave (1 = the model describes the "
           "channel there), per channel and band.\n\n")
    for k in MODELS:
        out += f"**{k}**\n\n" + _table([[c] + [_v(x, ".1f") for x in row] for c, row in zip(CHANNELS, d.mismatch[k])],
                                      ["channel"] + bands) + "\n"
    if d.located:
        out += "Where the refitted model leaves most: " + "; ".join(
            f"{c['channel']} {c['band_hz'][0]:g}-{c['band_hz'][1]:g} Hz ({c['excess']:.1f}x)" for c in d.located) + "\n\n"
    return out


def report_markdown(d: RigDiagnosis, figures: dict) -> str:
    s = [f"# Diagnosis of {Path(d.source).name}\n",
         f"{d.duration_s:.1f} s at {d.fs_hz:g} Hz; isolation modes: "
         + (", ".join(f"{k} {v:.1f} s" for k, v in d.modes.items()) or "not recorded")
         + f"; floor {'measured' if d.floor_measured else 'not measured (estimated from the mounts)'}; valves "
         + ("driven" if d.valves_driven else "not driven beyond the centring (valve effects cannot be told)") + ".\n",
         f"**Verdict: {d.verdict}.** {summary_text(d)}\n"]
    s += [f"- {n}\n" for n in d.notes]
    s.append("\n## Where the model and the recording differ\n\n" + _mismatch_md(d))
    if "mismatch" in figures:
        s.append(f"![mismatch]({figures['mismatch']})\n\n")
    s.append("## Physics named\n\n")
    if not d.effects:
        s.append("None: the refitted model describes the recording within what the tests can tell.\n\n")
    for e in d.effects:
        t = e.tests
        tests = (f"held-out residual cut {100 * t['holdout_gain']:.1f} %, likelihood ratio {t['lr_holdout']:.0f} "
                 f"(needs {t['lr_needed']:.0f}), fit-bin BIC gain {t['delta_bic_fit']:.0f}" if "lr_holdout" in t
                 else ", ".join(f"{k} {_v(v)}" for k, v in t.items() if k != "passed"))
        s.append(f"### {_fmt_effect(e)}\n\n{e.evidence}. Tests: {tests}.\n\nMargins with this effect:\n\n"
                 + "".join(f"- {line}\n" for line in e.margins) + "\n")
    s.append("## Fit per mount\n\nHeld-out residual over expected, model -> refit -> diagnosed:\n\n")
    s.append(_table([[m] + [f"{d.fit['nominal'][m][k]:.2f} -> {d.fit['refit'][m][k]:.2f} -> "
                            f"{d.fit['augmented'][m][k]:.2f}" for k in ("accel", "stroke")] for m in MOUNTS],
                    ["mount", "accelerometer", "stroke"]) + "\n")
    s.append("Refit (common to the four actuators): " + ", ".join(f"{k} {v:.4g}" for k, v in d.refit.items()) + "\n\n")
    s.append(_floor_md(d))
    s.append(_offsets_md(d))
    s.append(_detect_md(d))
    s.append(_transmissibility_md(d, figures))
    s.append("## rig design on the diagnosed rig\n\nThe configured isolation controller on each mount's loop "
             "(the paper's SISO view, Fig. 11), as diagnosed:\n\n" + "".join(f"- {line.text()}\n" for line in d.margins))
    s.append(f"\nDiagnosis time {d.timing_s:.1f} s. Data: diagnosis.json, replay.csv.\n")
    return "".join(s)


def _floor_md(d: RigDiagnosis) -> str:
    fm = d.floor
    if fm is None:
        return ""
    how = "measured" if fm.measured else "estimated from the mounts (what they cannot tell apart stays unknown)"
    rows = [[k, f"{v * 1e6:.3f}"] for k, v in fm.rms_m.items()]
    verdict = (f"it rocks about {fm.axis}: {fm.ratio:.2f}x twist's power ({fm.z:.0f} standard errors)" if fm.rocking
               else f"no rocking beyond the independent motion the model assumes ({fm.axis} {fm.ratio:.2f}x twist)")
    return (f"## The floor\n\nThe floor's motion ({how}) over its patterns at the mounts, 1-50 Hz: {verdict}.\n\n"
            + _table(rows, ["pattern", "rms (um)"]) + "\n")


def _offsets_md(d: RigDiagnosis) -> str:
    rows = [[o.mount, f"{o.offset_V:+.4f}", f"{o.se_V:.4f}", "yes" if o.stands_out else "no",
             "-" if not math.isfinite(o.start_m) else f"{o.start_m * 1e9:.1f}"] for o in d.offsets]
    start = ("The run starts at rest (valves at null): a stroke transducer's zero would read at the start."
             if d.starts_at_rest else "The recording does not start at rest: a valve's null offset and a stroke "
             "transducer's zero cannot be told apart.")
    return ("## The valves' null offsets\n\nThe command each mount holds to stay centred, as a valve offset "
            f"(stroke / static gain - command). {start}\n\n"
            + _table(rows, ["mount", "offset (V)", "std. error (V)", "stands out", "stroke at start (nm)"]) + "\n")


def _detect_md(d: RigDiagnosis) -> str:
    s = ["## What this recording can and cannot tell\n\nThe smallest size of each effect the tests would name, "
         "with this recording's inputs and noise"
         + (" (and with floor accelerometers fitted, the floor taken as estimated)" if not d.floor_measured else "")
         + ":\n\n"]
    can = [x for x in d.detectability if math.isfinite(x.smallest)]
    never = [x for x in d.detectability if not math.isfinite(x.smallest)]
    s += [f"- {x.text()}\n" for x in can]
    if never:
        s.append("- cannot be told at any size: " + ", ".join(f"{x.effect} at {x.location}" for x in never) + "\n")
    if not d.floor_measured:
        s += [f"- without floor accelerometers, {x}\n" for x in _cannot_tell(d)[:1]]
    if not d.valves_driven:
        s.append("- the valves were not driven (isolation off): the valves' delays and deadbands cannot be told\n")
    return "".join(s) + "\n"


def _transmissibility_md(d: RigDiagnosis, figures: dict) -> str:
    tr = d.transmissibility
    bands = [f"{lo:g}-{hi:g}" for lo, hi in tr["bands_hz"]]
    s = [f"## Transmissibility per mount and band (the paper's Figs. 12-13 from data)\n\nThe mount's motion over "
         f"the floor's at that mount (dB), measured and predicted in closed loop with the configured controllers; "
         f"floor {tr['floor']}.\n\n"]
    for m in MOUNTS:
        for mode, row in tr["mounts"][m].items():
            s.append(f"**{m}, {mode.replace('_', ' + ')}**\n\n" + _table(
                [[k.replace("_db", "")] + [_v(x, ".1f") for x in v] for k, v in row.items()], ["", *bands]) + "\n")
    if "transmissibility" in figures:
        s.append(f"![transmissibility]({figures['transmissibility']})\n\n")
    return "".join(s)


def write_outputs(out: Path, d: RigDiagnosis, series=None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    figures = plots(out, d)
    paths = {"json": out / "diagnosis.json", "md": out / "report.md"}
    paths["json"].write_text(json.dumps(diagnosis_dict(d), indent=1))
    paths["md"].write_text(report_markdown(d, figures))
    if series is not None:
        paths["csv"] = out / "replay.csv"
        write_series(paths["csv"], series)
    paths.update({k: out / v for k, v in figures.items()})
    return paths


def write_series(path: Path, series: dict) -> None:
    cols = list(series)
    data = np.column_stack([series[c] for c in cols])
    np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.7g")


def plots(out: Path, d: RigDiagnosis) -> dict:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figs = {}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), sharey=True)
    for ax, k in zip(axes, MODELS):
        a = np.array([[np.nan if x is None else x for x in row] for row in d.mismatch[k]])
        im = ax.imshow(np.log10(np.maximum(a, 0.1)), vmin=-0.3, vmax=2, cmap="magma_r", aspect="auto")
        ax.set_xticks(range(len(BANDS_HZ)), [f"{lo:g}-{hi:g}" for lo, hi in BANDS_HZ], rotation=45, fontsize=7)
        ax.set_yticks(range(len(CHANNELS)), CHANNELS, fontsize=8)
        ax.set_title(f"{k}: held-out residual / expected")
        for (i, j), v in np.ndenumerate(a):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.1f}", ha="center", va="center", fontsize=6)
    fig.colorbar(im, ax=axes, label="log10 residual / expected")
    figs["mismatch"] = "mismatch.png"
    fig.savefig(out / figs["mismatch"], dpi=90)
    plt.close(fig)
    tr = d.transmissibility
    if any(tr["mounts"][m] for m in MOUNTS):
        fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex=True, sharey=True)
        centres = [math.sqrt(lo * hi) for lo, hi in tr["bands_hz"]]
        colours = {"off": "C0", "feedback": "C1", "feedback_feedforward": "C2", "recorded": "C3"}
        for ax, m in zip(axes.ravel(), MOUNTS):
            for mode, row in tr["mounts"][m].items():
                c = colours.get(mode, "k")
                ax.semilogx(centres, [np.nan if x is None else x for x in row["measured_db"]], "o", color=c,
                            label=f"{mode}: measured")
                ax.semilogx(centres, [np.nan if x is None else x for x in row["model_db"]], ":", color=c,
                            label=f"{mode}: model")
                ax.semilogx(centres, [np.nan if x is None else x for x in row["diagnosed_db"]], "-", color=c,
                            label=f"{mode}: diagnosed")
            ax.set_title(m)
            ax.grid(True, which="both", alpha=0.3)
            ax.set_ylabel("mount / floor (dB)")
        axes[1, 0].set_xlabel("band centre (Hz)")
        axes[1, 1].set_xlabel("band centre (Hz)")
        axes[0, 0].legend(fontsize=7)
        fig.suptitle("Transmissibility floor -> mount per band: measured, model, diagnosed")
        figs["transmissibility"] = "transmissibility.png"
        fig.savefig(out / figs["transmissibility"], dpi=90)
        plt.close(fig)
    return figs

"""`rig design`: closed-loop analysis of the isolation controllers and the floor feedforward on the discrete
loop (paper Figs. 4, 10-14, and beyond the paper).

Per mount (the paper's SISO view, Fig. 5: that mount's loop closed, the other valves nulled, ground moving at
that mount): stability, classic and disk margins, attenuation of ground -> table and ground -> tool (Y).
All four loops at once (MIMO): stability, and the transmissibility for floor motion that is the same at every
mount and for independent motion at each, with feedback, feedforward and both. Robustness: all four loops on
plants with every actuator's gain +-30 % and every machine mode's frequency +-10 %; the feedforward with the
plant's actuator parameters +-10 % off its model. A linear prediction of `rig demo`'s figure.

--identified DIR: the actuator of `rig identify --out DIR` (DIR/identify.json) replaces the configured one
(Table 1): the feedforward is designed on it and the feedback checked on it. --tune: retune the feedback
(controllers/tune.py) first and analyse the tuned design (written to DIR/controller.toml with --out).
The analysis evaluates the very controller objects the runtime steps (controllers/isolation.py,
controllers/feedforward.py), with the ZOH and one period of computation delay (controllers/analysis.py).

On a stand layout (`--layout prototype`, [layout] plant = "stand") the report is the prototype's two loops
(rig/commands/prototype_design.py): tracking and isolation on the stand, with --identified and --tune.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

# Hundreds of small eigenvalue problems (~110 states): OpenBLAS threads only contend for them (measured on the
# shared 2-core machine: 8 ms with one thread, 117 ms with two). Set before numpy loads, for the CLI.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from rig import cliargs
from rig.config import check_actuator_value
from rig.errors import RigError

PAPER = {  # Law et al. 2015, text of Figs. 11-13
    "gain_margin_db": "4-14", "phase_margin_deg": "30-36", "gain_crossover_hz": "215-221",
    "phase_crossover_hz": "~397",
    "table": {"1hz": "~25", "5_10hz": "~10", "20_60hz": "5-10", "60_100hz": "~4 front, ~6 rear"},
    "tool": {"1hz": "~20", "5_10hz": "~10", "20_60hz": "~7-10 (26 Hz, 45 Hz modes)",
             "60_100hz": "~5 front, ~7 rear"},
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write the figures (PNG), design.md (beside the paper's numbers) and design.json")
    p.add_argument("--identified", metavar="DIR", type=Path, default=None,
                   help="design on the actuator identified by `rig identify --out DIR` (DIR/identify.json) "
                        "instead of the configured one")
    p.add_argument("--tune", action="store_true",
                   help="retune the feedback first (structured optimiser, controllers/tune.py; ~1-2 min; "
                        "--layout prototype: both stand loops, controllers/prototype.py)")
    p.add_argument("--starts", type=cliargs.count(1, 200), default=8, metavar="N",
                   help="optimiser starts with --tune (default 8)")
    p.add_argument("--robust", type=cliargs.count(0, 100000), default=100, metavar="N",
                   help="random plants in the robustness check, besides its 48 corners (default 100)")
    p.add_argument("--layout", choices=("machine", "prototype"), default=None,
                   help="prototype: the actuator on its stand, tracking and isolation (rig/commands/prototype_design.py;"
                        " --identified and --tune apply to it too)")


def _clean(v):
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def load_identified(cfg, folder: Path):
    """cfg with the six identified actuator parameters of DIR/identify.json (`rig identify --out DIR`)."""
    from controllers.analysis import ACTUATOR_KEYS, with_actuator
    path = folder / "identify.json"
    if not folder.is_dir():
        raise RigError(f"--identified {folder}: not a folder (expected the --out folder of rig identify)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RigError(f"--identified {folder}: no identify.json in it (write it with rig identify REC --out "
                       f"{folder})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise RigError(f"{path}: cannot read it as JSON ({e})") from None
    par = data.get("parameters") if isinstance(data, dict) else None
    if not isinstance(par, dict):
        raise RigError(f"{path}: 'parameters': expected an object with {', '.join(ACTUATOR_KEYS)}")
    vals = {}
    for k in ACTUATOR_KEYS:
        v = par.get(k)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise RigError(f"{path}: parameters.{k}: expected a positive number, got {v!r}")
        vals[k] = check_actuator_value(f"{path}: parameters", k, float(v))     # within [actuator]/[valve]'s range
    return with_actuator(cfg, **vals), vals, str(path)


def run(args) -> int:
    import dataclasses
    from rig.commands.run import layout_config
    cfg = layout_config(args)
    dt = 1.0 / cfg.loop.rate_hz
    log = (lambda s: print(f"rig design: {s}", file=sys.stderr, flush=True))
    if args.starts < 1:
        raise RigError(f"--starts: expected >= 1, got {args.starts}")
    if args.robust < 0:
        raise RigError(f"--robust: expected >= 0 random plants, got {args.robust}")
    model = {"actuator": "configured ([actuator], [valve]: Table 1 unless the config says otherwise)"}
    if args.identified is not None:
        cfg, vals, src = load_identified(cfg, args.identified)
        model = {"actuator": f"identified ({src})", "parameters": vals}
        log(f"actuator from {src}: " + ", ".join(f"{k} {v:.4g}" for k, v in vals.items()))
    if cfg.layout.plant == "stand":                      # the prototype's loops (its own module)
        from rig.commands import prototype_design
        return prototype_design.run(args, cfg, model)
    from controllers.analysis import (ACTUATOR_KEYS, DiscreteRig, design_report, model_error_check, predicted_rms,
                                      robust_check, sensitivity_integral, with_actuator)
    from controllers.feedforward import feedforward_params_from_config, make_feedforward_filters
    from controllers.isolation import make_isolation_controllers, params_from_config
    tuned = None
    if args.tune:
        from controllers.tune import tune
        log(f"tuning the feedback ({args.starts} starts; structured SLSQP, controllers/tune.py)")
        res = tune(cfg, dt, params_from_config(cfg), starts=args.starts, log=log)
        cfg = cfg.replace(controller=dataclasses.replace(cfg.controller, **{k: getattr(res.params, k) for k in
                                                                            _tuned_keys()}))
        tuned = {"toml": res.toml(), "worst_excess_db": res.worst_excess_db, "seconds": res.seconds,
                 "starts": res.starts}
        log(f"tuned in {res.seconds:.0f} s: worst band excess over the paper {res.worst_excess_db:+.2f} dB")
    log(f"discretising the rig at {cfg.loop.rate_hz:g} Hz (ZOH + 1 period computation delay)")
    rig = DiscreteRig(cfg, dt)
    ctrls = make_isolation_controllers(cfg, dt)
    ffs = make_feedforward_filters(cfg, dt)
    log("closing each mount's loop (SISO) and all four (MIMO), with and without the feedforward")
    rep = design_report(cfg, ctrls, dt, rig, ffs=ffs)
    data = rep.pop("_data")
    rep["sensitivity_integral"] = {m: sensitivity_integral(rig.f, data["siso"][m]["L"]) for m in rep["mounts"]}
    log(f"robustness: all four loops on {48 + args.robust} plants (actuator gains +-30 %, mode frequencies "
        f"+-10 %)")
    rep["robust"] = robust_check(cfg, dt, ctrls, n_random=args.robust, log=log)
    log("feedforward with the plant's actuator parameters +-10 % off its model (64 plants)")
    rep["feedforward"] = {"params": dataclasses.asdict(feedforward_params_from_config(cfg)),
                          "lead_s": ffs[0].tau_s, "model_error": model_error_check(cfg, dt, ctrls, ffs, log=log)}
    worst = rep["feedforward"]["model_error"]["worst_plant_factors"]
    off = with_actuator(cfg, **{k: getattr(cfg.actuator if ACTUATOR_KEYS[k] == "actuator" else cfg.valve, k) * x
                                for k, x in worst.items()})
    rep["predicted_demo"] = {"feedback": predicted_rms(cfg, dt, ctrls),
                             "feedback_feedforward": predicted_rms(cfg, dt, ctrls, ffs),
                             "feedback_feedforward_model_error": dict(predicted_rms(off, dt, ctrls, ffs),
                                                                     plant_factors=worst)}
    rep["predicted_vc"] = predicted_vc(cfg, dt, ctrls, ffs)
    from controllers.tune import Problem
    rep["tuning_slack"] = Problem(cfg, dt, params_from_config(cfg)).slack(params_from_config(cfg))
    rep["paper_targets_db"] = _targets()
    rep["meets_paper"] = _meets(rep)
    rep["design_model"] = model
    if tuned:
        rep["tuned"] = tuned
    result = _clean(rep)
    if not args.json:                        # the figures on stdout, the progress above on stderr
        print("\n".join(summary_lines(result)), flush=True)
    if args.out is not None:
        cliargs.make_out_dir(args.out)
        from controllers import figures
        files = figures.write_all(args.out, cfg, dt, rig, ctrls, data, result, PAPER, log, ffs=ffs)
        full = dict(result, controller={k: getattr(cfg.controller, k) for k in cfg.controller.__dataclass_fields__})
        (args.out / "design.json").write_text(json.dumps(_clean(full), indent=2, default=list))
        if tuned:
            (args.out / "controller.toml").write_text(tuned["toml"] + "\n")
        log(f"wrote {len(files) + 1 + bool(tuned)} files to {args.out}")
    if tuned and not args.json:
        print(tuned["toml"])
    if args.json:
        print(json.dumps(result, indent=2))
    ok = all(r["stable"] for r in result["mounts"].values()) and result["mimo_stable"]
    return 0 if ok else 1


def predicted_vc(cfg, dt, ctrls, ffs) -> dict:
    """The table's one-third-octave rms velocity predicted by the linear model under the configured floor
    (isolation off, feedback, feedback + feedforward) and the vibration criterion each meets."""
    import numpy as np
    from controllers.analysis import predicted_table_psd
    from controllers.vibration_criteria import band_velocity_rms_from_psd, vc_class
    fp = np.geomspace(0.8, 120.0, 1500)
    rep = {"band_hz": None, "velocity_um_s": {}, "vc_class": {}}
    for lab, c, ff in (("off", None, None), ("feedback", ctrls, None), ("feedback + feedforward", ctrls, ffs)):
        psd = predicted_table_psd(cfg, dt, c, ff, fp)
        fc, v = band_velocity_rms_from_psd(fp, psd["passive"] if c is None else psd["controlled"])
        rep["band_hz"] = [float(x) for x in fc]
        rep["velocity_um_s"][lab] = [float(x) for x in v * 1e6]
        rep["vc_class"][lab] = vc_class(v * 1e6, fc)
    return rep


def _tuned_keys():
    from controllers.tune import KEYS
    return KEYS


def _targets() -> dict:
    """The paper's Fig. 12 figures the tuner aims at, per mount and band (dB)."""
    from controllers.tune import PAPER_TABLE_TARGETS
    from rig.config import MOUNTS
    return {"ground_to_table": {m: {b: t[2][i] for b, t in PAPER_TABLE_TARGETS.items()}
                                for i, m in enumerate(MOUNTS)}}


def _meets(rep) -> dict:
    """Whether every mount is at or above the paper in every band, with GM >= 6 dB and PM >= 35 deg."""
    tg = _targets()["ground_to_table"]
    att = rep["attenuation_db"]["ground_to_table"]
    bands = all(att[m][b] >= t - 1e-9 for m in tg for b, t in tg[m].items())
    marg = all(r["gain_margin_db"] >= 6.0 and r["phase_margin_deg"] >= 35.0 for r in rep["mounts"].values())
    return {"bands": bands, "margins": marg, "robust": bool(rep["robust"]["all_stable"])}


def _yes(v: bool) -> str:
    return "yes" if v else "NO"


def verdict(result) -> str:
    """Whether the design meets the paper, in words: what holds and what does not."""
    m, rb = result["meets_paper"], result["robust"]
    parts = [("every mount at or above the paper's attenuation in every band" if m["bands"] else
              "a mount below the paper's attenuation in a band (see the lines above)"),
             ("GM >= 6 dB and PM >= 35 deg on every mount" if m["margins"] else
              "a mount's margins below GM 6 dB or PM 35 deg"),
             (f"all {rb['corners'] + rb['random']} plants of the robustness check stable" if m["robust"] else
              f"unstable on some of the {rb['corners'] + rb['random']} plants of the robustness check")]
    ok = all(m.values())
    return f"meets the paper: {'yes' if ok else 'NO'}: " + "; ".join(parts)


def summary_lines(result) -> list[str]:
    """The design's figures, one line each, ending with the verdict in words."""
    lines = []
    for m, r in result["mounts"].items():
        t = result["attenuation_db"]["ground_to_table"][m]
        lines.append(f"{m:11s} stable: {_yes(r['stable'])}, GM {r['gain_margin_db']:.1f} dB, PM "
                     f"{r['phase_margin_deg']:.1f} deg, disk {r['disk_margin']:.2f}, gc {r['gain_crossover_hz']:.0f} "
                     f"Hz | table 1 Hz {t['1hz']:.1f}, 5-10 Hz {t['5_10hz']:.1f}, 20-60 Hz {t['20_60hz']:.1f}, "
                     f"60-100 Hz {t['60_100hz']:.1f} dB")
    for tag in ("feedback", "feedforward", "feedback_feedforward"):
        v = result["mimo"].get(tag)
        if v:
            lines.append(f"all four loops, {tag.replace('_', ' + ')}: table min 1-100 Hz uniform floor "
                         f"{v['uniform']['ground_to_table']['min_1_100hz']:.1f} dB, independent "
                         f"{v['independent']['ground_to_table']['min_1_100hz']:.1f} dB")
    rb = result["robust"]
    lines.append(f"robust: {rb['corners'] + rb['random']} plants, all stable: {_yes(rb['all_stable'])}, worst "
                 f"multiloop disk margin {rb['worst_disk_margin_mimo']:.2f}, worst SISO GM {rb['worst_siso_gm_db']:.1f} "
                 f"dB PM {rb['worst_siso_pm_deg']:.1f} deg")
    w = result["feedforward"]["model_error"]["worst_attenuation_db"]["feedback_feedforward"]["uniform"]
    lines.append(f"feedback + feedforward, actuator +-10 % off the model: worst min 1-100 Hz {w['min_1_100hz']:.1f} dB")
    pd = result["predicted_demo"]
    lines.append(f"predicted demo (table rms 1-100 Hz, same floor): feedback {pd['feedback']['reduction_db']:.1f} dB, "
                 f"with feedforward {pd['feedback_feedforward']['reduction_db']:.1f} dB (nominal model), "
                 f"{pd['feedback_feedforward_model_error']['reduction_db']:.1f} dB (actuator +-10 % off, worst corner)")
    lines.append(verdict(result))
    return lines

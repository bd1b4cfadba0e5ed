"""`rig design`: closed-loop analysis of the isolation controllers on the discrete loop (paper Figs. 4, 10-14).

Per mount (the paper's SISO view, Fig. 5: that mount's loop closed, the other valves nulled, ground moving at
that mount): stability, gain/phase margins and crossovers, attenuation of ground -> table and ground -> tool
(Y). All four loops at once (MIMO): stability and the transmissibilities for uniform ground. The analysis
evaluates the very controller objects the runtime steps (controllers/isolation.py), with the ZOH and one
period of computation delay (controllers/analysis.py).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

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
    p.add_argument("--out", metavar="DIR", type=Path, default=None,
                   help="write the figures (PNG), design.md (beside the paper's numbers) and design.json")
    p.add_argument("--layout", choices=("machine", "prototype"), default=None,
                   help="prototype: the actuator on its stand, tracking and isolation (rig/commands/prototype_design.py)")


def _clean(v):
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def run(args) -> int:
    from rig.commands.run import layout_config
    cfg = layout_config(args)
    if cfg.layout.plant == "stand":                      # the prototype's loops (its own module)
        from rig.commands import prototype_design
        return prototype_design.run(args, cfg)
    dt = 1.0 / cfg.loop.rate_hz
    log = (lambda s: print(f"rig design: {s}", file=sys.stderr, flush=True))
    from controllers.analysis import DiscreteRig, design_report, mimo_summary
    from controllers.isolation import make_isolation_controllers
    log(f"discretising the rig at {cfg.loop.rate_hz:g} Hz (ZOH + 1 period computation delay)")
    rig = DiscreteRig(cfg, dt)
    ctrls = make_isolation_controllers(cfg, dt)
    log("closing each mount's loop (SISO) and all four (MIMO)")
    rep = design_report(cfg, ctrls, dt, rig)
    data = rep.pop("_data")
    result = _clean(rep)
    mimo = _clean(mimo_summary(rig, data["mimo"]))
    for m, r in result["mounts"].items():
        t = result["attenuation_db"]["ground_to_table"][m]
        q = result["attenuation_db"]["ground_to_tool"][m]
        log(f"{m:11s} stable={r['stable']} GM {r['gain_margin_db']:.1f} dB PM {r['phase_margin_deg']:.1f} deg "
            f"gc {r['gain_crossover_hz']:.0f} Hz pc {r['phase_crossover_hz']:.0f} Hz | table 1 Hz "
            f"{t['1hz']:.1f} dB min 1-100 Hz {t['min_1_100hz']:.1f} dB | tool 1 Hz {q['1hz']:.1f} dB "
            f"min {q['min_1_100hz']:.1f} dB")
    log(f"MIMO (all four loops) stable={result['mimo_stable']}; uniform ground: table min 1-100 Hz "
        f"{mimo['uniform']['ground_to_table']['min_1_100hz']:.1f} dB, tool "
        f"{mimo['uniform']['ground_to_tool']['min_1_100hz']:.1f} dB")
    if args.out is not None:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RigError(f"--out {args.out}: cannot create directory ({e})") from None
        from controllers import figures
        files = figures.write_all(args.out, cfg, dt, rig, ctrls, data, result, mimo, PAPER, log)
        full = dict(result, mimo=mimo, controller={k: getattr(cfg.controller, k) for k in
                                                   cfg.controller.__dataclass_fields__})
        (args.out / "design.json").write_text(json.dumps(_clean(full), indent=2, default=list))
        log(f"wrote {len(files) + 1} files to {args.out}")
    if args.json:
        print(json.dumps(result, indent=2))
    ok = all(r["stable"] for r in result["mounts"].values()) and result["mimo_stable"]
    return 0 if ok else 1

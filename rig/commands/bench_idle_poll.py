"""`rig bench idle-poll`: `rig hil` with idle CPUs kept polling and without, alternating in one run.

  rig bench idle-poll [--config FILE] [--rate HZ] [--rounds R] [--seconds N] [--json]

R rounds of two HIL runs of N seconds each (the config as `rig hil` takes it, default its 500 Hz one), one with
`[loop] idle_poll = "on"` and one with "off", in the order on-off, off-on, ... so that a drifting shared machine
falls on both alike. Per setting: each run's late periods per isolation mode (the loop woke a period late or
no new accelerometer conversion), its faults, and the isolation through the drivers and in lockstep. What the
pollers do and why: rig/runtime/idle_poll.py. --json prints {"config", "rate_hz", "seconds", "rounds",
"cpuidle_driver", "runs": {"on": [...], "off": [...]}, "median_late": {"on", "off"}} (each run: "late", "faults",
"fault_reason", "feedback_db", "feedforward_db", "lockstep_db").
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import statistics
import sys
import tempfile

from rig import cliargs
from rig.config import load_config
from rig.runtime import idle_poll


def add_arguments(p) -> None:
    p.add_argument("--rate", type=cliargs.rate_hz(le=5000), default=None, metavar="HZ",
                   help="loop rate (default: the config's [hil] rate_hz)")
    p.add_argument("--rounds", type=cliargs.count(1, 50), default=2, help="pairs of runs (default 2)")
    p.add_argument("--seconds", type=cliargs.seconds(ge=3, le=600), default=12.0, metavar="N",
                   help="seconds of each run (default 12)")
    p.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def _one(cfg, seconds: float, setting: str) -> dict:
    from rig.commands.hil import run_hil          # lazy: the drivers' stack only when the bench runs
    cfg = cfg.replace(loop=dataclasses.replace(cfg.loop, idle_poll=setting))
    with tempfile.TemporaryDirectory(prefix="rig-bench-idle-") as d:
        res = run_hil(cfg, seconds, record=os.path.join(d, "hil.h5"), quiet=True)
    late = res.get("late_periods") or {}
    ls = res.get("lockstep_reduction_db") or {}
    return {"late": late, "faults": res["faults"], "fault_reason": res["fault_reason"],
            "feedback_db": res["isolation_reduction_db"], "feedforward_db": res["feedforward_reduction_db"],
            "lockstep_db": ls}


def _worst(run: dict) -> float:
    vals = [v for v in run["late"].values() if v is not None]
    return max(vals) if vals else math.nan


def run(args) -> int:
    from rig.commands.hil import HIL_DEFAULT_CONFIG, hil_config
    cfg = hil_config(load_config(getattr(args, "config", None) or HIL_DEFAULT_CONFIG), args.rate)
    say = (lambda m: None) if args.json else (lambda m: print(f"rig bench idle-poll: {m}", file=sys.stderr))
    runs: dict[str, list] = {"on": [], "off": []}
    say(f"{cfg.source} at {cfg.loop.rate_hz:g} Hz, {args.rounds} rounds of {args.seconds:g} s with idle CPUs polling "
        f"and not (cpuidle driver: {idle_poll.driver()})")
    for r in range(args.rounds):
        for setting in (("on", "off") if r % 2 == 0 else ("off", "on")):
            one = _one(cfg, args.seconds, setting)
            runs[setting].append(one)
            say(f"round {r + 1}, idle_poll {setting}: " + _line(one))
    med = {k: _median([_worst(x) for x in v]) for k, v in runs.items()}
    out = {"config": str(cfg.source), "rate_hz": cfg.loop.rate_hz, "seconds": args.seconds, "rounds": args.rounds,
           "cpuidle_driver": idle_poll.driver(), "runs": runs, "median_late": med}
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    for k in ("on", "off"):
        print(f"idle_poll {k:3s}: late periods (worst mode per run) median {_pct(med[k])}; runs: "
              + " | ".join(_line(x) for x in runs[k]))
    return 0


def _median(xs) -> float | None:
    xs = [x for x in xs if not math.isnan(x)]
    return round(statistics.median(xs), 4) if xs else None


def _pct(x) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.1f} %"


def _line(one: dict) -> str:
    late = ", ".join(f"{m} {_pct(v)}" for m, v in one["late"].items())
    ls = one["lockstep_db"]
    iso = (f"feedback {one['feedback_db']} dB (lockstep {ls.get('feedback')})"
           if one["feedback_db"] is not None else "no isolation figure")
    if one["feedforward_db"] is not None:
        iso += f", feedback + feedforward {one['feedforward_db']} dB (lockstep {ls.get('feedback_feedforward')})"
    fault = f"FAULT: {one['fault_reason']}" if one["faults"] else "0 faults"
    return f"late {late or 'n/a'}; {iso}; {fault}"

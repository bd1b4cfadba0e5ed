"""`rig bench cli`: how long the command line takes to answer --help, against a bare interpreter start,
measured alternately in one run (the machine's load moves both alike)."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np

from rig import cliargs

CASES = {"python -c pass": ["-c", "pass"], "rig --help": ["-m", "rig.cli", "--help"],
         "rig run --help": ["-m", "rig.cli", "run", "--help"],
         "rig identify --help": ["-m", "rig.cli", "identify", "--help"]}


def add_arguments(p) -> None:
    p.add_argument("--rounds", type=cliargs.count(1, 1000), default=5, help="rounds of every case, alternating (default 5)")
    p.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def run(args) -> int:
    times: dict[str, list[float]] = {k: [] for k in CASES}
    for r in range(max(1, args.rounds)):
        for name, argv in CASES.items():
            t0 = time.perf_counter()
            subprocess.run([sys.executable, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
            times[name].append(time.perf_counter() - t0)
        print(f"rig bench cli: round {r + 1} of {args.rounds}", file=sys.stderr, flush=True)
    base = float(np.median(times["python -c pass"]))
    res = {name: {"median_s": float(np.median(t)), "min_s": min(t), "max_s": max(t),
                  "median_over_bare_python": float(np.median(t)) / base} for name, t in times.items()}
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"{'':22s}{'median':>10s}{'min':>10s}{'max':>10s}  over a bare python start")
    for name, r in res.items():
        print(f"{name:22s}{r['median_s']:9.3f}s{r['min_s']:9.3f}s{r['max_s']:9.3f}s  {r['median_over_bare_python']:.2f}x")
    return 0

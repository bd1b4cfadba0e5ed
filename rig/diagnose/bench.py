"""Speed of the diagnosis engine: `python -m rig.diagnose.bench [--cases DIR] [--habits N] [RECORDING ...]`.

--cases DIR   the recordings of DIR (a folder with answers.json, as `rig prove --cases`) plus the same cases
              re-simulated at 2 kHz, 100 s each;
--habits N    N blind cases with the habits of real recordings (`rig prove --habits`), each 100 s at 2 kHz;
RECORDING     any recordings;
--only I      only the I-th of those cases (from 0): one case a process, to compare two versions case by case,
              alternately (docs/PROOFS.md, "Speed of the eha diagnosis").
The issue's budget: median 15 s, worst 30 s per 100 s recording at 2 kHz on 2 cores. Prints wall and CPU time
per recording, the machine's load average before and after, and p50/p99/max of the wall time per 100 s (CPU
time is the figure to compare when other work shares the machine).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from rig.diagnose import catalogue, prove
from rig.diagnose.engine import diagnose
from rig.recordings.recording import Recording
from rig.recordings.rigformat import load_recording
from sim_backend.actuator import linear_chirp, simulate_stand
from sim_backend.linear import ActuatorParams


def _folder_cases(folder: Path):
    prove.read_answers(folder)                    # checks the folder (one line naming what is wrong)
    ans = json.loads((folder / "answers.json").read_text())
    for name in sorted(ans):
        yield name, lambda name=name: load_recording(folder / name)

    def at_2khz(name):                              # the same physics at 2 kHz
        a = ans[name]
        p = ActuatorParams().with_(**a["true_linear_parameters"])
        t, cmd = linear_chirp(2000.0, 100.0, 0.1, 100.0, a["amplitude_V"])
        fx = catalogue.stand_effects(a["effects"], position_noise_m=2e-8, accel_noise_mps2=2e-4, seed=1)
        y = simulate_stand(p, cmd, 2000.0, fx)
        return Recording.from_signals(cmd, y["position_m"], y["accel_mps2"], fs_hz=2000.0, source=name)
    for name in sorted(ans):
        yield name.split(".")[0] + "@2kHz", lambda name=name: at_2khz(name)


def _habit_cases(n: int, seed: int = 5):
    for c in prove.draw_cases(n, seed, duration_s=200.0, habits=True):
        c = replace(c, fs_hz=2000.0, duration_s=100.0)
        yield f"{c.name}@2kHz ({c.excitation['kind']})", lambda c=c: prove.simulate_case(c)


def _cases(args):
    """(name, a function making its recording): made only when it is diagnosed."""
    for path in args.recordings:
        yield path.name, lambda path=path: load_recording(path)
    if args.cases is not None:
        yield from _folder_cases(args.cases)
    if args.habits:
        yield from _habit_cases(args.habits)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m rig.diagnose.bench", description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="*", type=Path, metavar="RECORDING")
    ap.add_argument("--cases", type=Path, metavar="DIR", help="a folder with answers.json (rig prove --cases)")
    ap.add_argument("--habits", type=int, default=0, metavar="N", help="N habit cases, 100 s at 2 kHz")
    ap.add_argument("--only", type=int, default=None, metavar="I", help="only the I-th case (from 0)")
    args = ap.parse_args(argv)
    if not (args.recordings or args.cases or args.habits):
        ap.error("give recordings, --cases DIR or --habits N")
    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores; other work on the machine slows this down)")
    per100 = []
    diagnose(Recording.from_signals(*linear_chirp(1000.0, 5.0)[1:], np.zeros(5000) + np.linspace(0, 1e-6, 5000),
                                    fs_hz=1000.0), ActuatorParams())       # JIT warm-up
    for i, (name, make) in enumerate(_cases(args)):
        if args.only is not None and i != args.only:
            continue
        rec = make()
        w0, c0 = time.perf_counter(), time.process_time()
        d = diagnose(rec, ActuatorParams())
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        per100.append((wall * 100.0 / rec.duration_s, cpu * 100.0 / rec.duration_s))
        print(f"{name:32s} fs {rec.fs_hz:6.0f} Hz  wall {wall:6.2f} s  cpu {cpu:6.2f} s  named {d.names() or ['none']}",
              flush=True)
    if not per100:
        ap.error(f"--only {args.only}: there are only {i + 1} cases (numbered from 0)")
    v = np.array(per100)
    for col, what in ((0, "wall"), (1, "cpu")):
        print(f"{what} per 100 s of recording: p50 {np.percentile(v[:, col], 50):.2f} s  "
              f"p99 {np.percentile(v[:, col], 99):.2f} s  max {v[:, col].max():.2f} s  (n = {len(v)})")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

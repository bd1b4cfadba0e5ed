"""Speed of the diagnosis engine: `python -m rig.diagnose.bench [--habits N] [RECORDING ...]`.

Without recordings: the shared recordings (../shared/recordings) plus the same seven cases re-simulated at 2 kHz,
and with --habits N also N blind cases with the habits of real recordings (rig prove --habits), each 100 s at
2 kHz (the issue's budget: median 15 s, worst 30 s per 100 s recording at 2 kHz on 2 cores). Prints wall and CPU
time per recording, the machine's load average before and after, and p50/p99/max of the wall time per 100 s.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from rig.diagnose.engine import diagnose
from rig.recording import Recording, load_recording
from sim_backend.actuator import Effects, linear_chirp, simulate_stand
from sim_backend.linear import ActuatorParams

SHARED = Path(__file__).resolve().parents[3] / "shared" / "recordings"


def _cases(args: list[str]):
    if args:
        for a in args:
            yield Path(a).name, load_recording(a)
        return
    ans = json.loads((SHARED / "answers.json").read_text())
    for name in sorted(ans):
        yield name, load_recording(SHARED / name)
    for name in sorted(ans):                       # the same physics at 2 kHz
        a = ans[name]
        p = ActuatorParams().with_(**a["true_linear_parameters"])
        t, cmd = linear_chirp(2000.0, 100.0, 0.1, 100.0, a["amplitude_V"])
        fx = Effects.from_catalogue(a["effects"], position_noise_m=2e-8, accel_noise_mps2=2e-4, seed=1)
        y = simulate_stand(p, cmd, 2000.0, fx)
        yield name.split(".")[0] + "@2kHz", Recording.from_signals(cmd, y["position_m"], y["accel_mps2"],
                                                                   fs_hz=2000.0, source=name)


def _habit_cases(n: int, seed: int = 5):
    from dataclasses import replace
    from rig.diagnose import prove
    for c in prove.draw_cases(n, seed, duration_s=200.0, habits=True):
        c = replace(c, fs_hz=2000.0, duration_s=100.0)
        yield f"{c.name}@2kHz ({c.excitation['kind']})", prove.simulate_case(c)


def main(argv: list[str]) -> int:
    import os
    n_habits = 0
    if argv[:1] == ["--habits"]:
        n_habits, argv = int(argv[1]), argv[2:]
    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores; other work on the machine slows this down)")
    per100 = []
    diagnose(Recording.from_signals(*linear_chirp(1000.0, 5.0)[1:], np.zeros(5000) + np.linspace(0, 1e-6, 5000),
                                    fs_hz=1000.0), ActuatorParams())       # JIT warm-up
    from itertools import chain
    cases = _cases(argv) if argv or not n_habits else chain(_cases(argv), _habit_cases(n_habits))
    for name, rec in cases:
        w0, c0 = time.perf_counter(), time.process_time()
        d = diagnose(rec, ActuatorParams())
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        per100.append(wall * 100.0 / rec.duration_s)
        print(f"{name:32s} fs {rec.fs_hz:6.0f} Hz  wall {wall:6.2f} s  cpu {cpu:6.2f} s  named {d.names() or ['none']}",
              flush=True)
    v = np.array(per100)
    print(f"wall per 100 s of recording: p50 {np.percentile(v, 50):.2f} s  p99 {np.percentile(v, 99):.2f} s  "
          f"max {v.max():.2f} s  (n = {len(v)}); load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

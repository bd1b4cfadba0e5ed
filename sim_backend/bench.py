"""Simulation-speed benchmarks (figures, never pass/fail): `rig bench sim`."""
from __future__ import annotations

import sys
import time

import numpy as np

from rig.config import Config
from sim_backend.actuator import Effects, linear_chirp, simulate_stand
from sim_backend.linear import ActuatorParams
from sim_backend.rig_plant import FloorMotion, RigPlant, simulate_rig


def _pct(xs) -> dict:
    a = np.asarray(xs, dtype=float)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def bench_sim(cfg: Config, seconds: float = 100.0, rate_hz: float = 5000.0, repeats: int = 3,
              progress=None) -> dict:
    say = progress or (lambda msg: None)
    dt = 1.0 / rate_hz
    n = int(round(seconds * rate_hz))
    floor = FloorMotion.from_config(cfg, dt)
    g = floor.next_block(n)
    cmd = 0.01 * np.random.default_rng(0).standard_normal((n, 4))
    simulate_rig(cfg, dt, cmd[:16], g[:16, :4], g[:16, 4:8])          # compile / warm the cache
    batch = []
    for r in range(repeats):
        say(f"four-mount batch simulation {r + 1}/{repeats}: {seconds:g} s at {rate_hz:g} Hz")
        t0 = time.perf_counter()
        simulate_rig(cfg, dt, cmd, g[:, :4], g[:, 4:8])
        batch.append(time.perf_counter() - t0)
    say("four-mount stepped plant (one period per call, as the loop's sim backend uses it)")
    plant = RigPlant(cfg, dt, floor=FloorMotion(dt, seed=2))
    steps = []
    u = [0.0, 0.0, 0.0, 0.0]
    pc = time.perf_counter_ns
    for _ in range(min(n, 50000)):
        t0 = pc()
        plant.step(u)
        steps.append((pc() - t0) / 1000.0)
    say(f"single actuator on its stand: {seconds:g} s chirp at 2000 Hz (RK4 below 1/w_h)")
    p = ActuatorParams.from_config(cfg)
    _, chirp = linear_chirp(2000.0, min(seconds, 100.0), 0.1, 100.0, 2.0)
    simulate_stand(p, chirp[:100], 2000.0)
    t0 = time.perf_counter()
    simulate_stand(p, chirp, 2000.0, Effects())
    stand = time.perf_counter() - t0
    best = min(batch)
    return {
        "four_mount": {"simulated_s": seconds, "rate_hz": rate_hz, "states": int(plant.Ad.shape[0]),
                       "wall_s": _pct(batch), "realtime_factor": seconds / best},
        "four_mount_step_us": _pct(steps),
        "stand_chirp": {"simulated_s": min(seconds, 100.0), "rate_hz": 2000.0, "wall_s": stand,
                        "realtime_factor": min(seconds, 100.0) / stand},
    }

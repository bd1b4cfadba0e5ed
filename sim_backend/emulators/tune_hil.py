"""How the [controller] section of drivers/devicemaps/hil.toml was found: the isolation controller
(controllers/isolation.py, unchanged) re-tuned for the HIL loop rate with the drivers' loop timing.

HIL timing (drivers/devicemaps/valve408_canopen.md): the sample read in period k is the plant at the SYNC of
period k-1 and the command of period k acts from period k on, i.e. a ZOH plus one period of delay. Tuned in the
time domain on the four-mount plant (all loops closed, correlated broadband floor, sensor noise and the
Modbus module's 16-bit quantisation), in lockstep simulated time: minimise the rms table motion with isolation
on relative to off, and require the same design to stay in control, and not amplify, with one period more
delay (the drivers' latency tails). Nelder-Mead on log parameters from a hand start (low gain) or a given [controller] section.

Run: python -m sim_backend.emulators.tune_hil [rate_hz] [seconds] [start.toml|-] [delay]
(prints a [controller] section; delay = nominal periods of delay, the design must also survive delay + 1)
hil.toml: a first run from the hand start (5.6 dB), then a second from its result.
"""
from __future__ import annotations

import math
import sys

import numpy as np

KEYS = ("blend_hz", "kp_V_per_m", "pi_corner_hz", "lead1_zero_hz", "lead1_pole_hz", "lead2_zero_hz", "lead2_pole_hz",
        "rolloff_hz", "rolloff_zeta", "prewarp_hz")


def table_rms(cfg, params, dt: float, seconds: float, delay: int, isolation: bool, seed: int = 1,
              lsb_mps2: float | None = None) -> float:
    """rms table motion (m) after 1 s settling, or inf if the loop loses control (clamp or stroke limit).
    lsb_mps2: accelerometer quantisation (default: the Modbus module's 16 bits over +-10 V)."""
    if lsb_mps2 is None:
        lsb_mps2 = 20.0 / 65535 / cfg.drivers.accel_V_per_mps2
    import dataclasses
    from controllers.isolation import IsolationController
    from sim_backend.rig_plant import FloorMotion, RigPlant
    fcfg = cfg.replace(vibration=dataclasses.replace(cfg.vibration, seed=seed))
    plant = RigPlant(cfg, dt, floor=FloorMotion.from_config(fcfg, dt), seed=seed)
    ctrls = [IsolationController(params, dt) for _ in range(4)]
    states = [c.set_enabled(c.initial_state(), isolation) for c in ctrls]
    pipe = [[0.0] * 4 for _ in range(delay)]
    n0, n = int(1.0 / dt), int((1.0 + seconds) / dt)
    xs = np.empty(n - n0)
    clamp = 0
    lim = params.limit_V
    for k in range(n):
        acc, st = plant.accel_mps2, plant.stroke_m
        u = [0.0] * 4
        for i in range(4):
            a = round(acc[i] / lsb_mps2) * lsb_mps2
            u[i], states[i] = ctrls[i].step(states[i], (a, st[i]), dt)
            if abs(u[i]) >= lim:
                clamp += 1
        pipe.append(u)
        plant.step(pipe.pop(0))
        if k >= n0:
            xs[k - n0] = plant.table_m
        if clamp > 50 or max(abs(s) for s in plant.stroke_m) > cfg.safety.stroke_limit_m:
            return math.inf
    return float(np.std(xs))


def tune(rate_hz: float = 1000.0, seconds: float = 4.0, log=print, start_from: str | None = None,
         maxiter: int = 120, delay: int = 1):
    import scipy.optimize
    from controllers.isolation import params_from_config
    from rig.config import Config
    cfg = Config()
    dt = 1.0 / rate_hz
    start = params_from_config(cfg).with_(blend_hz=0.05, kp_V_per_m=2.0e4, pi_corner_hz=1.0, lead1_zero_hz=10.0,
                                          lead1_pole_hz=100.0, lead2_zero_hz=30.0, lead2_pole_hz=300.0,
                                          rolloff_hz=0.0, prewarp_hz=50.0)
    if start_from:                                  # continue from a [controller] section (e.g. hil.toml)
        from rig.config import load_config
        start = params_from_config(load_config(start_from))
    names = ("blend_hz", "kp_V_per_m", "pi_corner_hz", "lead1_zero_hz", "lead1_pole_hz", "lead2_zero_hz",
             "lead2_pole_hz")
    off = table_rms(cfg, start, dt, seconds, delay, False)
    def robust(p):                                  # in control and not amplifying with one period more
        return table_rms(cfg, p, dt, seconds, delay + 1, True) < off

    for _ in range(12):                             # a start that survives delay + 1: lower the gain
        if robust(start):
            break
        start = start.with_(kp_V_per_m=0.7 * start.kp_V_per_m)
        log(f"start: kp lowered to {start.kp_V_per_m:.4g}")

    def params(x):
        return start.with_(**{k: math.exp(v) for k, v in zip(names, x)})

    def cost(x):
        p = params(x)
        if max(p.lead1_pole_hz, p.lead2_pole_hz) >= 0.45 / dt or p.lead1_pole_hz <= p.lead1_zero_hz \
                or p.lead2_pole_hz <= p.lead2_zero_hz:
            return 10.0
        on = table_rms(cfg, p, dt, seconds, delay, True)
        if not math.isfinite(on) or not robust(p):
            return 10.0
        c = 20 * math.log10(on / off)
        log(f"{c:7.2f} dB  " + " ".join(f"{k}={getattr(p, k):.4g}" for k in names))
        return c

    x0 = np.array([math.log(getattr(start, k)) for k in names])
    res = scipy.optimize.minimize(cost, x0, method="Nelder-Mead",
                                  options={"maxiter": maxiter, "xatol": 0.02, "fatol": 0.05, "initial_simplex":
                                           np.vstack([x0] + [x0 + 0.4 * np.eye(len(x0))[i] for i in range(len(x0))])})
    p = params(res.x)
    log(f"# {rate_hz:g} Hz, delay {delay}: isolation reduction {-res.fun:.2f} dB (rms table {off * 1e6:.3f} um "
        f"off), stays in control with one period more delay")
    return p


def main(argv) -> int:
    rate = float(argv[0]) if argv else 1000.0
    seconds = float(argv[1]) if len(argv) > 1 else 4.0
    start = argv[2] if len(argv) > 2 and argv[2] != "-" else None
    delay = int(argv[3]) if len(argv) > 3 else 1
    p = tune(rate, seconds, log=lambda s: print(s, file=sys.stderr, flush=True), start_from=start, delay=delay)
    print("[controller]")
    for k in KEYS:
        print(f"{k} = {getattr(p, k):.6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

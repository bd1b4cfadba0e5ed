"""periodic_disturbance: a periodic force on the load not caused by the command (a neighbouring machine); on a
plant without a load, a periodic motion. Its response is linear in the force, so its amplitude and phase are
projected out of each residual and its frequency is found by a line search."""
import math

import numpy as np

from rig.diagnose.catalogue.base_resonance import EFFECT as STAND_MODE
from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import ForceLine
from sim_backend.actuator import Effects, simulate_stand
from sim_backend.linear import ActuatorParams


def _meaning(family: str, load: bool) -> str:
    return "periodic force not caused by the command" if load else "periodic motion not caused by the command"


def _stand(p: dict, u: str) -> dict:
    return {"disturbance_frequency_hz": p["frequency_hz"], "disturbance_force_n": p.get("force_n", 200.0),
            "disturbance_phase_rad": p.get("phase_rad", 0.0)}


def force_for_line(p: ActuatorParams, f_hz: float, amplitude_m: float, base: dict | None = None) -> float:
    """Force giving a position line of amplitude_m at f_hz: scale a short simulated 1 N response (with the stand
    mode when the case has one: a soft stand lets the force move piston and housing together)."""
    fs = 2000.0
    n = int(fs * max(1.0, 40.0 / f_hz))
    if base:
        n = max(n, int(fs * 8.0 / (base["damping_ratio"] * base["frequency_hz"])))    # past its ring-down
    fx = Effects(**{"disturbance_frequency_hz": f_hz, "disturbance_force_n": 1.0,
                    **(STAND_MODE.terms["stand"](base, "V") if base else {})})
    y = simulate_stand(p, np.zeros(n), fs, fx)
    tail = y["position_m"][n // 2:]                    # past the start transient
    t = np.arange(n)[n // 2:] / fs
    X = np.c_[np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t), np.ones_like(t)]
    c, *_ = np.linalg.lstsq(X, tail, rcond=None)
    return amplitude_m / max(float(np.hypot(c[0], c[1])), 1e-15)


def _draw(rng, c) -> tuple[dict, dict]:
    """A line clearly above the noise: its force from the position amplitude it gives."""
    f = round(float(rng.uniform(10.0, 90.0)), 2)
    line_m = float(rng.uniform(3.0, 6.0)) * c.position_noise_m
    return {"frequency_hz": f}, {"force_n": round(force_for_line(c.p, f, line_m, c.drawn.get(STAND_MODE.name)), 1),
                                 "phase_rad": round(float(rng.uniform(-math.pi, math.pi)), 3)}


EFFECT = Effect(
    name="periodic_disturbance", short="dist", order=30,
    families=("eha", "mechanical_axis", "transfer_function"),
    params=(Param("frequency_hz", "Hz"),),
    reported=(Param("force_n", "N"), Param("phase_rad", "rad"), Param("amplitude_m", "nm", 1e9)),
    meaning=_meaning,
    bounds=lambda s: [(0.5, 0.49 * s.fs)],
    start=ForceLine(), projected=True,
    evidence=Evidence("line", "spectral line not coherent with the command"),
    terms={"eha_model": lambda p, u: {}, "axis_model": lambda p, u: {}, "stand": _stand},
    draws={"stand": Draw(6, _draw, apart_from_pickup=True)},
)

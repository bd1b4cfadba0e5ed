"""The catalogue of candidate effects (names and keys as in docs/MODEL.md).

Each effect is a physical model with bounded parameters. `simulate(p, cmd, fs, fx)` runs the fastest exact model
that holds all the named effects (sim_linear when everything is linear or a pre-valve clip, else sim_reduced).
The periodic disturbance is not simulated here: it is an additive sinusoid at the fitted frequency whose amplitude
and phase are projected out (variable projection), since the position response to a force is linear.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim_backend.linear import ActuatorParams
from rig.diagnose.models import sim_linear, sim_reduced

CATALOGUE = ("transport_delay", "base_resonance", "valve_saturation", "valve_deadband", "coulomb_friction",
             "periodic_disturbance")

NONLINEAR = ("valve_saturation", "valve_deadband", "coulomb_friction")     # make harmonics of the chirp


@dataclass(frozen=True)
class Spec:
    name: str
    keys: tuple[str, ...]          # fitted keys (the disturbance's frequency is found by a line search)
    meaning: str


SPECS = {
    "transport_delay": Spec("transport_delay", ("delay_s",), "dead time between command and valve driver"),
    "base_resonance": Spec("base_resonance", ("frequency_hz", "damping_ratio", "mass_kg"),
                           "stand mode under the housing (resonance/antiresonance pair)"),
    "valve_saturation": Spec("valve_saturation", ("limit_ma",), "driver current clipped before the spool"),
    "valve_deadband": Spec("valve_deadband", ("width_ma",), "spool overlap: no flow within +-width"),
    "coulomb_friction": Spec("coulomb_friction", ("force_n",), "seal friction force_n tanh(v / 2e-5 m/s)"),
    "periodic_disturbance": Spec("periodic_disturbance", ("frequency_hz",), "periodic force not caused by the command"),
}


def bounds(name: str, *, fs: float, peak_ma: float, p: ActuatorParams) -> list[tuple[float, float]]:
    """Physical bounds of the fitted keys (wider than any plausible stand, never unphysical)."""
    if name == "transport_delay":
        return [(0.0, 8e-3)]
    if name == "base_resonance":
        return [(5.0, 0.45 * fs), (0.003, 0.4), (p.M / 3.0, 100.0 * p.M)]
    if name == "valve_saturation":
        return [(0.03 * peak_ma, 1.02 * peak_ma)]
    if name == "valve_deadband":
        return [(0.0, 0.6 * peak_ma)]
    if name == "coulomb_friction":
        return [(0.0, 5000.0)]
    if name == "periodic_disturbance":
        return [(0.5, 0.49 * fs)]
    raise KeyError(name)


def simulate(p: ActuatorParams, cmd_V: np.ndarray, fs: float, fx: dict[str, dict]) -> np.ndarray:
    """Position [m] at the sample instants for the nominal model plus the effects in fx (disturbance excluded)."""
    delay = fx.get("transport_delay", {}).get("delay_s", 0.0)
    sat = fx.get("valve_saturation", {}).get("limit_ma", 0.0)
    dead = fx.get("valve_deadband", {}).get("width_ma", 0.0)
    fric = fx.get("coulomb_friction", {}).get("force_n", 0.0)
    base = None
    if "base_resonance" in fx:
        b = fx["base_resonance"]
        base = (b["frequency_hz"], b["damping_ratio"], b.get("mass_kg", 280.0))
    if "valve_deadband" in fx or "coulomb_friction" in fx:
        return sim_reduced(p, cmd_V, fs, delay_s=delay, sat_ma=sat, dead_ma=dead, fric_n=fric, base=base)
    return sim_linear(p, cmd_V, fs, delay_s=delay, base=base, sat_ma=sat)


def load_receptance(p: ActuatorParams, f_hz: float) -> complex:
    """x_p / F on the piston (Eq. 8 with the load force), m/N, to turn a fitted line into a force."""
    s = 2j * math.pi * f_hz
    b4 = 4 * p.beta; A2 = p.A_p ** 2
    d3 = p.V_t * p.M / (b4 * A2); d2 = p.K_C * p.M / A2 + p.C * p.V_t / (b4 * A2)
    d1 = 1 + p.C * p.K_C / A2 + p.K_L * p.V_t / (b4 * A2); d0 = p.K_C * p.K_L / A2
    K = p.K_C / A2
    return K * (1 + p.V_t * s / (b4 * p.K_C)) / (((d3 * s + d2) * s + d1) * s + d0)

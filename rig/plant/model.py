"""The linear model families of a plant file (docs/PLANT.md, "Models and the catalogue").

  eha                the paper's actuator (Law et al. 2015, Eqs. 1-8): valve voltage -> piston position. Its
                     equations are written once, in rig.diagnose.models.ss_model / sim_backend; here it carries
                     the nominal ActuatorParams.
  mechanical_axis    M x'' = F - c x' - k x,  F = gain u (+ load forces: friction, constant force). Input a force
                     (unit N: gain fixed 1) or a voltage or current through the drive's gain (N/V, N/A).
  transfer_function  position / command = num(s) / den(s), strictly proper.

Every parameter has a start value and is either fixed or free within bounds (`Param`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from rig.errors import ConfigError
from sim_backend.linear import ActuatorParams

FAMILIES = ("eha", "mechanical_axis", "transfer_function")
INPUT_UNITS = ("V", "N", "A")
# the eha parameters the diagnosis refits (within these factors of the plant file's values: recordings move them
# +-15 %); the others (M, A_p, V_t, K_v, beta) stay as given
EHA_REFIT_KEYS = ("K_L", "K_C", "K_Q", "w_nv", "zeta")
EHA_REFIT_BOUNDS = (0.7, 1.4)


@dataclass(frozen=True)
class Param:
    """A parameter's start value; free within [lo, hi], or fixed (lo = hi = value)."""
    value: float
    lo: float
    hi: float
    free: bool

    @classmethod
    def fixed(cls, value: float) -> "Param":
        return cls(float(value), float(value), float(value), False)

    @property
    def log_scale(self) -> bool:
        """Fitted in log scale (bounds as ratios) when the whole range is positive."""
        return self.lo > 0.0


@dataclass(frozen=True)
class Plant:
    """A plant family with its parameters (name -> Param) and the unit of its input command."""
    family: str
    params: dict[str, Param]
    input_unit: str = "V"
    source: str = "<default>"
    actuator: ActuatorParams | None = None          # eha: the nominal actuator
    order: tuple[int, int] = (0, 0)                  # transfer_function: (len(num), len(den))
    output: str = "position"                         # mechanical_axis: the sensor reads its position or velocity

    # ---- parameters
    @property
    def free(self) -> tuple[str, ...]:
        return tuple(k for k, p in self.params.items() if p.free)

    def values(self, **override: float) -> dict[str, float]:
        out = {k: p.value for k, p in self.params.items()}
        out.update({k: float(v) for k, v in override.items()})
        return out

    # ---- equations
    @property
    def has_force(self) -> bool:
        """The model has a force on a load (friction, a constant force, a force disturbance apply)."""
        return self.family in ("eha", "mechanical_axis")

    def state_space(self, v: dict[str, float], base: tuple[float, float, float] | None = None):
        """Continuous (A, B, Bf, C, Cv) of a non-eha family: input the command, Bf the load-force input (zeros
        without a load), C the measured position, Cv the velocity friction acts on. base = (frequency_hz,
        damping_ratio, base mass kg): the axis's frame on a compliant base, the encoder measuring the carriage
        against the frame."""
        if self.family == "mechanical_axis":
            return axis_state_space(v["mass_kg"], v["damping_n_s_per_m"], v.get("stiffness_n_per_m", 0.0),
                                    v["gain_n_per_unit"], base, self.output)
        if self.family == "transfer_function":
            nn, nd = self.order
            num = [v[f"num{i}"] for i in range(nn)]
            den = [v[f"den{i}"] for i in range(nd)]
            A, B, C, D = scipy.signal.tf2ss(num, den)
            n = A.shape[0]
            return A, B[:, 0], np.zeros(n), C[0], np.zeros(n)
        raise ValueError(f"state_space: the {self.family} family has its own equations (rig.diagnose.models)")

    def moving_mass_kg(self, v: dict[str, float]) -> float:
        if self.family == "mechanical_axis":
            return v["mass_kg"]
        if self.family == "eha":
            return self.actuator.M
        return float("nan")

    def integrating(self, v: dict[str, float] | None = None) -> bool:
        """A pole at the origin (or in the right half-plane): simulated open loop from a recorded command the
        position drifts away, so the diagnosis shoots from segment-wise initial states."""
        if self.family == "eha":
            return False
        A = self.state_space(v or self.values())[0]
        ev = np.linalg.eigvals(A)
        scale = max(float(np.max(np.abs(ev))), 1e-9)
        return bool(np.max(ev.real) >= -1e-9 * scale)

    def not_computable(self, values: dict[str, float], what: str) -> ConfigError:
        """The one line for a fit this plant's model makes impossible: `what` came out not finite at these values
        (e.g. a mass of 1e-300 kg: no range fits every axis, so the values are refused by what they give)."""
        shown = ", ".join(f"{k} = {v:.4g}" for k, v in values.items())
        return ConfigError(f"{self.source}: [plant] {self.family}: no fit is possible: {what} is not finite with "
                           f"{shown}; check these values and their units (docs/PLANT.md)")

    def describe(self) -> str:
        parts = []
        for k, p in self.params.items():
            refit = self.family == "eha" and k in EHA_REFIT_KEYS
            parts.append(f"{k}={p.value:.4g}" + (f" [{p.lo:.3g}, {p.hi:.3g}]" if p.free else
                                                  " (refit from here)" if refit else " (fixed)"))
        return f"{self.family} (input {self.input_unit}): " + ", ".join(parts)


def axis_state_space(M: float, c: float, k: float, gain: float, base: tuple[float, float, float] | None = None,
                     output: str = "position"):
    """M x'' = gain u + F_load - c x' - k x. States x, v [, x_b, v_b]. On a base (mass m_b, its mode at f_b with
    damping zeta_b when the carriage is held): the drive and the axis's damping and stiffness act between carriage
    and base, the encoder reads x - x_b. output "velocity": the sensor reads the velocity (a tachometer, a motor's
    speed); without a spring or a base the position is then no state at all (M v' = gain u + F_load - c v)."""
    if output == "velocity" and base is None and k == 0.0:
        return (np.array([[-c / M]]), np.array([gain / M]), np.array([1.0 / M]), np.array([1.0]), np.array([1.0]))
    if base is None:
        A = np.array([[0.0, 1.0], [-k / M, -c / M]])
        B = np.array([0.0, gain / M])
        Bf = np.array([0.0, 1.0 / M])
        return A, B, Bf, np.array([1.0, 0.0] if output != "velocity" else [0.0, 1.0]), np.array([0.0, 1.0])
    fb, zb, mb = base
    wb = 2 * math.pi * fb
    kb, cb = mb * wb * wb, 2 * zb * wb * mb
    A = np.zeros((4, 4))
    A[0, 1] = 1.0; A[2, 3] = 1.0
    # carriage: M x'' = F - c (v - v_b) - k (x - x_b); base: m_b x_b'' = -F + c (v - v_b) + k (x - x_b) - k_b x_b - c_b v_b
    A[1] = [-k / M, -c / M, k / M, c / M]
    A[3] = [k / mb, c / mb, -(k + kb) / mb, -(c + cb) / mb]
    B = np.array([0.0, gain / M, 0.0, -gain / mb])
    Bf = np.array([0.0, 1.0 / M, 0.0, -1.0 / mb])              # friction and load forces act between the two
    Cv = np.array([0.0, 1.0, 0.0, -1.0])
    return A, B, Bf, (Cv if output == "velocity" else np.array([1.0, 0.0, -1.0, 0.0])), Cv


def eha_plant(p0: ActuatorParams | None = None, source: str = "<default>") -> Plant:
    """The paper's actuator: the default plant (today's behaviour: the diagnosis's own refit bounds)."""
    p0 = p0 or ActuatorParams()
    return Plant("eha", {k: Param.fixed(v) for k, v in p0.as_dict().items()}, "V", source, actuator=p0)

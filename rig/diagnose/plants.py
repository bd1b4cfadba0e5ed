"""The diagnosis's view of a plant (rig.plant): which catalogue effects apply, their parameters and bounds, and
the fast exact model of the plant with any set of them. The engine (rig.diagnose.engine) asks only this.

  EhaModel   the paper's actuator on its stand: today's catalogue and models (rig.diagnose.effects / models),
             the five identified parameters refit within 0.7-1.4 x nominal
  AxisModel  mechanical_axis and transfer_function: the plant file's free parameters within their bounds; the
             input nonlinearities (static, before the drive), the transport delay (exact ZOH), a constant force
             and Coulomb friction F_c tanh(v / v_s) on the load (sub-stepped, friction solved implicitly), the
             axis's frame on a compliant base, all in rig.plant.zoh's one simulator. A plant with a pole at the
             origin is simulated segment-wise from initial states (multiple shooting, docs/PLANT.md)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.diagnose import effects as eha_effects
from rig.diagnose.models import force_response as eha_force_response, sim_linear
from rig.plant.model import Plant, eha_plant
from rig.plant.zoh import discretise, free_response, phi, run_segments, substeps
from sim_backend.linear import ActuatorParams

FRICTION_SMOOTHING_M_PER_S = 1e-7   # v_s of F_c tanh(v / v_s), solved implicitly: the carriage sticks while the
                                    # applied force stays within F_c (it creeps at most at v_s, 50 nm in 0.5 s)
STATE_HALF_WINDOW_S = 0.010         # half-width of the cubic that reads a segment's start state from the data
SUB_HZ = 5000.0                     # sub-step rate of the friction model (implicit per sub-step) ...
FRICTION_REFINE = 20                # ... and a sub-step where the friction changes regime (a reversal, sticking,
                                    # breakaway) redone in 20 (an event timed to 10 us: a reversal's velocity
                                    # error F_c h / M would otherwise shift the position by F_c h / c)


def at_bounds(bounds_lin: dict, lin: dict, keys) -> dict[str, float]:
    """The linear parameters (of keys) a fit left within 1 % of their range's width from a bound: name -> that
    bound."""
    out = {}
    for k in keys:
        lo, hi = bounds_lin[k]
        edge = lo if abs(lin[k] - lo) <= abs(lin[k] - hi) else hi
        if abs(lin[k] - edge) < 0.01 * (hi - lo):
            out[k] = edge
    return out


@dataclass(frozen=True)
class Spec:
    name: str
    keys: tuple[str, ...]          # fitted keys (the disturbance's frequency is found by a line search)
    meaning: str


class EhaModel:
    """The paper's actuator (the default plant): exactly the engine's behaviour before plant files."""
    family = "eha"
    catalogue = ("transport_delay", "base_resonance", "periodic_disturbance", "valve_saturation",
                 "valve_deadband", "coulomb_friction")
    nonlinear = eha_effects.NONLINEAR
    slow = ("valve_deadband", "coulomb_friction")
    linear_sim = ("transport_delay", "base_resonance", "valve_saturation")
    saturation, deadband = "valve_saturation", "valve_deadband"
    lin_keys = ("K_L", "K_C", "K_Q", "w_nv", "zeta")
    LIN_BOUNDS = (0.7, 1.4)            # x nominal: physically bounded refit (recordings move them +-15 %)
    segmented = False
    input_unit = "V"
    axis_search = False                # its search stays as its proof measured it (docs/DIAGNOSIS.md)

    def __init__(self, plant: Plant):
        self.plant = plant
        self.p0: ActuatorParams = plant.actuator
        self.specs = {n: Spec(n, s.keys, s.meaning) for n, s in eha_effects.SPECS.items()}
        self.nominal = {k: getattr(self.p0, k) for k in self.lin_keys}
        self.bounds_lin = {k: (v * self.LIN_BOUNDS[0], v * self.LIN_BOUNDS[1]) for k, v in self.nominal.items()}
        self.log_scale = {k: True for k in self.lin_keys}

    def params(self, lin: dict) -> ActuatorParams:
        return self.p0.with_(**lin)

    def peak_effect_scale(self, cmd: np.ndarray) -> float:
        return float(np.max(np.abs(cmd))) * self.p0.K_v          # peak driver current, mA

    def simulate(self, lin: dict, cmd: np.ndarray, fs: float, fx: dict) -> np.ndarray:
        return eha_effects.simulate(self.params(lin), cmd, fs, fx)

    def force_response(self, lin: dict, fx: dict, fs: float, f_hz: float, n: int) -> np.ndarray:
        b = fx.get("base_resonance")
        base = (b["frequency_hz"], b["damping_ratio"], b.get("mass_kg", 280.0)) if b else None
        return eha_force_response(self.params(lin), fs, f_hz, n, base)

    def accel(self, lin: dict, cmd: np.ndarray, fs: float) -> np.ndarray:
        return sim_linear(self.params(lin), cmd, fs, output="accel")

    def effect_bounds(self, name: str, fs: float, peak: float) -> list[tuple[float, float]]:
        return eha_effects.bounds(name, fs=fs, peak_ma=peak, p=self.p0)

    def moving_mass_kg(self, lin: dict) -> float:
        return self.p0.M

    def public_linear(self, lin: dict) -> dict:
        return {k: float(v) for k, v in lin.items()} | {"C": float(self.p0.C)}


class AxisModel:
    """mechanical_axis and transfer_function plants from a plant file."""

    def __init__(self, plant: Plant):
        self.plant = plant
        self.family = plant.family
        u = plant.input_unit
        self.input_unit = u
        self.saturation, self.deadband = "input_saturation", "input_deadband"
        force = plant.has_force
        specs = [Spec("transport_delay", ("delay_s",), "dead time between the command and the drive's force"),
                 Spec("input_saturation", (f"limit_{u}",), f"the command clipped at +-limit before the drive"),
                 Spec("input_deadband", (f"width_{u}",), f"no drive output within +-width of the command"),
                 Spec("periodic_disturbance", ("frequency_hz",),
                      "periodic force not caused by the command" if force else
                      "periodic motion not caused by the command")]
        if force:
            specs += [Spec("coulomb_friction", ("force_n",),
                           f"friction force_n tanh(v / {FRICTION_SMOOTHING_M_PER_S:g} m/s) against the motion"),
                      Spec("constant_force", ("force_n",), "a constant force on the load (a cable, a weight "
                                                           "component, the drive's offset)"),
                      Spec("base_resonance", ("frequency_hz", "damping_ratio", "mass_kg"),
                           "the axis's frame on a compliant base (resonance/antiresonance pair)")]
        self.specs = {s.name: s for s in specs}
        order = ("transport_delay", "base_resonance", "periodic_disturbance", "input_saturation", "input_deadband",
                 "constant_force", "coulomb_friction")
        self.catalogue = tuple(n for n in order if n in self.specs)
        self.nonlinear = tuple(n for n in ("input_saturation", "input_deadband", "coulomb_friction")
                               if n in self.specs)
        self.slow = ("coulomb_friction",) if force else ()
        self.linear_sim = tuple(n for n in self.catalogue if n not in self.slow and n != "periodic_disturbance")
        self.lin_keys = plant.free
        vals = plant.values()
        self.fixed = {k: v for k, v in vals.items() if k not in self.lin_keys}
        self.nominal = {k: vals[k] for k in self.lin_keys}
        self.bounds_lin = {k: (plant.params[k].lo, plant.params[k].hi) for k in self.lin_keys}
        self.log_scale = {k: plant.params[k].log_scale for k in self.lin_keys}
        self.segmented = plant.integrating()
        self.axis_search = True        # the pair step, the stand mode's edge test, the post-polish check (engine)
        self.p0 = None

    # ---- values
    def values(self, lin: dict) -> dict:
        return {**self.fixed, **lin}

    def peak_effect_scale(self, cmd: np.ndarray) -> float:
        return float(np.max(np.abs(cmd)))                         # peak command, in its unit

    def peak_force_n(self, cmd: np.ndarray, lin: dict | None = None) -> float:
        v = self.values(lin or self.nominal)
        return float(np.max(np.abs(cmd))) * v.get("gain_n_per_unit", 1.0)

    def moving_mass_kg(self, lin: dict) -> float:
        return self.plant.moving_mass_kg(self.values(lin))

    def public_linear(self, lin: dict) -> dict:
        return {k: float(v) for k, v in self.values(lin).items()}

    # ---- models
    @staticmethod
    def _base(fx: dict):
        b = fx.get("base_resonance")
        return (b["frequency_hz"], b["damping_ratio"], b.get("mass_kg", 100.0)) if b else None

    def shaped_command(self, cmd: np.ndarray, fx: dict) -> np.ndarray:
        """The static input nonlinearities: saturation at +-limit, then the deadband of +-width."""
        u = self.plant.input_unit
        out = np.asarray(cmd, dtype=float)
        lim = fx.get("input_saturation", {}).get(f"limit_{u}", 0.0)
        if lim > 0:
            out = np.clip(out, -lim, lim)
        w = fx.get("input_deadband", {}).get(f"width_{u}", 0.0)
        if w > 0:
            out = np.sign(out) * np.maximum(np.abs(out) - w, 0.0)
        return out

    def matrices(self, lin: dict, fx: dict):
        return self.plant.state_space(self.values(lin), self._base(fx))

    def simulate(self, lin: dict, cmd: np.ndarray, fs: float, fx: dict, starts=None, X0=None) -> np.ndarray:
        """Position [m] at the samples; with starts/X0 the state is set to X0[s] at sample starts[s]."""
        A, B, Bf, C, Cv = self.matrices(lin, fx)
        delay = fx.get("transport_delay", {}).get("delay_s", 0.0)
        fric = fx.get("coulomb_friction", {}).get("force_n", 0.0)
        f0 = fx.get("constant_force", {}).get("force_n", 0.0)
        n_sub = max(1, int(math.ceil(SUB_HZ / fs))) if fric > 0 else 1
        Ah, Bnew, Bold, m = substeps(A, B, 1.0 / fs, n_sub, delay)
        Gf = phi(A, Bf, 1.0 / (fs * n_sub))[1] if (fric > 0 or f0 != 0) else np.zeros(len(B))
        fine = None
        if fric > 0:
            K = FRICTION_REFINE
            fine = (*substeps(A, B, 1.0 / fs, n_sub * K, delay)[:3], phi(A, Bf, 1.0 / (fs * n_sub * K))[1])
        return run_segments(Ah, Bnew, Bold, Gf, Cv, C, self.shaped_command(cmd, fx), m, friction_n=fric,
                            smoothing_m_per_s=FRICTION_SMOOTHING_M_PER_S, force_n=f0, starts=starts, X0=X0,
                            fine=fine)

    def free_response(self, lin: dict, fx: dict, fs: float, length: int) -> np.ndarray:
        """(length, n) output response to each unit initial state (the segment-state regressors)."""
        A, B, _, C, _ = self.matrices(lin, fx)
        Ad = discretise(A, B, 1.0 / fs, 0.0)[0]
        return free_response(Ad, C, length)

    def state_from_data(self, y: np.ndarray, fs: float, starts: np.ndarray, fx: dict) -> np.ndarray:
        """Initial states at the segment starts from the measured position: a cubic through +-10 ms of position
        centred on the start (one-sided at the record's ends) gives position and velocity (mechanical axis; the
        base at rest); other families start at zero (their segment states are found exactly by the projection).
        Centred, because a one-sided fit's end velocity is poor, and a friction model's response is not linear
        in its start (the engine refines these states by Gauss-Newton steps)."""
        n_state = 4 if (self.family == "mechanical_axis" and "base_resonance" in fx) else \
            self.matrices(self.nominal, fx)[0].shape[0]
        X0 = np.zeros((len(starts), n_state))
        if self.family != "mechanical_axis":
            return X0
        w = max(2, int(round(STATE_HALF_WINDOW_S * fs)))
        for i, s in enumerate(starts):
            a, b = max(0, s - w), min(len(y), s + w + 1)
            if b - a < 5:
                X0[i, 0] = y[min(s, len(y) - 1)]
                continue
            t = (np.arange(a, b) - s) / fs
            c = np.polynomial.polynomial.polyfit(t, y[a:b], 3)
            X0[i, 0], X0[i, 1] = c[0], c[1]
        return X0

    def force_response(self, lin: dict, fx: dict, fs: float, f_hz: float, n: int) -> np.ndarray:
        """(n, 2) position responses to a sin/cos load force of 1 N (a plant without a load: the line itself,
        in m). Segment states absorb the start transient."""
        w = 2 * math.pi * f_hz * (np.arange(n) + 0.5) / fs
        if not self.plant.has_force:
            return np.column_stack([np.sin(2 * math.pi * f_hz * np.arange(n) / fs),
                                    np.cos(2 * math.pi * f_hz * np.arange(n) / fs)])
        A, B, Bf, C, Cv = self.matrices(lin, fx)
        Ah, Bnew, Bold, m = substeps(A, Bf, 1.0 / fs, 1, 0.0)
        z = np.zeros(len(Bf))
        return np.column_stack([run_segments(Ah, Bnew, Bold, z, Cv, C, np.sin(w), m),
                                run_segments(Ah, Bnew, Bold, z, Cv, C, np.cos(w), m)])

    def accel(self, lin: dict, cmd: np.ndarray, fs: float) -> np.ndarray:
        y = self.simulate(lin, cmd, fs, {})
        return np.gradient(np.gradient(y, 1.0 / fs), 1.0 / fs)

    def effect_bounds(self, name: str, fs: float, peak: float) -> list[tuple[float, float]]:
        F = self.peak_force_n(np.array([peak]))
        if name == "transport_delay":
            return [(0.0, 8e-3)]
        if name == "input_saturation":
            return [(0.03 * peak, 1.02 * peak)]
        if name == "input_deadband":
            return [(0.0, 0.6 * peak)]
        if name == "coulomb_friction":
            return [(0.0, 2.0 * F)]
        if name == "constant_force":
            return [(-F, F)]
        if name == "base_resonance":
            M = self.moving_mass_kg(self.nominal)
            return [(5.0, 0.45 * fs), (0.003, 0.4), (M / 3.0, 100.0 * M)]
        if name == "periodic_disturbance":
            return [(0.5, 0.49 * fs)]
        raise KeyError(name)


def model_for(plant) -> EhaModel | AxisModel:
    """The diagnosis's model of a Plant (or of the eha plant's nominal ActuatorParams)."""
    if isinstance(plant, ActuatorParams):
        plant = eha_plant(plant)
    return EhaModel(plant) if plant.family == "eha" else AxisModel(plant)

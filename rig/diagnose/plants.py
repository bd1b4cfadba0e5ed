"""The diagnosis's view of a plant (rig.plant): which catalogue effects apply (rig.diagnose.catalogue, by family),
what their bounds and starts are relative to (`scale`), and the fast exact model of the plant with any set of them
(each effect's term in it from the catalogue). The engine (rig.diagnose.engine) asks only this.

  EhaModel   the paper's actuator on its stand (rig.diagnose.models), the five identified parameters refit
             within 0.7-1.4 x nominal
  AxisModel  mechanical_axis and transfer_function: the plant file's free parameters within their bounds; the
             input nonlinearities (static, before the drive), the transport delay (exact ZOH), a constant force
             and Coulomb friction F_c tanh(v / v_s) on the load (sub-stepped, friction solved implicitly), the
             axis's frame on a compliant base, all in rig.plant.zoh's one simulator. A plant with a pole at the
             origin is simulated segment-wise from initial states (multiple shooting, docs/PLANT.md)
"""
from __future__ import annotations

import math
import numpy as np

from rig.diagnose import catalogue
from rig.diagnose.models import force_response as eha_force_response, sim_linear, sim_reduced
from rig.plant.model import EHA_REFIT_BOUNDS, EHA_REFIT_KEYS, Plant, eha_plant
from rig.plant.zoh import discretise, free_response, phi, play, run_segments, substeps
from sim_backend.linear import ActuatorParams

FRICTION_SMOOTHING_M_PER_S = 1e-7   # v_s of F_c tanh(v / v_s), solved implicitly: the carriage sticks while the
                                    # applied force stays within F_c (it creeps at most at v_s, 50 nm in 0.5 s)
STATE_HALF_WINDOW_S = 0.010         # half-width of the cubic that reads a segment's start state from the data
SUB_HZ = 5000.0                     # sub-step rate of the friction model (implicit per sub-step) ...
FRICTION_REFINE = 20                # ... and a sub-step where the friction changes regime (a reversal, sticking,
                                    # breakaway) redone in 20 (an event timed to 10 us: a reversal's velocity
                                    # error F_c h / M would otherwise shift the position by F_c h / c)


def at_bounds(bounds_lin: dict, lin: dict, keys, log_scale: dict | None = None) -> dict[str, float]:
    """The linear parameters (of keys) a fit left within 1 % of their range's width from a bound (on a log scale
    for a parameter fitted on one: 0.1 on 0.001..1000 is not at its lower bound): name -> that bound."""
    out = {}
    for k in keys:
        lo, hi = bounds_lin[k]
        if log_scale and log_scale.get(k):
            v, a, b = math.log(lin[k]), math.log(lo), math.log(hi)
        else:
            v, a, b = lin[k], lo, hi
        edge = a if abs(v - a) <= abs(v - b) else b
        if abs(v - edge) < 0.01 * (b - a):
            out[k] = lo if edge == a else hi
    return out


class EhaModel:
    """The paper's actuator (the default plant): exactly the engine's behaviour before plant files."""
    family = "eha"
    lin_keys = EHA_REFIT_KEYS
    LIN_BOUNDS = EHA_REFIT_BOUNDS      # x nominal: physically bounded refit
    segmented = False
    input_unit = "V"
    has_load = True
    axis_search = False                # its search stays as its proof measured it (docs/DIAGNOSIS.md)
    slow_second_lin = ("K_Q", "K_C")   # on a slow model a second effect is fitted with the gain and lag free

    def __init__(self, plant: Plant):
        self.plant = plant
        self.p0: ActuatorParams = plant.actuator
        self.effects = catalogue.for_plant(self.family, self.has_load, plant.output)
        self.nominal = {k: getattr(self.p0, k) for k in self.lin_keys}
        self.bounds_lin = {k: (v * self.LIN_BOUNDS[0], v * self.LIN_BOUNDS[1]) for k, v in self.nominal.items()}
        self.log_scale = {k: True for k in self.lin_keys}

    def params(self, lin: dict) -> ActuatorParams:
        return self.p0.with_(**lin)

    def scale(self, cmd: np.ndarray, fs: float) -> catalogue.Scale:
        """What the effects' bounds and starts are relative to: the peak driver current (mA), the stand's
        moving mass."""
        return catalogue.Scale(self.family, fs, float(np.max(np.abs(cmd))) * self.p0.K_v, math.nan, self.p0.M)

    def simulate(self, lin: dict, cmd: np.ndarray, fs: float, fx: dict) -> np.ndarray:
        """Position [m] at the sample instants for the nominal model plus the effects in fx (no projected line):
        the fastest exact model that holds them (sim_linear unless a slow effect needs sim_reduced)."""
        kw = catalogue.terms("eha_model", fx)
        if catalogue.slow_in(fx):
            return sim_reduced(self.params(lin), cmd, fs, **kw)
        return sim_linear(self.params(lin), cmd, fs, **kw)

    def force_response(self, lin: dict, fx: dict, fs: float, f_hz: float, n: int) -> np.ndarray:
        base = catalogue.terms("eha_model", fx).get("base")
        return eha_force_response(self.params(lin), fs, f_hz, n, base)

    def accel(self, lin: dict, cmd: np.ndarray, fs: float) -> np.ndarray:
        return sim_linear(self.params(lin), cmd, fs, output="accel")

    def moving_mass_kg(self, lin: dict) -> float:
        return self.p0.M

    def public_linear(self, lin: dict) -> dict:
        return {k: float(v) for k, v in lin.items()} | {"C": float(self.p0.C)}


class AxisModel:
    """mechanical_axis and transfer_function plants from a plant file."""
    slow_second_lin = None             # on a slow model a second effect is fitted with every linear key free

    def __init__(self, plant: Plant):
        self.plant = plant
        self.family = plant.family
        self.input_unit = plant.input_unit
        self.has_load = plant.has_force
        self.effects = catalogue.for_plant(self.family, self.has_load, plant.output)
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

    def scale(self, cmd: np.ndarray, fs: float) -> catalogue.Scale:
        """What the effects' bounds and starts are relative to: the peak command (its unit), the peak drive force
        and the moving mass at the nominal parameters."""
        peak = float(np.max(np.abs(cmd)))
        return catalogue.Scale(self.family, fs, peak, peak * self.values(self.nominal).get("gain_n_per_unit", 1.0),
                               self.moving_mass_kg(self.nominal))

    def moving_mass_kg(self, lin: dict) -> float:
        return self.plant.moving_mass_kg(self.values(lin))

    def public_linear(self, lin: dict) -> dict:
        return {k: float(v) for k, v in self.values(lin).items()}

    # ---- models
    def _terms(self, fx: dict) -> dict:
        return catalogue.terms("axis_model", fx, self.input_unit)

    @staticmethod
    def shaped_command(cmd: np.ndarray, saturation: float = 0.0, deadband: float = 0.0) -> np.ndarray:
        """The static input nonlinearities: saturation at +-limit, then the deadband of +-width (0: none)."""
        out = np.asarray(cmd, dtype=float)
        if saturation > 0:
            out = np.clip(out, -saturation, saturation)
        if deadband > 0:
            out = np.sign(out) * np.maximum(np.abs(out) - deadband, 0.0)
        return out

    def matrices_key(self, fx: dict):
        """What of fx the state-space matrices depend on (a compliant base)."""
        return self._terms(fx).get("base")

    def matrices(self, lin: dict, fx: dict):
        return self.plant.state_space(self.values(lin), self.matrices_key(fx))

    def simulate(self, lin: dict, cmd: np.ndarray, fs: float, fx: dict, starts=None, X0=None) -> np.ndarray:
        """Position [m] at the samples; with starts/X0 the (drive's) state is set to X0[s] at sample starts[s]."""
        return self.read(self.simulate_drive(lin, cmd, fs, fx, starts, X0), fx)

    def read(self, y: np.ndarray, fx: dict) -> np.ndarray:
        """What the sensor reads of the drive's output y (simulate_drive): through a gear's play, or its magnitude."""
        kw = self._terms(fx)
        gap = kw.get("backlash_m", 0.0)
        if gap > 0:                         # the sensor on the load, behind the gear's play
            y = play(y, gap)
        return np.abs(y) if kw.get("rectify", False) else y  # a sensor blind to the sign reads the magnitude

    def simulate_drive(self, lin: dict, cmd: np.ndarray, fs: float, fx: dict, starts=None,
                       X0=None) -> np.ndarray:
        """The drive's output before the sensor's reading (read): linear in X0 unless friction is in."""
        kw = self._terms(fx)                   # each effect's term: its keyword arguments, passed on below
        A, B, Bf, C, Cv = self.plant.state_space(self.values(lin), kw.pop("base", None))
        delay, fric, f0 = kw.pop("delay_s", 0.0), kw.pop("friction_n", 0.0), kw.pop("force_n", 0.0)
        sliding = fric > 0 or kw.get("stribeck_n", 0.0) > 0          # a friction force to solve for
        n_sub = max(1, int(math.ceil(SUB_HZ / fs))) if sliding else 1
        Ah, Bnew, Bold, m = substeps(A, B, 1.0 / fs, n_sub, delay)
        Gf = phi(A, Bf, 1.0 / (fs * n_sub))[1] if (sliding or f0 != 0) else np.zeros(len(B))
        fine = None
        if sliding:
            K = FRICTION_REFINE
            fine = (*substeps(A, B, 1.0 / fs, n_sub * K, delay)[:3], phi(A, Bf, 1.0 / (fs * n_sub * K))[1])
        kw.pop("rectify", False), kw.pop("backlash_m", 0.0)            # the sensor's (read)
        cmd = self.shaped_command(np.asarray(cmd, float) + kw.pop("bias", 0.0), kw.pop("saturation", 0.0),
                                  kw.pop("deadband", 0.0))
        return run_segments(Ah, Bnew, Bold, Gf, Cv, C, cmd, m, friction_n=fric,
                            smoothing_m_per_s=FRICTION_SMOOTHING_M_PER_S, force_n=f0, starts=starts, X0=X0,
                            fine=fine, **kw)   # a new effect's term: run_segments' own keyword

    def drive_states(self, X0: np.ndarray, fx: dict) -> np.ndarray:
        """The drive's start states from the load's (state_from_data reads the load): behind a play a load that
        moves is pushed by the drive's near side, half the play ahead of it (a load at rest: the drive centred).
        Set once from the data, not on each refinement of the states: a start velocity near 0 whose sign flipped
        between two refinements moved the drive by the whole play, and the refinements cycled."""
        gap = self._terms(fx).get("backlash_m", 0.0)
        if gap <= 0:
            return X0
        X = np.array(X0, dtype=float)
        X[:, 0] += 0.5 * gap * np.sign(X[:, 1])
        return X

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
        n_state = 4 if (self.family == "mechanical_axis" and "base" in self._terms(fx)) else \
            self.matrices(self.nominal, fx)[0].shape[0]
        X0 = np.zeros((len(starts), n_state))
        if self.family != "mechanical_axis":
            return X0
        w = max(2, int(round(STATE_HALF_WINDOW_S * fs)))
        if self.plant.output == "velocity":      # the sensor reads the velocity: the state it gives, position 0
            X0[:, 1 if n_state > 1 else 0] = y[np.minimum(starts, len(y) - 1)]
            return X0
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


def model_for(plant) -> EhaModel | AxisModel:
    """The diagnosis's model of a Plant (or of the eha plant's nominal ActuatorParams)."""
    if isinstance(plant, ActuatorParams):
        plant = eha_plant(plant)
    return EhaModel(plant) if plant.family == "eha" else AxisModel(plant)

"""Time-domain plant of one actuator on its test stand (Law et al. 2015, Eqs. 1-7), with optional effects.

States: spool x_v [mA-equivalent] and its rate, load pressure P_L [Pa], piston position x_p and velocity v_p,
and (when the base mode is on) the stand's position x_b and velocity v_b. The command is held (zero-order hold)
at the sample rate and integrated with fixed-step RK4 at an inner step well below 1/w_h.

Measured outputs at each sample instant t_k (before the command u_k takes effect, as a DAC/ADC pair does):
  position_m  = x_p         (absolute piston position: fits p03_base to the noise floor with m_b = 280 kg;
                             the relative x_p - x_b left a 3e-7 m residual at any stand mass)
  accel_mps2  = d2x_p/dt2   (accelerometer on the moving part, absolute)

Effects (all off by default; names and keys as in docs/MODEL.md):
  transport_delay   delay_s      dead time between the recorded command and the valve driver
  valve_saturation  limit_ma     driver current clipped to +-limit before the spool dynamics
  valve_deadband    width_ma     spool overlap: no flow while |x_v| < width (flow from |x_v| - width)
  coulomb_friction  force_n      seal friction force_n * tanh(v / 2e-5 m/s) on the piston
  base_resonance    frequency_hz, damping_ratio, mass_kg   the stand under the housing as a mass-spring mode
  periodic_disturbance frequency_hz, force_n, phase_rad    a force on the piston unrelated to the command
  sensor noise      position_noise_m, accel_noise_mps2     white, Gaussian, rms
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, asdict

import numpy as np
import numba

from sim_backend.linear import ActuatorParams

FRICTION_V_SCALE = 2e-5     # m/s, the tanh smoothing of sign(v) used by the recordings' simulator


@dataclass(frozen=True)
class Effects:
    delay_s: float = 0.0
    saturation_limit_ma: float = 0.0          # 0 = off
    deadband_width_ma: float = 0.0            # 0 = off
    friction_force_n: float = 0.0             # 0 = off
    base_frequency_hz: float = 0.0            # 0 = off
    base_damping_ratio: float = 0.03
    base_mass_kg: float = 280.0               # fitted on p03_base (5 M); mass ratio M/m_b = 0.2
    disturbance_frequency_hz: float = 0.0     # 0 = off
    disturbance_force_n: float = 0.0
    disturbance_phase_rad: float = 0.0
    position_noise_m: float = 0.0
    accel_noise_mps2: float = 0.0
    seed: int = 0

    @classmethod
    def from_catalogue(cls, effects: dict, **extra) -> "Effects":
        """Build from the recordings' answers.json style: {"transport_delay": {"delay_s": ...}, ...}."""
        kw = dict(extra)
        for name, prm in effects.items():
            if name == "transport_delay":
                kw["delay_s"] = prm["delay_s"]
            elif name == "valve_saturation":
                kw["saturation_limit_ma"] = prm["limit_ma"]
            elif name == "valve_deadband":
                kw["deadband_width_ma"] = prm["width_ma"]
            elif name == "coulomb_friction":
                kw["friction_force_n"] = prm["force_n"]
            elif name == "base_resonance":
                kw["base_frequency_hz"] = prm["frequency_hz"]
                kw["base_damping_ratio"] = prm.get("damping_ratio", 0.03)
                if "mass_kg" in prm:
                    kw["base_mass_kg"] = prm["mass_kg"]
            elif name == "periodic_disturbance":
                kw["disturbance_frequency_hz"] = prm["frequency_hz"]
                kw["disturbance_force_n"] = prm.get("force_n", 200.0)
                kw["disturbance_phase_rad"] = prm.get("phase_rad", 0.0)
            else:
                raise ValueError(f"unknown effect {name!r}")
        return cls(**kw)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_config(cls, cfg) -> "Effects":
        """The [stand] section of the config (rig.config.StandConfig)."""
        return cls(**asdict(cfg.stand))


def inner_step_s(p: ActuatorParams, fx: Effects) -> float:
    """An RK4 step well below 1/w_h, and inside the stability limit of the friction's tanh slope."""
    h = 0.1 / p.w_h                                  # ~7.5 us for Table 1
    if fx.friction_force_n > 0:
        c_eq = fx.friction_force_n / FRICTION_V_SCALE   # N s/m, slope of the tanh at v = 0
        h = min(h, 1.0 * p.M / c_eq)                    # RK4 real-axis limit is 2.78; keep margin
    if fx.base_frequency_hz > 0:
        h = min(h, 0.05 / (2 * math.pi * fx.base_frequency_hz))
    return h


@numba.njit(cache=True, fastmath=False)
def _deriv(y, i_cmd, f_dist, prm, out):
    # prm: M A_p C V_t K_L K_Q K_C w_nv zeta beta sat dead fric base_on m_b k_b c_b
    M = prm[0]; A_p = prm[1]; C = prm[2]; V_t = prm[3]; K_L = prm[4]; K_Q = prm[5]; K_C = prm[6]
    w_nv = prm[7]; zeta = prm[8]; beta = prm[9]; dead = prm[11]; fric = prm[12]
    base_on = prm[13]; m_b = prm[14]; k_b = prm[15]; c_b = prm[16]
    xv = y[0]; vv = y[1]; PL = y[2]; xp = y[3]; vp = y[4]; xb = y[5]; vb = y[6]
    # Eq. 1: second-order spool, driven by the (possibly saturated) driver current
    out[0] = vv
    out[1] = w_nv * w_nv * (i_cmd - xv) - 2.0 * zeta * w_nv * vv
    # spool overlap: no flow inside +-dead
    if dead > 0.0:
        if xv > dead:
            xe = xv - dead
        elif xv < -dead:
            xe = xv + dead
        else:
            xe = 0.0
    else:
        xe = xv
    y_rel = xp - xb
    v_rel = vp - vb
    # Eqs. 3, 6: Q_L = K_Q x_v - K_C P_L = A_p dy/dt + V_t/(4 beta) dP_L/dt
    out[2] = (K_Q * xe - K_C * PL - A_p * v_rel) * 4.0 * beta / V_t
    # Eq. 7 on the piston: A_p P_L = M a + C v + K_L y (+ friction, disturbance)
    f_spring = K_L * y_rel + C * v_rel
    f_fric = fric * math.tanh(v_rel / 2e-5) if fric > 0.0 else 0.0
    f_act = A_p * PL - f_spring - f_fric
    out[3] = vp
    out[4] = (f_act + f_dist) / M
    if base_on > 0.0:
        out[5] = vb
        out[6] = (-f_act - k_b * xb - c_b * vb) / m_b      # reaction of the actuator force on the stand
    else:
        out[5] = 0.0
        out[6] = 0.0


@numba.njit(cache=True)
def _simulate(cmd_V, fs, n_sub, delay_s, K_v, sat, prm, dist_f, dist_F, dist_ph, pos_out, acc_out, spool_out):
    """The whole record: sample the outputs at t_k, then integrate [t_k, t_k+1) with `_advance_stand`
    (the command array itself serves as the command history)."""
    y = np.zeros(7)
    out = np.zeros(2)
    work = np.zeros((5, 7))
    for k in range(cmd_V.shape[0]):
        pos_out[k] = y[3]          # transducer: absolute piston position (see module docstring)
        spool_out[k] = y[0]
        _advance_stand(y, k, cmd_V, fs, n_sub, delay_s, K_v, sat, prm, dist_f, dist_F, dist_ph, out, work)
        acc_out[k] = out[0]


def simulate_stand(p: ActuatorParams, cmd_V: np.ndarray, fs: float, fx: Effects = Effects(),
                   *, inner_step: float | None = None) -> dict[str, np.ndarray]:
    """Simulate the actuator on its stand for a command sampled at fs (held between samples).

    Returns arrays at the sample instants: position_m, accel_mps2, spool_mA (noise added as configured).
    """
    cmd = np.ascontiguousarray(cmd_V, dtype=float)
    h = inner_step or inner_step_s(p, fx)
    n_sub = max(1, int(math.ceil(1.0 / (fs * h))))
    m_b = fx.base_mass_kg
    w_b = 2 * math.pi * fx.base_frequency_hz
    prm = np.array([p.M, p.A_p, p.C, p.V_t, p.K_L, p.K_Q, p.K_C, p.w_nv, p.zeta, p.beta,
                    fx.saturation_limit_ma, fx.deadband_width_ma, fx.friction_force_n,
                    1.0 if fx.base_frequency_hz > 0 else 0.0, m_b, m_b * w_b ** 2,
                    2 * fx.base_damping_ratio * m_b * w_b], dtype=float)
    n = cmd.shape[0]
    pos = np.empty(n); acc = np.empty(n); spool = np.empty(n)
    _simulate(cmd, float(fs), n_sub, fx.delay_s, p.K_v, fx.saturation_limit_ma, prm,
              fx.disturbance_frequency_hz, fx.disturbance_force_n if fx.disturbance_frequency_hz > 0 else 0.0,
              fx.disturbance_phase_rad, pos, acc, spool)
    if fx.position_noise_m > 0 or fx.accel_noise_mps2 > 0:
        rng = np.random.default_rng(fx.seed)
        pos = pos + fx.position_noise_m * rng.standard_normal(n)
        acc = acc + fx.accel_noise_mps2 * rng.standard_normal(n)
    return {"position_m": pos, "accel_mps2": acc, "spool_mA": spool}


def linear_chirp(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0,
                 amplitude_V: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's identification input: a linear sine chirp, sampled at fs. Returns (t_s, cmd_V)."""
    n = int(round(duration_s * fs))
    t = np.arange(n) / fs
    phase = 2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) / duration_s * t ** 2)
    return t, amplitude_V * np.sin(phase)


@numba.njit(cache=True)
def _advance_stand(y, k, hist, fs, n_sub, delay_s, K_v, sat, prm, dist_f, dist_F, dist_ph, out, work):
    """Advance the stand one sample period [t_k, t_k+1) with commands from the ring `hist` (index mod len).

    out[0] = acceleration at t_k (before advancing), out[1] = piston position x_p at t_k+1."""
    L = hist.shape[0]
    h = 1.0 / (fs * n_sub)
    k1 = work[0]; k2 = work[1]; k3 = work[2]; k4 = work[3]; yt = work[4]     # RK4 scratch, (5, 7)
    w_d = 2.0 * math.pi * dist_f
    t0 = k / fs
    for j in range(n_sub):
        t = t0 + j * h
        for stage in range(4):
            if stage == 0:
                ts = t
            elif stage == 3:
                ts = t + h
            else:
                ts = t + 0.5 * h
            idx = int(math.floor((ts - delay_s) * fs + 1e-9))
            if idx < 0 or idx < k - L + 1:
                u = 0.0
            else:
                u = hist[min(idx, k) % L]
            i_cmd = K_v * u
            if sat > 0.0:
                if i_cmd > sat:
                    i_cmd = sat
                elif i_cmd < -sat:
                    i_cmd = -sat
            f_d = dist_F * math.sin(w_d * ts + dist_ph) if dist_F != 0.0 else 0.0
            if stage == 0:
                _deriv(y, i_cmd, f_d, prm, k1)
                if j == 0:
                    out[0] = k1[4]
                for q in range(7):
                    yt[q] = y[q] + 0.5 * h * k1[q]
            elif stage == 1:
                _deriv(yt, i_cmd, f_d, prm, k2)
                for q in range(7):
                    yt[q] = y[q] + 0.5 * h * k2[q]
            elif stage == 2:
                _deriv(yt, i_cmd, f_d, prm, k3)
                for q in range(7):
                    yt[q] = y[q] + h * k3[q]
            else:
                _deriv(yt, i_cmd, f_d, prm, k4)
        for q in range(7):
            y[q] += h / 6.0 * (k1[q] + 2.0 * k2[q] + 2.0 * k3[q] + k4[q])
    out[1] = y[3]


class StandPlant:
    """One actuator on its test stand, stepped one sample period at a time (for the loop's sim backend).

    Same physics and effects as `simulate_stand` (a test checks they agree). `step(cmd_V)` holds cmd_V over
    one period; afterwards `position_m` is the transducer value at the new instant and `accel_mps2` the
    acceleration at the start of the period (as sampled by the ADC at t_k), both with sensor noise."""

    n_mounts = 1

    def __init__(self, p: ActuatorParams, fx: Effects = Effects(), fs: float = 1000.0, *,
                 inner_step: float | None = None):
        self.p, self.fx, self.fs = p, fx, float(fs)
        h = inner_step or inner_step_s(p, fx)
        self.n_sub = max(1, int(math.ceil(1.0 / (fs * h))))
        m_b = fx.base_mass_kg
        w_b = 2 * math.pi * fx.base_frequency_hz
        self.prm = np.array([p.M, p.A_p, p.C, p.V_t, p.K_L, p.K_Q, p.K_C, p.w_nv, p.zeta, p.beta,
                             fx.saturation_limit_ma, fx.deadband_width_ma, fx.friction_force_n,
                             1.0 if fx.base_frequency_hz > 0 else 0.0, m_b, m_b * w_b ** 2,
                             2 * fx.base_damping_ratio * m_b * w_b], dtype=float)
        self.hist = np.zeros(int(math.ceil(fx.delay_s * fs)) + 4)
        self.y = np.zeros(7)
        self.k = 0
        self._out = np.zeros(2)
        self._work = np.zeros((5, 7))
        self.rng = np.random.default_rng(fx.seed)
        self.position_m = self._noisy_pos(0.0)
        self.accel_mps2 = 0.0
        self.t_s = 0.0
        # compile (or load) the step now: a first compile inside a running loop stalls it past its watchdog
        _advance_stand(np.zeros(7), 0, np.zeros_like(self.hist), self.fs, 1, fx.delay_s, p.K_v, 0.0, self.prm,
                       0.0, 0.0, 0.0, np.zeros(2), np.zeros((5, 7)))

    def _noisy_pos(self, x):
        return x + (self.fx.position_noise_m * self.rng.standard_normal() if self.fx.position_noise_m else 0.0)

    def step(self, cmd_V: float) -> tuple[float, float]:
        fx = self.fx
        self.hist[self.k % len(self.hist)] = cmd_V
        _advance_stand(self.y, self.k, self.hist, self.fs, self.n_sub, fx.delay_s, self.p.K_v,
                       fx.saturation_limit_ma, self.prm, fx.disturbance_frequency_hz,
                       fx.disturbance_force_n if fx.disturbance_frequency_hz > 0 else 0.0,
                       fx.disturbance_phase_rad, self._out, self._work)
        self.k += 1
        self.t_s = self.k / self.fs
        self.accel_mps2 = float(self._out[0]) + (fx.accel_noise_mps2 * self.rng.standard_normal()
                                                 if fx.accel_noise_mps2 else 0.0)
        self.position_m = self._noisy_pos(float(self._out[1]))
        return self.position_m, self.accel_mps2

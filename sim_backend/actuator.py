"""Time-domain plant of one actuator on its test stand (Law et al. 2015, Eqs. 1-7), with optional effects.

States: spool x_v [mA-equivalent] and its rate, load pressure P_L [Pa], piston position x_p and velocity v_p,
and (when the base mode is on) the stand's position x_b and velocity v_b. The command is held (zero-order hold)
at the sample rate and integrated with fixed-step RK4 at an inner step well below 1/w_h.

Measured outputs at each sample instant t_k (before the command u_k takes effect, as a DAC/ADC pair does):
  position_m  = x_p         (absolute piston position: fits p03_base to the noise floor with m_b = 5 M;
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
  base_motion       the floor under the stand moving by x_g (StandPlant.step's `ground`; StandBank draws it):
                    the housing follows it (through k_b, c_b with the base mode on), the transducer reads the
                    piston against the floor frame, x_p - x_g, and the accelerometer the piston's absolute motion

`stand_state_space` is the same physics, linear (effects off, base mode optional), for the loop analyses.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, asdict, replace

import numpy as np
import numba

from rig.config import STAND_BASE_MASS_KG
from sim_backend.linear import ActuatorParams, discretize_zoh_foh

FRICTION_V_SCALE = 2e-5     # m/s, the tanh smoothing of sign(v) used by the recordings' simulator


@numba.njit(cache=True, inline="always")
def dead_zone(x, width):
    """x less a dead zone of +-width (no output inside it); width <= 0: x unchanged.

    The one rule for a spool overlap or a drive's input deadband, in every simulator and diagnosis model."""
    if width <= 0.0:
        return x
    if x > width:
        return x - width
    if x < -width:
        return x + width
    return 0.0


@dataclass(frozen=True)
class Effects:
    delay_s: float = 0.0
    saturation_limit_ma: float = 0.0          # 0 = off
    deadband_width_ma: float = 0.0            # 0 = off
    friction_force_n: float = 0.0             # 0 = off
    base_frequency_hz: float = 0.0            # 0 = off
    base_damping_ratio: float = 0.03
    base_mass_kg: float = STAND_BASE_MASS_KG  # rig/config.py: 5 M, fitted on p03_base
    disturbance_frequency_hz: float = 0.0     # 0 = off
    disturbance_force_n: float = 0.0
    disturbance_phase_rad: float = 0.0
    position_noise_m: float = 0.0
    accel_noise_mps2: float = 0.0
    seed: int = 0
    base_motion_rms_m: float = 0.0            # the floor under the stand (StandBank), 0 = still

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


def stand_prm(p: ActuatorParams, fx: Effects) -> np.ndarray:
    """The compiled plant's parameter vector (the layout _deriv reads): the actuator, then the effects' terms."""
    m_b = fx.base_mass_kg
    w_b = 2 * math.pi * fx.base_frequency_hz
    return np.array([p.M, p.A_p, p.C, p.V_t, p.K_L, p.K_Q, p.K_C, p.w_nv, p.zeta, p.beta,
                     fx.saturation_limit_ma, fx.deadband_width_ma, fx.friction_force_n,
                     1.0 if fx.base_frequency_hz > 0 else 0.0, m_b, m_b * w_b ** 2,
                     2 * fx.base_damping_ratio * m_b * w_b], dtype=float)


@numba.njit(cache=True, fastmath=False)
def _deriv(y, i_cmd, f_dist, xg, vg, prm, out):
    # prm: M A_p C V_t K_L K_Q K_C w_nv zeta beta sat dead fric base_on m_b k_b c_b; xg, vg: the floor
    M = prm[0]; A_p = prm[1]; C = prm[2]; V_t = prm[3]; K_L = prm[4]; K_Q = prm[5]; K_C = prm[6]
    w_nv = prm[7]; zeta = prm[8]; beta = prm[9]; dead = prm[11]; fric = prm[12]
    base_on = prm[13]; m_b = prm[14]; k_b = prm[15]; c_b = prm[16]
    xv = y[0]; vv = y[1]; PL = y[2]; xp = y[3]; vp = y[4]; xb = y[5]; vb = y[6]
    # Eq. 1: second-order spool, driven by the (possibly saturated) driver current
    out[0] = vv
    out[1] = w_nv * w_nv * (i_cmd - xv) - 2.0 * zeta * w_nv * vv
    xe = dead_zone(xv, dead)                # spool overlap: no flow inside +-dead
    if base_on > 0.0:
        y_rel = xp - xb
        v_rel = vp - vb
    else:                                   # the housing rigid on the floor
        y_rel = xp - xg
        v_rel = vp - vg
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
        out[6] = (-f_act - k_b * (xb - xg) - c_b * (vb - vg)) / m_b   # the actuator's reaction on the stand
    else:
        out[5] = 0.0
        out[6] = 0.0


@numba.njit(cache=True, nogil=True)     # nogil: a signal reaches the main thread meanwhile
def _simulate(cmd_V, fs, n_sub, delay_s, K_v, sat, prm, dist_f, dist_F, dist_ph, pos_out, acc_out, spool_out):
    """The whole record: sample the outputs at t_k, then integrate [t_k, t_k+1) with `_advance_stand`
    (the command array itself serves as the command history)."""
    y = np.zeros(7)
    out = np.zeros(3)
    work = np.zeros((5, 7))
    ground = np.zeros(4)
    for k in range(cmd_V.shape[0]):
        pos_out[k] = y[3]          # transducer: absolute piston position (see module docstring)
        spool_out[k] = y[0]
        _advance_stand(y, k, cmd_V, fs, n_sub, delay_s, K_v, sat, prm, dist_f, dist_F, dist_ph, ground, out,
                       work)
        acc_out[k] = out[0]


def simulate_stand(p: ActuatorParams, cmd_V: np.ndarray, fs: float, fx: Effects = Effects(),
                   *, inner_step: float | None = None, fine_near_rest: bool = False) -> dict[str, np.ndarray]:
    """Simulate the actuator on its stand for a command sampled at fs (held between samples).

    Returns arrays at the sample instants: position_m, accel_mps2, spool_mA (noise added as configured).
    fine_near_rest: with friction (and no disturbance force), the short inner step that the friction's tanh slope
    needs only in the inner steps where the piston's velocity comes within reach of it; the others take the
    step without friction (_simulate_near_rest, on the same _deriv: 1.5x faster, positions within 1e-13 m of the fixed
    step's on 100 s chirps at 2 kHz with 200-800 N).
    """
    cmd = np.ascontiguousarray(cmd_V, dtype=float)
    h = inner_step or inner_step_s(p, fx)
    n_sub = max(1, int(math.ceil(1.0 / (fs * h))))
    prm = stand_prm(p, fx)
    n = cmd.shape[0]
    pos = np.empty(n); acc = np.empty(n); spool = np.empty(n)
    dist_F = fx.disturbance_force_n if fx.disturbance_frequency_hz > 0 else 0.0
    if fine_near_rest and inner_step is None and fx.friction_force_n > 0 and dist_F == 0.0:
        h_free = inner_step_s(p, replace(fx, friction_force_n=0.0))
        n_free = max(1, int(math.ceil(1.0 / (fs * h_free))))
        n_fine = max(1, int(math.ceil(n_sub / n_free)))
        _simulate_near_rest(cmd, float(fs), n_free, n_fine, _near_rest_speed(p, fx, fs * n_free), fx.delay_s, p.K_v,
                            fx.saturation_limit_ma, prm, pos, acc, spool)
    else:
        _simulate(cmd, float(fs), n_sub, fx.delay_s, p.K_v, fx.saturation_limit_ma, prm,
                  fx.disturbance_frequency_hz, dist_F, fx.disturbance_phase_rad, pos, acc, spool)
    if fx.position_noise_m > 0 or fx.accel_noise_mps2 > 0:
        rng = np.random.default_rng(fx.seed)
        pos = pos + fx.position_noise_m * rng.standard_normal(n)
        acc = acc + fx.accel_noise_mps2 * rng.standard_normal(n)
    return {"position_m": pos, "accel_mps2": acc, "spool_mA": spool}


def _near_rest_speed(p: ActuatorParams, fx: Effects, rate_hz: float) -> float:
    """The piston speed below which the friction's tanh slope, F/v_s sech^2(v/v_s), puts an RK4 step of
    1/rate_hz beyond inner_step_s's margin (h slope / M <= 1)."""
    ratio = p.M * rate_hz / (fx.friction_force_n / FRICTION_V_SCALE)
    return FRICTION_V_SCALE * math.acosh(math.sqrt(1.0 / ratio)) if ratio < 1.0 else 0.0


@numba.njit(cache=True)
def _rk4_still(y, t, h, k, cmd_V, fs, delay_s, K_v, sat, prm, v_near, watch, work):
    """One RK4 step of h from t of the stand's physics (_deriv; still floor, no disturbance force), y advanced in
    place: (ok, the acceleration at t). watch: ok False (y not advanced) once a stage's piston velocity is below
    v_near (its friction slope needs a shorter step), or where the delayed command switches inside the step (RK4
    across the jump errs in proportion to the step: the short step keeps a delay as the fixed step had it)."""
    k1 = work[0]; k2 = work[1]; k3 = work[2]; k4 = work[3]; yt = work[4]
    base_on = prm[13] > 0.0
    if watch and min(int(math.floor((t - delay_s) * fs + 1e-9)), k) != min(int(math.floor((t + h - delay_s) * fs
                                                                                          + 1e-9)), k):
        return False, 0.0
    for q in range(7):
        yt[q] = y[q]
    for stage in range(4):
        ts = t if stage == 0 else (t + h if stage == 3 else t + 0.5 * h)
        idx = min(int(math.floor((ts - delay_s) * fs + 1e-9)), k)
        i_cmd = K_v * (0.0 if idx < 0 else cmd_V[idx])
        if sat > 0.0:
            i_cmd = min(max(i_cmd, -sat), sat)
        if watch and abs(yt[4] - yt[6] if base_on else yt[4]) < v_near:
            return False, 0.0
        ks = k1 if stage == 0 else (k2 if stage == 1 else (k3 if stage == 2 else k4))
        _deriv(yt, i_cmd, 0.0, 0.0, 0.0, prm, ks)
        g = h if stage == 2 else 0.5 * h
        for q in range(7):
            yt[q] = y[q] + g * ks[q]
    for q in range(7):
        y[q] += h / 6.0 * (k1[q] + 2.0 * k2[q] + 2.0 * k3[q] + k4[q])
    return True, k1[4]


@numba.njit(cache=True, nogil=True)
def _simulate_near_rest(cmd_V, fs, n_free, n_fine, v_near, delay_s, K_v, sat, prm, pos_out, acc_out, spool_out):
    """_simulate (still floor, no disturbance force) at n_free inner steps a sample; an inner step in which the
    piston's velocity comes below v_near, or the delayed command switches, is taken again as n_fine shorter ones."""
    y = np.zeros(7)
    work = np.zeros((5, 7))
    h = 1.0 / (fs * n_free)
    hf = h / n_fine
    for k in range(cmd_V.shape[0]):
        pos_out[k] = y[3]
        spool_out[k] = y[0]
        t0 = k / fs
        for j in range(n_free):
            t = t0 + j * h
            ok, a = _rk4_still(y, t, h, k, cmd_V, fs, delay_s, K_v, sat, prm, v_near, True, work)
            if not ok:
                for i in range(n_fine):
                    _, a_f = _rk4_still(y, t + i * hf, hf, k, cmd_V, fs, delay_s, K_v, sat, prm, 0.0, False, work)
                    if i == 0:
                        a = a_f
            if j == 0:
                acc_out[k] = a


def linear_chirp(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0,
                 amplitude_V: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's identification input: a linear sine chirp, sampled at fs. Returns (t_s, cmd_V)."""
    n = int(round(duration_s * fs))
    t = np.arange(n) / fs
    phase = 2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) / duration_s * t ** 2)
    return t, amplitude_V * np.sin(phase)


@numba.njit(cache=True)
def _advance_stand(y, k, hist, fs, n_sub, delay_s, K_v, sat, prm, dist_f, dist_F, dist_ph, ground, out, work):
    """Advance the stand one sample period [t_k, t_k+1) with commands from the ring `hist` (index mod len);
    ground = (x_g, v_g at t_k, x_g, v_g at t_k+1), interpolated linearly in between (the floor moves
    continuously).

    out[0] = acceleration at t_k (before advancing), out[1] = piston position x_p at t_k+1, out[2] = the
    acceleration at t_k+1 (the command's spool does not enter it directly)."""
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
            fr = (ts - t0) * fs
            xg = ground[0] + fr * (ground[2] - ground[0])
            vg = ground[1] + fr * (ground[3] - ground[1])
            if stage == 0:
                _deriv(y, i_cmd, f_d, xg, vg, prm, k1)
                if j == 0:
                    out[0] = k1[4]
                for q in range(7):
                    yt[q] = y[q] + 0.5 * h * k1[q]
            elif stage == 1:
                _deriv(yt, i_cmd, f_d, xg, vg, prm, k2)
                for q in range(7):
                    yt[q] = y[q] + 0.5 * h * k2[q]
            elif stage == 2:
                _deriv(yt, i_cmd, f_d, xg, vg, prm, k3)
                for q in range(7):
                    yt[q] = y[q] + h * k3[q]
            else:
                _deriv(yt, i_cmd, f_d, xg, vg, prm, k4)
        for q in range(7):
            y[q] += h / 6.0 * (k1[q] + 2.0 * k2[q] + 2.0 * k3[q] + k4[q])
    out[1] = y[3]
    t1 = (k + 1) / fs
    f_d = dist_F * math.sin(w_d * t1 + dist_ph) if dist_F != 0.0 else 0.0
    _deriv(y, 0.0, f_d, ground[2], ground[3], prm, k1)
    out[2] = k1[4]


class StandPlant:
    """One actuator on its test stand, stepped one sample period at a time (for the loop's sim backend).

    Same physics and effects as `simulate_stand` (a test checks they agree). `step(cmd_V)` holds cmd_V over
    one period; afterwards `position_m` is the transducer value at the new instant and `accel_mps2` the
    acceleration at the start of the period (as sampled by the ADC at t_k), both with sensor noise;
    `accel_now_mps2` is the acceleration at the new instant (with noise), `x_abs_m` the piston's true
    absolute position. `ground` = (x_g, v_g at t_k, x_g, v_g at t_k+1): the floor under the stand.

    Linear effects only (no delay, saturation, deadband, friction or disturbance): the period is stepped
    exactly (stand_state_space discretised, command held, floor interpolated: one matrix product), else by
    RK4; a test holds the two against each other."""

    n_mounts = 1

    def __init__(self, p: ActuatorParams, fx: Effects = Effects(), fs: float = 1000.0, *,
                 inner_step: float | None = None):
        self.p, self.fx, self.fs = p, fx, float(fs)
        self.linear = not (fx.delay_s or fx.saturation_limit_ma or fx.deadband_width_ma or fx.friction_force_n
                           or (fx.disturbance_frequency_hz and fx.disturbance_force_n))
        if self.linear:
            A, B, C, D = stand_state_space(p, fx)
            self._Ad, Bu, G0, G1 = discretize_zoh_foh(A, B[:, :1], B[:, 1:], 1.0 / self.fs)
            self._Bu = np.ascontiguousarray(Bu[:, 0])
            self._G = np.ascontiguousarray(np.hstack([G0, G1]))      # times (x_g, v_g at t_k, at t_k+1)
            self._ca, self._da = np.ascontiguousarray(C[1]), np.ascontiguousarray(D[1, 1:])
        h = inner_step or inner_step_s(p, fx)
        self.n_sub = max(1, int(math.ceil(1.0 / (fs * h))))
        self.prm = stand_prm(p, fx)
        self.hist = np.zeros(int(math.ceil(fx.delay_s * fs)) + 4)
        self.y = np.zeros(7)
        self.k = 0
        self._out = np.zeros(3)
        self._work = np.zeros((5, 7))
        self._still = np.zeros(4)
        self.rng = np.random.default_rng(fx.seed)
        self.position_m = self._noisy_pos(0.0)
        self.accel_mps2 = 0.0
        self.accel_now_mps2 = 0.0
        self.x_abs_m = 0.0
        self.t_s = 0.0
        # compile (or load) the step now: a first compile inside a running loop stalls it past its watchdog
        _advance_stand(np.zeros(7), 0, np.zeros_like(self.hist), self.fs, 1, fx.delay_s, p.K_v, 0.0, self.prm,
                       0.0, 0.0, 0.0, np.zeros(4), np.zeros(3), np.zeros((5, 7)))
        if self.linear:
            _step_linear(self._Ad, self._Bu, self._G, self._ca, self._da, np.zeros(7), 0.0, self._still,
                         np.zeros(3))

    def _noisy_pos(self, x):
        return x + (self.fx.position_noise_m * self.rng.standard_normal() if self.fx.position_noise_m else 0.0)

    def _noisy_acc(self, a):
        return a + (self.fx.accel_noise_mps2 * self.rng.standard_normal() if self.fx.accel_noise_mps2 else 0.0)

    def step(self, cmd_V: float, ground=None) -> tuple[float, float]:
        fx = self.fx
        g = self._still if ground is None else ground
        if self.linear:
            _step_linear(self._Ad, self._Bu, self._G, self._ca, self._da, self.y, float(cmd_V), g, self._out)
        else:
            self.hist[self.k % len(self.hist)] = cmd_V
            _advance_stand(self.y, self.k, self.hist, self.fs, self.n_sub, fx.delay_s, self.p.K_v,
                           fx.saturation_limit_ma, self.prm, fx.disturbance_frequency_hz,
                           fx.disturbance_force_n if fx.disturbance_frequency_hz > 0 else 0.0,
                           fx.disturbance_phase_rad, g, self._out, self._work)
        self.k += 1
        self.t_s = self.k / self.fs
        self.accel_mps2 = self._noisy_acc(float(self._out[0]))
        self.x_abs_m = float(self._out[1])
        self.position_m = self._noisy_pos(self.x_abs_m - float(g[2]))      # against the floor frame
        if ground is not None:
            self.accel_now_mps2 = self._noisy_acc(float(self._out[2]))
        return self.position_m, self.accel_mps2


@numba.njit(cache=True)
def _step_linear(Ad, Bu, G, ca, da, y, u, g, out):
    """One exact period of the linear stand: out as _advance_stand's (accel at t_k, x_p and accel at t_k+1)."""
    n = Ad.shape[0]
    x = y[:n]
    out[0] = ca @ x + da[0] * g[0] + da[1] * g[1]
    xn = Ad @ x + Bu * u + G[:, 0] * g[0] + G[:, 1] * g[1] + G[:, 2] * g[2] + G[:, 3] * g[3]
    y[:n] = xn
    out[1] = xn[3]
    out[2] = ca @ xn + da[0] * g[2] + da[1] * g[3]


class StandBank:
    """n actuators, each alone on its test stand, on one floor: the plant of the `stand` layout (one mount is
    the prototype). After `step(valve_cmd_V)` the attributes hold the values at the new instant, as the
    four-mount plant's do: accel_mps2 (absolute, the load's accelerometer) and stroke_m (the transducer,
    piston against the floor frame), with sensor noise; table_m the loads' true absolute positions (the
    isolation figure), floor_m the floor. floor: a FloorMotion over n mounts (base_motion), or None.

    When every stand is linear (StandPlant.linear) the bank steps them all in one exact matrix product, with
    the floor and the sensor noise drawn in blocks (the loop's simulated port reads it every period);
    otherwise each stand by its own RK4."""

    BLOCK = 256

    def __init__(self, stands, floor=None) -> None:
        self.stands = list(stands)
        self.n_mounts = n = len(self.stands)
        self.floor = floor
        self.accel_mps2 = [0.0] * n
        self.stroke_m = [float(s.position_m) for s in self.stands]
        self.table_m = [0.0] * n
        self.t_s = 0.0
        self.k = 0
        self._g = np.zeros((n, 4))
        self._block = np.zeros((0, 2 * n))
        self._j = 0
        self._block_next = None
        self.exact = all(s.linear for s in self.stands)
        if self.exact:
            self._build_exact()

    def _build_exact(self) -> None:
        """One block-diagonal system: X <- Ad X + B w, w = (u (n), floor at t_k (2n), at t_k+1 (2n));
        Y = (accel, x_p at t_k+1) = C X + D w."""
        n = self.n_mounts
        sizes = [s._Ad.shape[0] for s in self.stands]
        N = sum(sizes)
        Ad, B = np.zeros((N, N)), np.zeros((N, 5 * n))
        C, D = np.zeros((2 * n, N)), np.zeros((2 * n, 5 * n))
        o = 0
        for i, (s, k) in enumerate(zip(self.stands, sizes)):
            Ad[o:o + k, o:o + k] = s._Ad
            B[o:o + k, i] = s._Bu
            for j, col in enumerate((n + 2 * i, n + 2 * i + 1, 3 * n + 2 * i, 3 * n + 2 * i + 1)):
                B[o:o + k, col] = s._G[:, j]
            C[i, o:o + k] = s._ca
            D[i, 3 * n + 2 * i:3 * n + 2 * i + 2] = s._da
            C[n + i, o + 3] = 1.0
            o += k
        self._X, self._w, self._y = np.zeros(N), np.zeros(5 * n), np.zeros(3 * n)
        self._M = np.ascontiguousarray(np.vstack([np.hstack([Ad, B]), np.hstack([C, D])]))   # one array to hand over
        fx = self.stands[0].fx
        self._sd = np.array([s.fx.accel_noise_mps2 for s in self.stands] + [s.fx.position_noise_m for s in self.stands])
        self._rng = np.random.default_rng(fx.seed)
        self._noise = np.zeros((0, 2 * n))
        self._nj = 0
        self._noise_next = None
        # compile (or load) the bank's step now, not in the loop's first period (the watchdog)
        _bank_step(self._M, np.zeros(N), np.zeros(5 * n), np.zeros((n, 4)), np.zeros(2 * n), self.floor is not None,
                   np.zeros(2 * n), np.zeros(3 * n))

    def prefetch(self) -> None:
        """Draw the next blocks of floor motion and sensor noise ahead of time, between steps (the simulated
        port's idle time, the HIL plant's server after its TPDOs), so no step pays for a draw; the sequence is
        the same either way."""
        half = self.BLOCK // 2
        if self.exact and self._noise_next is None and self._nj >= len(self._noise) - half:
            self._noise_next = self._rng.standard_normal((self.BLOCK, 2 * self.n_mounts)) * self._sd
        if self.floor is not None and self._block_next is None and self._j >= len(self._block) - half:
            self._block_next = self.floor.next_block(self.BLOCK)

    def _next_floor(self) -> None:
        nxt, self._block_next = self._block_next, None
        self._block, self._j = (nxt if nxt is not None else self.floor.next_block(self.BLOCK)), 0

    def _floor_step(self) -> None:
        g = self._g
        if self.floor is not None:
            if self._j >= len(self._block):             # floor motion drawn in blocks (a draw costs ~20 us)
                self._next_floor()
            b = self._block[self._j]                    # x_g (n), v_g (n) at the new instant
            self._j += 1
            n = self.n_mounts
            g[:, 0:2] = g[:, 2:4]
            g[:, 2] = b[:n]
            g[:, 3] = b[n:2 * n]

    def step(self, valve_cmd_V) -> None:
        n = self.n_mounts
        g = self._g
        if self.exact:
            w = self._w
            w[:n] = valve_cmd_V
            if self._nj >= len(self._noise):
                nxt, self._noise_next = self._noise_next, None
                self._noise = nxt if nxt is not None else self._rng.standard_normal((self.BLOCK, 2 * n)) * self._sd
                self._nj = 0
            if self.floor is not None and self._j >= len(self._block):
                self._next_floor()
            y = self._y
            _bank_step(self._M, self._X, w, g, self._block[self._j] if self.floor is not None else self._noise[0],
                       self.floor is not None, self._noise[self._nj], y)
            self._nj += 1
            self._j += 1
            self.accel_mps2 = y[:n].tolist()             # fresh lists (never edited in place)
            self.stroke_m = y[n:2 * n].tolist()
            self.table_m = y[2 * n:].tolist()
            self.k += 1
            self.t_s = self.k / self.stands[0].fs
        else:
            self._floor_step()
            acc, xs, tab = [0.0] * n, [0.0] * n, [0.0] * n
            for i, s in enumerate(self.stands):
                s.step(float(valve_cmd_V[i]), g[i])
                acc[i], xs[i], tab[i] = s.accel_now_mps2, s.position_m, s.x_abs_m
            self.accel_mps2, self.stroke_m, self.table_m = acc, xs, tab
            self.t_s = self.stands[0].t_s

    @property
    def floor_m(self) -> list:
        """The floor under each stand at the last instant."""
        return self._g[:, 2].tolist()


@numba.njit(cache=True)
def _bank_step(M, X, w, g, b, moving, noise, y):
    """The stand bank's exact period: the floor g moves on to b (x_g, v_g at t_k+1) if moving; w = (u, floor
    at t_k, at t_k+1); X <- Ad X + B w; y = (accel + noise, x_p - x_g + noise, x_p) at t_k+1 from C X + D w.
    M = [[Ad, B], [C, D]]."""
    N = X.shape[0]
    n = g.shape[0]
    if moving:
        for i in range(n):
            g[i, 0] = g[i, 2]
            g[i, 1] = g[i, 3]
            g[i, 2] = b[i]
            g[i, 3] = b[n + i]
    for i in range(n):
        w[n + 2 * i] = g[i, 0]
        w[n + 2 * i + 1] = g[i, 1]
        w[3 * n + 2 * i] = g[i, 2]
        w[3 * n + 2 * i + 1] = g[i, 3]
    nw = w.shape[0]
    Xn = np.empty(N)
    for r in range(N):
        acc = 0.0
        for c in range(N):
            acc += M[r, c] * X[c]
        for c in range(nw):
            acc += M[r, N + c] * w[c]
        Xn[r] = acc
    X[:] = Xn
    for r in range(2 * n):
        acc = 0.0
        for c in range(N):
            acc += M[N + r, c] * X[c]
        for c in range(nw):
            acc += M[N + r, N + c] * w[c]
        if r < n:
            y[r] = acc + noise[r]                      # accelerometer
        else:
            y[n + r] = acc                             # the load's true x_p
            y[r] = acc - g[r - n, 2] + noise[r]        # transducer, against the floor frame


def stand_state_space(p: ActuatorParams, fx: Effects = Effects()):
    """The stand's physics, linear (Eqs. 1, 3, 6, 7; base mode as configured, other effects off), as
    continuous (A, B, C, D): states x_v, dx_v/dt, P_L, x_p, v_p (+ x_b, v_b with the base mode); inputs u [V],
    x_g, v_g (the floor); outputs position_m (transducer, x_p - x_g), accel_mps2 (absolute), x_p (absolute)."""
    base = fx.base_frequency_hz > 0
    n = 7 if base else 5
    A = np.zeros((n, n))
    B = np.zeros((n, 3))
    g = 4 * p.beta / p.V_t
    A[0, 1] = 1.0                                             # Eq. 1
    A[1, 0] = -p.w_nv ** 2
    A[1, 1] = -2 * p.zeta * p.w_nv
    B[1, 0] = p.w_nv ** 2 * p.K_v
    A[2, 0] = g * p.K_Q                                       # Eqs. 3, 6
    A[2, 2] = -g * p.K_C
    A[3, 4] = 1.0
    rel = np.zeros((2, n + 2))     # (y_rel, v_rel) as rows over [states, x_g, v_g]
    rel[0, 3] = rel[1, 4] = 1.0
    if base:
        rel[0, 5] = rel[1, 6] = -1.0
    else:
        rel[0, n] = rel[1, n + 1] = -1.0
    f_act = p.A_p * np.eye(1, n + 2, 2)[0] - p.K_L * rel[0] - p.C * rel[1]     # Eq. 7: A_p P_L - K_L y - C v
    A[2] += -g * p.A_p * rel[1, :n]
    B[2, 1:] = -g * p.A_p * rel[1, n:]
    A[4] += f_act[:n] / p.M
    B[4, 1:] = f_act[n:] / p.M
    if base:
        m_b = fx.base_mass_kg
        w_b = 2 * math.pi * fx.base_frequency_hz
        k_b, c_b = m_b * w_b ** 2, 2 * fx.base_damping_ratio * m_b * w_b
        A[5, 6] = 1.0
        A[6] += -f_act[:n] / m_b
        A[6, 5] -= k_b / m_b
        A[6, 6] -= c_b / m_b
        B[6, 1:] = -f_act[n:] / m_b + np.array([k_b, c_b]) / m_b
    C = np.zeros((3, n))
    D = np.zeros((3, 3))
    C[0, 3] = 1.0
    D[0, 1] = -1.0
    C[1] = A[4]
    D[1] = B[4]
    C[2, 3] = 1.0
    return A, B, C, D

"""Reference tracking of one actuator alone (paper Fig. 4, ~95 Hz bandwidth): a discrete PID on position.

  u = Kp e + Ki/s e + Kd s/(1 + s/w_d) e,   e = r - x_p       (Tustin for the integral and the filtered D)

The plant is G_EHA (Eq. 10, sim_backend/linear.py g_eha) on its test stand. The integral corner Ki/Kp is put at
the actuator's low-frequency lag K_C K_L / A_p^2 (~7.4 Hz), which turns the loop into ~k/s * G_valve: the
bandwidth is then set by Kp against the valve's 83 Hz mode. Explicit state, no clock, I/O or globals;
conditional-integration anti-windup against the output clamp and slew limit.

`pid_step` (numba) is the law, the one implementation: rig/kernel.py runs it for a mount of this kind with the
reference held in the state's `reference_m` slot (0: the piston held at mid-stroke); TrackingPID builds the
coefficients and the named state and calls the same law for design tools and tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numba
import numpy as np

from controllers.limits import clamp, slew
from controllers.state import step_law
from rig.config import ControllerConfig, SafetyConfig
from sim_backend.linear import g_eha

KIND = 3                      # rig/kernel.py dispatches on it

STATE_NAMES = ("integral_V", "error_prev_m", "deriv_V", "cmd_prev_V", "reference_m")
_I, _E, _D, _U, _R = range(5)
COEFFICIENTS = ("kp", "half_dt_ki", "ad", "bd", "limit_V", "slew_V")
_KP, _HI, _AD, _BD, _LIM, _SLEW = range(6)


_CC, _SC = ControllerConfig(), SafetyConfig()      # the one source of defaults: rig/config.py


@dataclass(frozen=True)
class PIDParams:
    kp_V_per_m: float = _CC.track_kp_V_per_m
    ki_V_per_ms: float = _CC.track_ki_V_per_ms
    kd_Vs_per_m: float = _CC.track_kd_Vs_per_m
    deriv_hz: float = _CC.track_deriv_hz
    limit_V: float = _SC.valve_limit_V
    slew_V_per_s: float = _SC.slew_V_per_s


class TrackingPID:
    """step(state, (reference_m, position_m), dt) -> (valve_cmd_V, state); state updated in place."""

    kind = KIND
    state_names = STATE_NAMES

    def __init__(self, p: PIDParams, dt: float, name: str = ""):
        self.p = p
        self.dt = float(dt)
        self.name = name
        wd = 2 * math.pi * p.deriv_hz
        # Tustin of Kd s/(1 + s/wd): y_k = ad y_{k-1} + bd (e_k - e_{k-1})
        c = 2.0 / dt
        self.ad = (c - wd) / (c + wd)
        self.bd = p.kd_Vs_per_m * wd * c / (c + wd)
        self.hi = 0.5 * dt * p.ki_V_per_ms
        self.slew = p.slew_V_per_s * dt
        self._coef = self.coefficients()

    def coefficients(self) -> np.ndarray:
        return np.array((self.p.kp_V_per_m, self.hi, self.ad, self.bd, self.p.limit_V, self.slew))

    def initial_state(self) -> list[float]:
        return [0.0] * len(STATE_NAMES)

    def set_enabled(self, state, on: bool):
        """No isolation to switch: the PID holds its reference either way."""
        return state

    def step(self, state, meas, dt: float):
        if abs(dt - self.dt) > 1e-6 * self.dt:
            raise ValueError(f"controller built for dt={self.dt} s, stepped with dt={dt} s")
        return step_law(pid_step, state, self._coef, float(meas[0]), float(meas[1])), state

    def frf(self, w: np.ndarray) -> np.ndarray:
        """C(z) at z = exp(j w dt), linear range."""
        zi = np.exp(-1j * np.asarray(w, dtype=float) * self.dt)
        integ = self.hi * (1 + zi) / (1 - zi)
        deriv = self.bd * (1 - zi) / (1 - self.ad * zi)
        return self.p.kp_V_per_m + integ + deriv


@numba.njit(cache=True)
def pid_step(st, cf, r, x):
    """One period: reference r and position x [m] -> valve command [V]; st (STATE_NAMES) updated in place."""
    e = r - x
    d_i = cf[_HI] * (e + st[_E])
    integ = st[_I] + d_i
    d = cf[_AD] * st[_D] + cf[_BD] * (e - st[_E])
    u = cf[_KP] * e + integ + d
    u, sat = clamp(u, cf[_LIM], 0.0)
    u, sat = slew(u, st[_U], cf[_SLEW], sat)
    if sat * d_i > 0.0:
        integ -= d_i                     # anti-windup: no increment pushing further into the limit
    st[_I] = integ
    st[_E] = e
    st[_D] = d
    st[_U] = u
    return u


def tracking_response(act, ctrl: TrackingPID, f_hz: np.ndarray, delay: int = 1) -> np.ndarray:
    """Closed-loop r -> x_p of the actuator alone: ZOH-discretised G_EHA, the PID, `delay` periods."""
    Gd = control.sample_system(g_eha(act), ctrl.dt, method="zoh")
    w = 2 * np.pi * np.asarray(f_hz, dtype=float)
    z = np.exp(1j * w * ctrl.dt)
    G = np.asarray(Gd(z)).reshape(-1)
    L = ctrl.frf(w) * G * z ** (-delay)
    return L / (1 + L)


def bandwidth_hz(f_hz: np.ndarray, T: np.ndarray) -> float:
    """First frequency where |T| falls 3 dB below its low-frequency value."""
    db = 20 * np.log10(np.abs(T))
    k = np.nonzero(db < db[0] - 3.0)[0]
    return float(f_hz[k[0]]) if len(k) else math.nan


def tune_tracking(act, dt: float, target_hz: float = 95.0, limit_V: float = 10.0, slew_V_per_s: float = 1e4,
                  deriv_hz: float = 1000.0) -> PIDParams:
    """Ki = Kp * (actuator lag corner); for each derivative time Td = Kd/Kp on a grid, Kp by bisection for the
    target bandwidth; keep the one with the smallest resonant peak of |T|."""
    lag = act.lag_corner
    f = np.linspace(1.0, 600.0, 3000)
    best = None
    for td in np.concatenate([[0.0], np.geomspace(1e-5, 3e-3, 24)]):
        lo, hi = 1e3, 1e9
        for _ in range(50):
            kp = math.sqrt(lo * hi)
            c = TrackingPID(PIDParams(kp, kp * lag, kp * td, deriv_hz, limit_V, slew_V_per_s), dt)
            T = tracking_response(act, c, f)
            bw = bandwidth_hz(f, T)
            if math.isnan(bw) or bw > target_hz:
                hi = kp
            else:
                lo = kp
        kp = math.sqrt(lo * hi)
        c = TrackingPID(PIDParams(kp, kp * lag, kp * td, deriv_hz, limit_V, slew_V_per_s), dt)
        T = tracking_response(act, c, f)
        L_ok = abs(bandwidth_hz(f, T) - target_hz) < 2.0
        peak = float(np.max(20 * np.log10(np.abs(T))))
        if L_ok and (best is None or peak < best[0]):
            best = (peak, c.p)
    return best[1]


def pid_from_config(cfg) -> PIDParams:
    c = cfg.controller
    return PIDParams(c.track_kp_V_per_m, c.track_ki_V_per_ms, c.track_kd_Vs_per_m, c.track_deriv_hz,
                     cfg.safety.valve_limit_V, cfg.safety.slew_V_per_s)

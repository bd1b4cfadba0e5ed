"""Floor-motion feedforward of one mount: from a floor accelerometer at the mount, command the valve so that
the actuator's stroke cancels the floor's motion there.

The actuator is far stiffer than the machine, so the mount moves with the floor plus the stroke
(x_p = x_g + stroke, Eq. 13 with K >> machine); commanding stroke = -x_g keeps the mount, and so the machine,
still. Then the machine does not accelerate and the actuator only moves its own piston against the floor, so
valve voltage -> stroke is the actuator's own G_EHA (Eq. 10: valve Eq. 1 times actuator Eq. 8 with the piston's
mass M, its hydraulic mode at ~2 kHz), not the actuator loaded by the machine (~250 Hz): inverting the loaded
one cost 12-15 dB of cancellation at 20-100 Hz on the simulated rig. With that model G(s) the command is

    u_ff = -G^-1(s) x_g,   x_g = a_g / s^2   (a_g: the floor accelerometer)

made realisable as one cascade of second-order sections, designed in continuous time and discretised once
(Tustin, prewarped in the band, explicit dt):

    F(s) = u_ff / a_g = -[1 / (s^2 + sqrt2 w_hp s + w_hp^2)]     band-limited double integration: the
                                                                  2nd-order Butterworth high-pass over s^2
                                                                  (an accelerometer offset or drift then
                                                                  gives a bounded transient, not a ramp)
                        x (s^2 + 2 zeta w_nv s + w_nv^2)/(K_v w_nv^2)         inverse valve, Eq. 1
                        x (A_p/K_Q) (d3 s^3 + d2 s^2 + d1 s + d0)             inverse actuator, Eq. 8
                        x (1 + tau s + (tau s)^2 / 2)                        phase lead for the delays
                        x LP6(s)                                             6th-order Butterworth roll-off
                        x s / (s + w_dc)                                     DC block on the command

The DC block: the double integration's DC gain is 1/w_hp^2, so a floor-accelerometer offset of 1e-5 m/s^2 would
hold the valve volts off null (the stroke 25 um off, beyond what the valve holds against leakage). It is a first-
order section, out = y - z with z the command's slow level, at w_dc (0.05 Hz) once settled. It starts at switch-on:
z = y there (the output starts at 0, bumpless), then z is the mean of y since switch-on until that mean's window
reaches 1/w_dc. So neither the offset nor the start transient (the floor already moving when the filters start,
read by the double integration as an initial velocity) carries into the command, and a slow mode of its own never
runs from the loop's start.

The lead (e^{s tau} to second order) gives back what the path delays: the zero-order hold (half a period),
the loop's one period of computation delay and the roll-off's own group delay at low frequency
(3.8637 / w_lp). Seven zeros over eight poles: the filter is strictly proper and rolls off above w_lp.

A restart (feedforward_restart): floor conversions lost, and stepped as a line across the gap, are a velocity
error to the double integration, and the inverse actuator's leakage term (d0 = K_C K_L / A_p^2 dominates d1 s
below ~7 Hz) turns the stroke error it integrates into a ramp of valve volts, held for seconds by the 0.1 Hz
high-pass. So after a loss the filters start again from rest, the last output fades out, and the output comes
back, bumpless (the DC block starts again, z = y), once the restart's own transient has died out: five time
constants of the slowest corner (restart_s, 16 s at 0.05 Hz).

Why it stops working: the residual is |1 - (1 + e) e^{j phi}| of the floor motion for a gain error e and a
phase error phi (2 sin(phi/2) for phi alone), so a 10 % gain error alone limits the cancellation to 20 dB;
that is why `rig design --identified DIR` designs it on the identified actuator rather than Table 1.

The law takes the actuator figures it needs as parameters (FeedforwardParams; from the config or from an
identification), not the simulator. The step is a compiled function of float arrays (feedforward_step) that the
runtime's period calls per mount (rig/runtime/kernel.py); FeedforwardFilter is its builder (coefficients, state,
switching) with the same interface as the controllers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np

from controllers.discrete import sections_step, sos_frf, tustin_section
from controllers.timebase import check_step
from rig.config import MOUNTS

# state after the sections: output gain (fades between 0 and 1 when switched), switch request, periods since the
# DC block started (0: not started), periods a restart still holds the output off, the output held at the restart
# (fading out), the last output, the periods a restart holds it off (restart_s)
_G, _ON, _K, _WAIT, _HOLD, _LAST, _SETTLE = range(7)
STATE_EXTRA = 7


def butterworth_pairs(order: int) -> list[float]:
    """2 zeta of each pole pair of an even-order Butterworth low-pass (order 4: 0.7654, 1.8478)."""
    return [2 * math.sin((2 * k - 1) * math.pi / (2 * order)) for k in range(1, order // 2 + 1)]


@dataclass(frozen=True)
class FeedforwardParams:
    """The actuator model the feedforward inverts (paper symbols, SI; K_Q per mA, K_v in mA/V) and the
    sensor/roll-off figures. M_kg: the piston's moving mass (Table 1; the machine stays still when the floor
    is cancelled)."""
    K_v: float = 2.0                  # mA/V, valve driver gain (Eq. 1)
    K_Q: float = 1.94e-6              # m^3/s/mA, flow gain (Eq. 3)
    K_C: float = 6.6e-11              # m^3/s/Pa, flow-pressure coefficient (Eq. 3)
    w_nv: float = 524.0               # rad/s, valve natural frequency (Eq. 1)
    zeta: float = 0.65                # valve damping ratio (Eq. 1)
    A_p: float = 3.10e-2              # m^2 (Eq. 6)
    K_L: float = 6.8e8                # N/m (Eq. 7)
    C: float = 1951.0                 # N s/m (Eq. 7)
    V_t: float = 5.39e-4              # m^3 (Eq. 6)
    beta: float = 1.4e9               # Pa (Eq. 6)
    M_kg: float = 56.0                # moving mass of the piston (Eq. 7)
    hp_hz: float = 0.1                # floor accelerometer high-pass (2nd-order Butterworth)
    lowpass_hz: float = 600.0         # Butterworth roll-off corner
    lowpass_order: int = 6            # its order (even, >= 6: the inverse has 7 zeros, HP/s^2 2 poles)
    delay_s: float | None = None      # delay the lead compensates (None: 1.5 periods, ZOH + computation)
    lead_order: int = 2               # 2: 1 + tau s + (tau s)^2/2; 1: 1 + tau s (grows slower above the band)
    prewarp_hz: float = 50.0          # Tustin prewarp: exact in the middle of the floor band
    gain: float = 1.0                 # trim on the whole path (1 = cancel as modelled)
    fade_s: float = 0.1               # on/off: the output gain fades with this time constant
    dc_hz: float = 0.05               # the command's DC block, once settled (an accelerometer offset decays)

    def with_(self, **kw) -> "FeedforwardParams":
        return replace(self, **kw)


def feedforward_params_from_config(cfg) -> FeedforwardParams:
    """The configured actuator (Table 1 unless the config says otherwise) and the [controller] feedforward
    settings."""
    a, v, fl = cfg.actuator, cfg.valve, cfg.fluid
    c = cfg.controller
    return FeedforwardParams(K_v=v.K_v, K_Q=v.K_Q, K_C=v.K_C, w_nv=v.w_nv, zeta=v.zeta, A_p=a.A_p, K_L=a.K_L,
                             C=a.C, V_t=a.V_t, beta=fl.beta, M_kg=a.M,
                             hp_hz=getattr(c, "ff_hp_hz", 0.1), lowpass_hz=getattr(c, "ff_lowpass_hz", 600.0),
                             gain=getattr(c, "ff_gain", 1.0))


def actuator_denominator(p: FeedforwardParams) -> tuple[float, float, float, float]:
    """Eq. 8 with F_L = 0: x_p / x_v = (K_Q/A_p) / (d3 s^3 + d2 s^2 + d1 s + d0)."""
    b4, A2 = 4 * p.beta, p.A_p ** 2
    return (p.V_t * p.M_kg / (b4 * A2), p.K_C * p.M_kg / A2 + p.C * p.V_t / (b4 * A2),
            1 + p.C * p.K_C / A2 + p.K_L * p.V_t / (b4 * A2), p.K_C * p.K_L / A2)


def _quadratics(coeffs) -> list[list[float]]:
    """A real cubic (monic after division) as a first-order and a second-order real factor."""
    r = np.roots(coeffs)
    real = sorted((x.real for x in r if abs(x.imag) < 1e-9 * max(1.0, abs(x))), key=abs)
    cplx = [x for x in r if abs(x.imag) >= 1e-9 * max(1.0, abs(x))]
    if cplx:
        z = cplx[0]
        return [[1.0, -real[0]], [1.0, -2 * z.real, abs(z) ** 2]]
    a, b, c = real
    return [[1.0, -a], [1.0, -(b + c), b * c]]


class FeedforwardFilter:
    """One mount: step(state, accel_floor_mps2, dt) -> (valve_cmd_V, state); the command is added to the
    feedback's. The filters always run; switching fades the output (bumpless)."""

    def __init__(self, params: FeedforwardParams, dt: float, name: str = ""):
        self.p, self.dt, self.name = params, float(dt), name
        p = params
        if p.lowpass_order < 6 or p.lowpass_order % 2:
            raise ValueError(f"lowpass_order: expected an even order >= 6, got {p.lowpass_order}")
        zl = butterworth_pairs(p.lowpass_order)
        # the lead's time constant: ZOH + computation delay, plus the roll-off's group delay at low frequency
        # (sum of 2 zeta_k / w_lp over the Butterworth pairs)
        tau = (1.5 * dt if p.delay_s is None else p.delay_s) + sum(zl) / (2 * math.pi * p.lowpass_hz)
        self.tau_s = tau
        whp, wlp, wnv = 2 * math.pi * p.hp_hz, 2 * math.pi * p.lowpass_hz, p.w_nv
        d3, d2, d1, d0 = actuator_denominator(p)
        first, second = _quadratics([1.0, d2 / d3, d1 / d3, d0 / d3])
        k = -p.gain * d3 * p.A_p / (p.K_Q * p.K_v * wnv * wnv)          # all constant factors
        w2 = wlp * wlp
        # e^{s tau} to second order: 1 + tau s + (tau s)^2 / 2 keeps the magnitude within (w tau)^4 / 8 of 1,
        # where the first-order lead 1 + tau s is already 30 % high at w tau = 0.83 (100 Hz)
        lead = [0.5 * tau * tau, tau, 1.0] if p.lead_order == 2 else [0.0, tau, 1.0]
        self.continuous = [
            ([1.0, 2 * p.zeta * wnv, wnv * wnv], [1.0, math.sqrt(2.0) * whp, whp * whp]),   # valve^-1 / (s^2 HP)
            ([w2 * c for c in second], [1.0, zl[0] * wlp, w2]),                          # actuator pair / LP
            ([w2 * c for c in lead], [1.0, zl[1] * wlp, w2]),                            # lead / LP
            ([k * w2 * c for c in first], [1.0, zl[2] * wlp, w2]),                       # actuator root / LP
        ] + [([w2], [1.0, z * wlp, w2]) for z in zl[3:]]                                # rest of the roll-off
        self.sections = tuple(tustin_section(n, d, dt, p.prewarp_hz) for n, d in self.continuous)
        # the DC block, last: z += alpha (y - z), out = y - z, exactly as feedforward_step runs it once settled
        wdc = 2 * math.pi * p.dc_hz
        self.continuous.append(([1.0, 0.0], [1.0, wdc]))
        self.sections += ((1.0, -1.0, 0.0, -math.exp(-wdc * dt), 0.0),)
        self.coef = np.ravel(np.array(self.sections, dtype=float))      # (b0, b1, b2, a1, a2) per section
        self.fade = math.exp(-dt / p.fade_s)
        self._o = 2 * len(self.sections)
        self.restart_s = 5.0 / (2 * math.pi * min(p.dc_hz, p.hp_hz))

    def initial_state(self, on: bool = False) -> np.ndarray:
        s = np.zeros(self._o + STATE_EXTRA)
        s[self._o + _G] = s[self._o + _ON] = 1.0 if on else 0.0
        s[self._o + _SETTLE] = round(self.restart_s / self.dt)
        return s

    def restarting_s(self, state: np.ndarray) -> float:
        """The time a restart still holds the output off (0: none pending)."""
        return float(state[self._o + _WAIT]) * self.dt

    def set_enabled(self, state: np.ndarray, on: bool) -> np.ndarray:
        state[self._o + _ON] = 1.0 if on else 0.0
        return state

    def enabled(self, state: np.ndarray) -> bool:
        return state[self._o + _ON] > 0.5

    def step(self, state: np.ndarray, accel_floor_mps2: float, dt: float):
        check_step(self.dt, dt, "feedforward")
        return feedforward_step(self.coef, self.fade, state, accel_floor_mps2), state

    def frf(self, w: np.ndarray) -> np.ndarray:
        """Discrete response at z = exp(j w dt) of the command to the floor acceleration [V/(m/s^2)], on."""
        return sos_frf(self.sections, w, self.dt)

    def tf(self):
        """The designed continuous filter as a python-control TransferFunction (for plots and checks)."""
        import control
        g = control.tf([1.0], [1.0])
        for n, d in self.continuous:
            g = g * control.tf(n, d)
        return g


@numba.njit(cache=True)
def feedforward_step(coef: np.ndarray, fade: float, state: np.ndarray, accel_floor_mps2: float) -> float:
    """One period: the sections (coef: flat, five per section) on the floor acceleration, times the output gain,
    which moves towards the switch request (0 or 1; 0 while a restart holds it off) with factor `fade` per period,
    plus the output a restart held (fading out at the same pace). The last section, the DC block,
    starts at switch-on from the command it meets (z = y) and averages from there until its window reaches its
    settled corner (alpha = max(1/k, alpha_dc)). Compiled (numba): the runtime's period (rig/runtime/kernel.py)
    calls it for every mount, FeedforwardFilter.step through the same dispatcher."""
    n = coef.shape[0] // 5
    o = 2 * n
    y, i, c = sections_step(state, coef, 0, 0, n - 1, accel_floor_mps2)
    wait = state[o + 3]
    on = state[o + 1] > 0.5 and wait <= 0.0
    if wait > 0.0:
        state[o + 3] = wait - 1.0
    k = state[o + 2]
    if on and k == 0.0:
        state[i] = -y                                   # transposed direct form: the state is -z
    k = k + 1.0 if on else 0.0
    state[o + 2] = k
    alpha = 1.0 + coef[c + 3]
    if k > 0.0 and 1.0 / k > alpha:
        alpha = 1.0 / k
    out = y + state[i]
    state[i] -= alpha * out
    target = 1.0 if on else 0.0
    g = target + (state[o] - target) * fade
    state[o] = g
    hold = state[o + 4]
    state[o + 4] = hold * fade
    u = g * out + hold
    state[o + 5] = u
    return u


@numba.njit(cache=True)
def feedforward_restart(coef: np.ndarray, state: np.ndarray) -> None:
    """Floor conversions were lost: the filters from rest, the last output fading out, the output held off for
    restart_s (then it fades in as at a switch-on, if still switched on)."""
    o = 2 * (coef.shape[0] // 5)
    state[:o] = 0.0
    state[o + 4] = state[o + 5]
    state[o] = 0.0
    state[o + 2] = 0.0
    state[o + 3] = state[o + 6]


def make_feedforward_filters(cfg, dt: float, params: FeedforwardParams | None = None,
                             names: tuple[str, ...] | None = None) -> list[FeedforwardFilter]:
    """One filter per mount (rig.config.MOUNTS order, or `names`)."""
    p = params or feedforward_params_from_config(cfg)
    return [FeedforwardFilter(p, dt, name=m) for m in (names or MOUNTS)]

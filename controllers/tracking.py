"""Reference tracking of one actuator alone (paper Fig. 4, ~95 Hz bandwidth): a discrete PID on position, with
the reference generated in the law and fed forward through the actuator's inverse.

  u = Kp e + Ki/s e + Kd s/(1 + s/w_d) e + u_ff,   e = r - x_p       (Tustin for the integral and the filtered D)
  u_ff = ff (dr/dt + K_C K_L/A_p^2 r) / (K_v K_Q / A_p)            evaluated P periods ahead of r

The plant is G_EHA (Eq. 10, sim_backend/linear.py g_eha) on its test stand. The integral corner Ki/Kp is put at
the actuator's low-frequency lag K_C K_L / A_p^2 (~7.4 Hz), which turns the loop into ~k/s * G_valve: the
bandwidth is then set by Kp against the valve's 83 Hz mode. The feedforward is the inverse of Eq. 9 below the
hydraulic mode (flow integrator with the leakage lag); the valve, which at low frequency is a delay of
2 zeta / w_nv (~2.5 ms), and the loop's own delay (ZOH + computation) are covered by running the reference P
periods ahead: the law generates the reference on that lead timeline, feeds it forward, and closes the loop
on the same reference P periods later (a ring of the last P + 1 lead values). Explicit state, no clock, I/O
or globals; conditional-integration anti-windup against the output clamp and slew limit. A position sample
equal to the last one, bit for bit, is taken as no new sample (a transducer that did not deliver: a serial
amplifier slower than the loop): the feedback holds its last output while the reference and its
feedforward move on, instead of integrating the same error again; for at most HOLD_MAX_S, after which a
constant reading is taken as the position (a noise-free simulation at rest).

The reference (controllers/reference.py requests): a hold position (`offset_m`) that moves towards its
`target_m` at most at the rate limit, plus a waveform (sine, chirp, or a profile table in the coefficients)
that starts once the offset has arrived; a finished waveform is folded into the hold position. A new request
starts from the current lead value, so the reference never jumps.

`track_step` (numba) is the law, the one implementation: rig/runtime/kernel.py runs it for a mount of this kind (and
controllers/modes.py inside the operating modes); TrackingPID builds the coefficients and the named state,
checks and applies requests, and calls the same law for design tools and tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numba
import numpy as np

from controllers.limits import clamp, slew
from controllers.reference import Reference, check_stroke, positions_m
from controllers.state import step_law
from controllers.timebase import check_step
from rig.config import ControllerConfig, SafetyConfig
from rig.errors import RigError
from sim_backend.linear import ActuatorParams, g_eha

KIND = 3                      # rig/runtime/kernel.py dispatches on it

STATE_NAMES = ("integral_V", "error_m", "deriv_V", "cmd_prev_V", "reference_m", "feedforward_V", "lead_m",
               "lead_rate_mps", "offset_m", "offset_rate_mps", "target_m", "wave", "wave_t_s", "amp_m", "f0_hz",
               "f1_hz", "span_s", "ring_at", "position_prev_m", "feedback_V", "held")
(_I, _E, _D, _U, _R, _FF, _LEAD, _LV, _O, _OV, _TGT, _WAVE, _WT, _AMP, _F0, _F1, _SPAN,
 _AT, _XP, _FB, _HELD) = range(len(STATE_NAMES))
_RING = len(STATE_NAMES)      # then ring0 .. ringP: the last P + 1 lead values
COEFFICIENTS = ("kp", "half_dt_ki", "ad", "bd", "limit_V", "slew_V", "ff_V_per_mps", "lag_rad_s", "rate_mps",
                "accel_mps2", "dt_s", "preview", "profile_len", "hold_max")
(_KP, _HI, _AD, _BD, _LIM, _SLEW, _FFK, _LAG, _RATE, _ACC, _DT, _PRE, _PLEN, _HMAX) = range(len(COEFFICIENTS))
HOLD_MAX_S = 0.05             # a repeated position is no new sample for at most this long (then it is the position)
_TABLE = len(COEFFICIENTS)    # then the profile table (profile_len samples at dt)
WAVE_NONE, WAVE_SINE, WAVE_CHIRP, WAVE_TABLE = 0, 1, 2, 3
_WAVES = {"sine": WAVE_SINE, "chirp": WAVE_CHIRP, "csv": WAVE_TABLE}


_CC, _SC = ControllerConfig(), SafetyConfig()      # the one source of defaults: rig/config.py


@dataclass(frozen=True)
class PIDParams:
    kp_V_per_m: float = _CC.track_kp_V_per_m
    ki_V_per_ms: float = _CC.track_ki_V_per_ms
    kd_Vs_per_m: float = _CC.track_kd_Vs_per_m
    deriv_hz: float = _CC.track_deriv_hz
    limit_V: float = _SC.valve_limit_V
    slew_V_per_s: float = _SC.slew_V_per_s


@dataclass(frozen=True)
class ReferenceParams:
    """The reference side: the actuator's figures the feedforward and the checks need (Eq. 9), the preview,
    the rate limit and the profile capacity. The defaults switch it all off (a plain PID on a held reference)."""
    flow_gain_m_per_Vs: float = math.inf   # K_v K_Q / A_p: piston velocity per volt above the lag corner
    lag_rad_s: float = 0.0                 # K_C K_L / A_p^2
    ff: float = 0.0                        # feedforward gain, 0..1
    preview_periods: int = 0               # P: the reference runs this many periods ahead of the loop's
    rate_m_per_s: float = math.inf         # hold-position rate limit
    accel_m_per_s2: float = math.inf       # and its acceleration limit (the velocity, so the feedforward,
                                           # never jumps)
    profile_len: int = 0                   # samples of the profile table
    stroke_limit_m: float = math.inf       # a reference beyond it is refused
    headroom: float = 1.0                  # share of limit_V a reference's feedforward may need


def preview_periods(act: ActuatorParams, dt: float, delay_periods: int, band_hz: tuple = (1.0, 50.0)) -> int:
    """P: how far ahead the feedforward runs. The valve is a delay of about 2 zeta / w_nv at low frequency
    (Eq. 1), growing towards its resonance; with the ZOH's half period and the loop's delay that is about
    1.5 + 12 periods at 5 kHz. P is the whole number of periods that makes the feedforward alone closest to
    the sampled actuator (ZOH, Eq. 10, the loop's delay) over band_hz: least sum of |1 - G F z^P|^2."""
    f = np.linspace(band_hz[0], min(band_hz[1], 0.4 / dt), 60)
    w = 2 * np.pi * f
    z = np.exp(1j * w * dt)
    Gd = control.sample_system(g_eha(act), dt, method="zoh")
    G = np.asarray(Gd(z)).reshape(-1) * z ** (-delay_periods)
    F = (1j * w + act.lag_corner) / (act.K_v * act.K_Q / act.A_p)
    guess = int(round((2 * act.zeta / act.w_nv) / dt + 0.5 + delay_periods))
    cands = range(max(0, guess - 4), guess + 8)
    return min(cands, key=lambda P: float(np.sum(np.abs(1 - G * F * z ** P) ** 2)))


def reference_params_from_config(cfg, dt: float, act: ActuatorParams | None = None) -> ReferenceParams:
    c = cfg.controller
    act = act or ActuatorParams.from_config(cfg)
    return ReferenceParams(act.K_v * act.K_Q / act.A_p, act.lag_corner, c.track_ff,
                           preview_periods(act, dt, c.track_delay_periods), c.track_rate_m_per_s,
                           c.track_accel_m_per_s2, int(math.floor(c.track_profile_s / dt + 1e-9)) + 1,
                           cfg.safety.stroke_limit_m, c.track_headroom)


class TrackingPID:
    """step(state, (reference_m, position_m), dt) -> (valve_cmd_V, state): reference_m becomes the target
    (ramped at the rate limit); state updated in place."""

    kind = KIND

    def __init__(self, p: PIDParams, dt: float, name: str = "", ref: ReferenceParams = ReferenceParams()):
        self.p = p
        self.ref = ref
        self.dt = float(dt)
        self.name = name
        wd = 2 * math.pi * p.deriv_hz
        # Tustin of Kd s/(1 + s/wd): y_k = ad y_{k-1} + bd (e_k - e_{k-1})
        c = 2.0 / dt
        self.ad = (c - wd) / (c + wd)
        self.bd = p.kd_Vs_per_m * wd * c / (c + wd)
        self.hi = 0.5 * dt * p.ki_V_per_ms
        self.slew = p.slew_V_per_s * dt
        self.preview = int(ref.preview_periods)
        self.ff_V_per_mps = ref.ff / ref.flow_gain_m_per_Vs
        self.state_names = STATE_NAMES + tuple(f"ring{i}" for i in range(self.preview + 1))
        self._coef = self.coefficients()

    def coefficients(self) -> np.ndarray:
        r = self.ref
        head = (self.p.kp_V_per_m, self.hi, self.ad, self.bd, self.p.limit_V, self.slew, self.ff_V_per_mps,
                r.lag_rad_s, r.rate_m_per_s, r.accel_m_per_s2, self.dt, self.preview, r.profile_len,
                max(1, int(round(HOLD_MAX_S / self.dt))))
        return np.concatenate([np.array(head, dtype=np.float64), np.zeros(r.profile_len)])

    def initial_state(self) -> list[float]:
        st = [0.0] * len(self.state_names)
        st[_XP] = math.nan                     # the first sample is new
        return st

    def set_enabled(self, state, on: bool):
        """No isolation to switch: the PID holds its reference either way."""
        return state

    # ---- requests (between periods) -------------------------------------------------------------------
    def take_over(self, state, u_V: float, x_m: float) -> list:
        """Take the valve from a command u_V with the piston at x_m without a jump: hold here (the ring full of
        x_m), the integral carrying what the feedforward of x_m does not."""
        st = list(state)
        st[_RING:] = [x_m] * (self.preview + 1)
        st[_AT] = 0.0
        st[_LEAD] = st[_O] = st[_TGT] = st[_R] = x_m
        st[_WAVE] = st[_WT] = st[_SPAN] = st[_LV] = st[_OV] = 0.0
        ff = self.ff_V_per_mps * self.ref.lag_rad_s * x_m
        st[_FF] = ff
        st[_I] = st[_FB] = u_V - ff
        st[_E] = st[_D] = 0.0
        st[_U] = u_V
        st[_XP], st[_HELD] = math.nan, 0.0   # the next sample is new
        return st

    def apply(self, state, ref: Reference | None, coef=None) -> list:
        """A new reference from the current lead value and rate (no jump): the running waveform is folded into
        the hold position, which then moves to the reference's target within the rate and acceleration limits.
        coef: the kernel's view of coefficients() (a profile goes into its table). Call check() first."""
        st = list(state)
        st[_O], st[_OV] = st[_LEAD], st[_LV]
        st[_WAVE] = st[_WT] = st[_AMP] = st[_F0] = st[_F1] = st[_SPAN] = 0.0
        if ref is None or ref.kind == "hold":
            st[_TGT] = st[_O]
            return st
        if ref.kind == "step":
            st[_TGT] = st[_TGT] + ref.target_m
            return st
        if ref.target_m is not None:
            st[_TGT] = ref.target_m
        if ref.kind == "setpoint":
            return st
        st[_WAVE] = float(_WAVES[ref.kind])
        st[_WT] = -1.0                                 # starts once the hold position is at its target
        st[_AMP], st[_F0], st[_F1], st[_SPAN] = ref.amp_m, ref.f0_hz, ref.f1_hz, ref.span_s
        if ref.kind == "csv":
            prof = np.asarray(ref.profile_m, dtype=float)
            tab = coef if coef is not None else self._coef
            tab[_TABLE:_TABLE + len(prof)] = prof
            st[_SPAN] = float(len(prof))               # the table's samples
        return st

    def hold_range_m(self) -> float:
        """The largest |position| the actuator holds with its feedforward inside the headroom: leakage makes the
        static gain K_v K_Q/A_p / (K_C K_L/A_p^2) (2.68 um/V for Table 1)."""
        r = self.ref
        return r.headroom * self.p.limit_V * r.flow_gain_m_per_Vs / r.lag_rad_s if r.lag_rad_s > 0 else math.inf

    def check(self, ref: Reference, state=None) -> None:
        """RigError (one line) unless the actuator can follow `ref` from `state`: positions inside the stroke
        limit and the static range, speed inside the rate limit, the voltage it needs (the actuator's inverse,
        whatever share the feedforward supplies) inside the headroom of the clamp. Nothing is clamped."""
        r, lim = self.ref, self.p.limit_V
        tgt_now = float(state[_TGT]) if state is not None else 0.0
        check_stroke(ref, r.stroke_limit_m, tgt_now)
        base = positions_m(ref, tgt_now)[0]
        name = f"reference {ref}"
        if ref.kind == "csv":
            prof = np.asarray(ref.profile_m, dtype=float)
            if len(prof) > r.profile_len:
                raise RigError(f"{name}: {len(prof)} samples, the table holds {r.profile_len} "
                               f"(controller.track_profile_s)")
            vel = np.diff(prof) / self.dt if len(prof) > 1 else np.zeros(1)
            peak_rate = float(np.max(np.abs(vel)))
            volts = np.abs(vel + r.lag_rad_s * prof[:-1]) / r.flow_gain_m_per_Vs if len(prof) > 1 else [0.0]
            peak_V = float(np.max(volts))
            dv = float(np.max(np.abs(np.diff(volts)))) / self.dt if len(prof) > 2 else 0.0
        else:
            a = ref.amp_m
            w = 2 * math.pi * max(ref.f0_hz, ref.f1_hz)
            peak_rate = a * w
            dyn = a * math.hypot(w, r.lag_rad_s) / r.flow_gain_m_per_Vs
            peak_V = abs(base) * r.lag_rad_s / r.flow_gain_m_per_Vs + dyn
            dv = dyn * w
        rng = self.hold_range_m()
        if ref.kind in ("hold", "setpoint", "step") and abs(base) > rng:
            raise RigError(f"{name}: {base * 1e6:.1f} um is outside what the actuator can hold: +-{rng * 1e6:.1f} um "
                           f"(leakage: DC gain {r.flow_gain_m_per_Vs / r.lag_rad_s * 1e6:.2f} um/V, "
                           f"{100 * r.headroom:.0f} % of the {lim:g} V clamp, controller.track_headroom)")
        if peak_rate > r.rate_m_per_s * (1 + 1e-9):
            raise RigError(f"{name}: moves at up to {peak_rate * 1e3:.3f} mm/s, above the reference rate limit "
                           f"{r.rate_m_per_s * 1e3:.3f} mm/s (controller.track_rate_m_per_s)")
        if peak_V > r.headroom * lim:
            raise RigError(f"{name}: needs {peak_V:.1f} V at the valve, above {r.headroom * lim:.1f} V "
                           f"({100 * r.headroom:.0f} % of the {lim:g} V clamp, controller.track_headroom): "
                           f"the actuator cannot follow it")
        if dv > self.p.slew_V_per_s:
            raise RigError(f"{name}: needs the valve command to change at {dv:.0f} V/s, above the slew limit "
                           f"{self.p.slew_V_per_s:g} V/s (safety.slew_V_per_s)")

    # ---- design tools and tests -----------------------------------------------------------------------
    def step(self, state, meas, dt: float):
        check_step(self.dt, dt)
        state[_TGT] = float(meas[0])
        return step_law(track_step, state, self._coef, float(meas[1])), state

    def frf(self, w: np.ndarray) -> np.ndarray:
        """C(z) at z = exp(j w dt), linear range."""
        zi = np.exp(-1j * np.asarray(w, dtype=float) * self.dt)
        integ = self.hi * (1 + zi) / (1 - zi)
        deriv = self.bd * (1 - zi) / (1 - self.ad * zi)
        return self.p.kp_V_per_m + integ + deriv

    def ff_frf(self, w: np.ndarray) -> np.ndarray:
        """The feedforward's response to the (loop-time) reference: ff (j w + lag)/flow gain, P periods ahead
        (the law's analytic waveforms give exactly this)."""
        w = np.asarray(w, dtype=float)
        return self.ff_V_per_mps * (1j * w + self.ref.lag_rad_s) * np.exp(1j * w * self.preview * self.dt)


@numba.njit(cache=True, inline="always")
def _envelope(t, ramp, span):
    """A raised-cosine fade-in over `ramp` seconds (and out before `span`, if it ends): (value, rate)."""
    e, de = 1.0, 0.0
    if ramp > 0.0 and t < ramp:
        e = 0.5 - 0.5 * math.cos(math.pi * t / ramp)
        de = 0.5 * math.pi / ramp * math.sin(math.pi * t / ramp)
    elif ramp > 0.0 and span > 0.0 and span - t < ramp:
        e = 0.5 - 0.5 * math.cos(math.pi * (span - t) / ramp)
        de = -0.5 * math.pi / ramp * math.sin(math.pi * (span - t) / ramp)
    return e, de


@numba.njit(cache=True, inline="always")
def _wave(st, cf, tw):
    """The waveform at lead time tw (s): (value [m], rate [m/s], finished). A sine fades in over its first
    cycle (and out over its last), a chirp over its first cycle (at most a tenth of it): they start and
    end at rest, so the feedforward does not jump."""
    kind = int(st[_WAVE])
    amp = st[_AMP]
    if kind == WAVE_SINE:
        span = st[_SPAN]
        if span > 0.0 and tw >= span:
            return 0.0, 0.0, True
        w = 2.0 * math.pi * st[_F0]
        e, de = _envelope(tw, 1.0 / st[_F0], span)
        s, c = math.sin(w * tw), math.cos(w * tw)
        return amp * e * s, amp * (de * s + e * w * c), False
    if kind == WAVE_CHIRP:
        f0, f1, span = st[_F0], st[_F1], st[_SPAN]
        t = min(tw, span)
        ph = 2.0 * math.pi * (f0 * t + 0.5 * (f1 - f0) / span * t * t)
        e, de = _envelope(t, min(1.0 / f0, 0.1 * span), 0.0)
        if tw >= span:
            return amp * math.sin(ph), 0.0, True
        dph = 2.0 * math.pi * (f0 + (f1 - f0) * t / span)
        return amp * e * math.sin(ph), amp * (de * math.sin(ph) + e * dph * math.cos(ph)), False
    if kind == WAVE_TABLE:
        n = int(st[_SPAN])
        dt = cf[_DT]
        x = tw / dt
        k = int(x + 1e-6)
        t0 = cf[_TABLE]
        if k >= n - 1:
            return cf[_TABLE + n - 1] - t0, 0.0, True
        a, b = cf[_TABLE + k], cf[_TABLE + k + 1]
        return a + (x - k) * (b - a) - t0, (b - a) / dt, False
    return 0.0, 0.0, True


@numba.njit(cache=True, inline="always")
def _approach(o, v, tgt, vmax, amax, dt):
    """The hold position o (rate v) one period towards tgt: speed within vmax, its change within amax, and
    slow enough to stop at the target (braking at amax). (o, v) after the period."""
    d = tgt - o
    if amax * dt > 1e30:                                   # no limits: there at once
        return tgt, 0.0
    s = math.sqrt(2.0 * amax * abs(d) + (amax * dt) ** 2) - amax * dt
    vd = math.copysign(min(vmax, s, abs(d) / dt), d)
    dv = min(max(vd - v, -amax * dt), amax * dt)
    v += dv
    o += v * dt
    if abs(tgt - o) <= 0.5 * amax * dt * dt and abs(v) <= amax * dt:
        return tgt, 0.0                                    # arrived (within half a period's braking)
    return o, v


@numba.njit(cache=True)
def track_step(st, cf, x):
    """One period: position x [m] -> valve command [V]. The reference moves one period on its lead timeline,
    is fed forward, and the PID closes the loop on it P periods later; st (state_names) updated in place."""
    dt = cf[_DT]
    tgt = st[_TGT]
    o, do = st[_O], st[_OV]
    if o != tgt or do != 0.0:
        o, do = _approach(o, do, tgt, cf[_RATE], cf[_ACC], dt)
    w = 0.0
    wd = 0.0
    if st[_WAVE] > 0.5:
        tw = st[_WT]
        if tw < 0.0 and o == tgt and do == 0.0:
            tw = 0.0                                   # the hold position has arrived: the waveform starts
        if tw >= 0.0:
            w, wd, done = _wave(st, cf, tw)
            if done:                                   # fold it into the hold position, at its rate
                o += w
                do += wd
                st[_TGT] = o
                w = 0.0
                wd = 0.0
                st[_WAVE] = 0.0
                tw = 0.0
            else:
                tw += dt
        st[_WT] = tw
    st[_O] = o
    st[_OV] = do
    lead = o + w
    st[_LEAD] = lead
    st[_LV] = do + wd
    ff = cf[_FFK] * (do + wd + cf[_LAG] * lead)
    nring = int(cf[_PRE]) + 1
    at = int(st[_AT])
    st[_RING + at] = lead
    at += 1
    if at >= nring:
        at = 0
    st[_AT] = at
    r = st[_RING + at]                                 # the lead value of P periods ago
    # the PID on r, with the feedforward
    e = r - x
    if x == st[_XP] and st[_HELD] < cf[_HMAX]:     # no new position sample: the feedback holds
        st[_HELD] += 1.0
        u, sat = clamp(st[_FB] + ff, cf[_LIM], 0.0)
        u, sat = slew(u, st[_U], cf[_SLEW], sat)
        st[_U] = u
        st[_R] = r
        st[_FF] = ff
        return u
    d_i = cf[_HI] * (e + st[_E])
    integ = st[_I] + d_i
    d = cf[_AD] * st[_D] + cf[_BD] * (e - st[_E])
    fb = cf[_KP] * e + integ + d
    u, sat = clamp(fb + ff, cf[_LIM], 0.0)
    u, sat = slew(u, st[_U], cf[_SLEW], sat)
    if sat * d_i > 0.0:
        integ -= d_i                     # anti-windup: no increment pushing further into the limit
        fb -= d_i
    st[_I] = integ
    st[_E] = e
    st[_D] = d
    st[_U] = u
    st[_R] = r
    st[_FF] = ff
    st[_XP] = x
    st[_FB] = fb
    st[_HELD] = 0.0
    return u


def tracking_response(act, ctrl: TrackingPID, f_hz: np.ndarray, delay: int = 1, *,
                      feedforward: bool = False) -> np.ndarray:
    """Closed-loop r -> x_p of the actuator alone: ZOH-discretised G_EHA, the PID, `delay` periods; with
    feedforward, the controller's reference feedforward too ((L + G F) / (1 + L))."""
    Gd = control.sample_system(g_eha(act), ctrl.dt, method="zoh")
    w = 2 * np.pi * np.asarray(f_hz, dtype=float)
    z = np.exp(1j * w * ctrl.dt)
    G = np.asarray(Gd(z)).reshape(-1) * z ** (-delay)
    L = ctrl.frf(w) * G
    if feedforward:
        return (L + G * ctrl.ff_frf(w)) / (1 + L)
    return L / (1 + L)


def bandwidth_hz(f_hz: np.ndarray, T: np.ndarray) -> float:
    """First frequency where |T| falls 3 dB below its low-frequency value."""
    db = 20 * np.log10(np.abs(T))
    k = np.nonzero(db < db[0] - 3.0)[0]
    return float(f_hz[k[0]]) if len(k) else math.nan


def tune_tracking(act, dt: float, target_hz: float = 100.0, limit_V: float = 10.0, slew_V_per_s: float = 1e4,
                  delay: int = 1, *, noise_m: float = 2e-8, min_gm_db: float = 6.0, min_pm_deg: float = 45.0,
                  max_peak_db: float = 1.0) -> PIDParams:
    """Ki = Kp * (actuator lag corner); over a grid of derivative times Td = Kd/Kp and filter corners, Kp by
    bisection for the target bandwidth of |T| (Fig. 4); of those with the margins and a flat |T| (within
    max_peak_db either way below 0.7 of the bandwidth), keep the one that puts the least transducer noise
    (rms noise_m, white) into the valve command. ValueError if none."""
    lag = act.lag_corner
    fn = 0.5 / dt
    f = np.geomspace(0.5, 0.999 * fn, 1500)
    fl = np.linspace(1.0, 0.999 * fn, 1500)
    best = None
    for fd in (60.0, 100.0, 150.0, 250.0):
        if fd >= 0.45 * fn:
            continue
        for td in np.concatenate([[0.0], np.geomspace(2e-4, 2e-2, 16)]):
            lo, hi = 1e3, 1e9
            for _ in range(30):
                kp = math.sqrt(lo * hi)
                c = TrackingPID(PIDParams(kp, kp * lag, kp * td, fd, limit_V, slew_V_per_s), dt)
                bw = bandwidth_hz(f, tracking_response(act, c, f, delay))
                if math.isnan(bw) or bw > target_hz:
                    hi = kp
                else:
                    lo = kp
            c = TrackingPID(PIDParams(lo, lo * lag, lo * td, fd, limit_V, slew_V_per_s), dt)
            T = tracking_response(act, c, f, delay)
            gm, pm = loop_margins(act, c, f, delay)
            db = 20 * np.log10(np.abs(T))
            if abs(bandwidth_hz(f, T) - target_hz) > 0.03 * target_hz or gm < min_gm_db or pm < min_pm_deg \
                    or np.max(db) > max_peak_db or np.min(db[f < 0.7 * target_hz]) < -max_peak_db:
                continue
            S = 1 - tracking_response(act, c, fl, delay)
            noise = noise_m * math.sqrt(np.mean(np.abs(c.frf(2 * np.pi * fl) * S) ** 2))
            if best is None or noise < best[0]:
                best = (noise, c.p)
    if best is None:
        raise ValueError(f"no PID reaches {target_hz:g} Hz with GM >= {min_gm_db:g} dB and PM >= {min_pm_deg:g} deg "
                         f"at {1 / dt:g} Hz with {delay} period(s) of delay")
    return best[1]


def loop_margins(act, ctrl: TrackingPID, f_hz: np.ndarray, delay: int = 1) -> tuple[float, float]:
    """(gain margin dB, phase margin deg) of the loop C G z^-delay (first crossings on the grid f_hz)."""
    Gd = control.sample_system(g_eha(act), ctrl.dt, method="zoh")
    w = 2 * np.pi * np.asarray(f_hz, dtype=float)
    z = np.exp(1j * w * ctrl.dt)
    L = ctrl.frf(w) * np.asarray(Gd(z)).reshape(-1) * z ** (-delay)
    mag, ph = np.abs(L), np.unwrap(np.angle(L))
    i = np.nonzero(mag < 1)[0]
    pm = 180.0 + math.degrees(ph[i[0]]) if len(i) else math.inf
    j = np.nonzero(ph < -math.pi)[0]
    gm = -20 * math.log10(mag[j[0]]) if len(j) else math.inf
    return gm, pm


def pid_from_config(cfg) -> PIDParams:
    c = cfg.controller
    return PIDParams(c.track_kp_V_per_m, c.track_ki_V_per_ms, c.track_kd_Vs_per_m, c.track_deriv_hz,
                     cfg.safety.valve_limit_V, cfg.safety.slew_V_per_s)


def tracking_from_config(cfg, dt: float, name: str = "", act: ActuatorParams | None = None) -> TrackingPID:
    """The tracking controller of the config: [controller] track_* gains and reference settings, [safety]
    limits, the actuator's figures (Table 1 values of the config, the stand's load on the piston)."""
    return TrackingPID(pid_from_config(cfg), dt, name, reference_params_from_config(cfg, dt, act))

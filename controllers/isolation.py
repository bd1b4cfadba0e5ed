"""Decentralised isolation controller of one mount (paper Figs. 5, 10): PI + compensator on the mount's absolute
motion, with stroke centring. One object per mount; explicit state; no clock, I/O or globals.

Feedback signal: a complementary blend (sensor fusion) of the two sensors at the mount, crossing at blend_hz:

  y = H(s) a / s^2 + F(s) stroke,   H = s^3 (s + c3) / D(s),  F = 1 - H = (c2 s^2 + c1 s + w^4) / D(s),
  D = s^4 + c3 s^3 + c2 s^2 + c1 s + w^4 the 4th-order Butterworth polynomial at w = 2 pi blend_hz
    - above the blend (~0.05 Hz) y is the mount's absolute motion from the low-frequency accelerometer
      (band-limited double integration: H/s^2 = s (s + c3)/D has zero gain at DC, so an accelerometer
      offset only makes a transient, and the noise below the blend does not run away);
    - below it y is the stroke (displacement transducer): the loop then centres the piston. That is the slow
      stroke-centring loop, and because u -> stroke equals u -> x_p, the loop gain is K(s) P(s) at every
      frequency: the blend adds no phase wrap (a separate high-pass plus a separate centring integrator makes
      the low-frequency loop conditionally stable and, with the PI, unstable near 0.02-0.04 Hz).
  u_iso = -(Kp v + Ki/s v),  v = Comp(s) y,  Comp = Lead1 Lead2 Notch Roll-off (each optional)
  isolation off: u = -k_c/s stroke (slow centring alone, ~centring_hz); the isolation filters keep running.
  u -> slew limit -> clamp to the valve range; PI and centring integrators: conditional-integration anti-windup.

Why this compensator: the plant u -> x_p (valve, Eq. 1; flow integrator with the K_C K_L lag at ~7 Hz, Eq. 9;
the machine's mass on the actuators' stiffness at 230-290 Hz, damping ~0.2) has lost ~210 deg of phase at
100 Hz and ~300 deg at 200 Hz, ZOH and one period of computation delay included. Lead1 cancels the 7 Hz lag
(so the loop gain stays up to the valve's 83 Hz), lead2 buys the phase at crossover, the notch takes the
machine-on-actuator resonances down so they are gain-stabilised, the second notch (a peak when its zero is
damped more than its pole) lifts the loop gain at the top of the 1-100 Hz band just below crossover, and the
roll-off keeps accelerometer noise and high-frequency modes out of the valve. The PI gives the low-frequency
gain (>= 25 dB at 1 Hz).

Why Tustin, prewarped at prewarp_hz (200 Hz, the phase-crossover / resonance region where the gain margin is
decided) for the compensator, plain for the slow blend: it maps a stable continuous factor to a stable discrete
one without aliasing, and is exact at the prewarp frequency. The design is checked (and
was tuned, controllers/tune.py) on the *discrete* loop with the ZOH and one period of computation delay
(controllers/analysis.py), which evaluates exactly the coefficients the compiled law runs.

One implementation: `isolation_step` (numba) is the law; the runtime's period (rig/runtime/kernel.py) calls it for
every isolation mount, and IsolationController.step calls it for design tools and tests. The controller
object is the builder: coefficients (`coefficients()`), the named state layout (`state_names`), bumpless
switching (`set_enabled`) and the transfer functions for analysis.

Bumpless isolation on/off (`set_enabled`): the filters always run (so they are warm); switching seeds a
fading offset b so that the command does not jump, then b decays with time constant fade_s. Centring stays on
(the blend when isolating, the slow integrator when not). The loop is closed at full gain at once.

Saturation recovery (sat_reset_s, sat_resume_s): isolating with the output held at the clamp for sat_reset_s
(longer than the clamp bursts of shocks the loop rides out, well below safety.saturation_s) suspends
isolation bumplessly (centring alone, filters running) and resumes it by itself once the estimate has
settled; see isolation_step. The usual cause of the latch: a scheduling gap leaves a velocity error in the double
integration, which a 0.1 Hz blend forgets only over many seconds (tests/rig/runtime/test_saturation.py). Where
the gap is known, conversions the accelerometer module lost, the runtime suspends at once (isolation_suspend)
rather than after the clamp, and holds off the resume for five time constants of the blend (loss_n).

The defaults are rig/config.py's [controller] section; `rig design` prints the margins and isolation they
give (README).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numba
import numpy as np

from controllers.discrete import sections_step as _sections
from controllers.discrete import sos_frf, sos_ss, sos_tf
from controllers.discrete import tustin_section as _tustin
from controllers.limits import clamp, slew
from controllers.state import step_law
from controllers.timebase import check_step
from rig.config import ControllerConfig, SafetyConfig, layout_mounts
from sim_backend.linear import ActuatorParams

KIND = 1                      # rig/runtime/kernel.py dispatches on it

# Named state: two states per filter section (transposed direct form II, in section order), then these scalars
SCALAR_STATES = ("v", "pi_integral", "centring_integral", "stroke_prev_m", "fade_offset_V", "isolation_on",
                 "cmd_prev_V", "sat_count", "suspended", "v_mean")
_V, _I, _C, _S, _B, _ON, _U, _K, _SUS, _A = range(10)
_N = len(SCALAR_STATES)

# Named coefficients: these scalars, then the sections (b0, b1, b2, a1, a2) in state order
COEFFICIENTS = ("n_sections", "n_h_acc", "n_f_str", "half_dt", "kp", "ki", "kc", "fade", "limit_V", "slew_V",
                "sat_n", "resume_n", "resume_m", "resume_a", "loss_n")
(_CF_NSEC, _CF_NH, _CF_NF, _CF_H, _CF_KP, _CF_KI, _CF_KC, _CF_FADE, _CF_LIM, _CF_SLEW, _CF_SATN, _CF_RESN,
 _CF_RESM, _CF_RESA, _CF_LOSSN) = range(15)
_CF_SECTIONS = len(COEFFICIENTS)


_CC, _SC = ControllerConfig(), SafetyConfig()      # the one source of defaults: rig/config.py


@dataclass(frozen=True)
class IsolationParams:
    """Continuous design parameters of one mount's loop (SI units; frequencies in Hz). Defaults: rig/config.py
    [controller] and [safety]; dc_gain_m_per_V is the actuator model's (sim_backend/linear.py)."""
    blend_hz: float = _CC.blend_hz                # complementary blend accelerometer / stroke (centring bandwidth)
    kp_V_per_m: float = _CC.kp_V_per_m            # PI proportional gain on the compensated position
    pi_corner_hz: float = _CC.pi_corner_hz        # PI integral corner w_i / 2 pi
    lead1_zero_hz: float = _CC.lead1_zero_hz
    lead1_pole_hz: float = _CC.lead1_pole_hz
    lead2_zero_hz: float = _CC.lead2_zero_hz
    lead2_pole_hz: float = _CC.lead2_pole_hz
    rolloff_hz: float = _CC.rolloff_hz            # second-order low-pass (0 = none)
    rolloff_zeta: float = _CC.rolloff_zeta
    notch_hz: float = _CC.notch_hz                # optional notch (0 = none)
    notch_zeta_zero: float = _CC.notch_zeta_zero
    notch_zeta_pole: float = _CC.notch_zeta_pole
    notch2_hz: float = _CC.notch2_hz              # optional second notch, or peak (zeta_zero > zeta_pole); 0 = none
    notch2_zeta_zero: float = _CC.notch2_zeta_zero
    notch2_zeta_pole: float = _CC.notch2_zeta_pole
    centring_hz: float = _CC.centring_hz          # crossover of the slow centring loop while isolation is off
    dc_gain_m_per_V: float = ActuatorParams().dc_gain_m_per_V   # actuator static gain (sets the centring gain)
    prewarp_hz: float = _CC.prewarp_hz            # Tustin prewarp frequency of the compensator
    fade_s: float = _CC.fade_s                    # bumpless switching offset decay time
    sat_reset_s: float = _CC.sat_reset_s          # isolating at the output clamp this long: suspend (0 = never)
    sat_resume_s: float = _CC.sat_resume_s        # suspended: resume once the estimate's mean stayed small
    limit_V: float = _SC.valve_limit_V            # output clamp
    slew_V_per_s: float = _SC.slew_V_per_s        # output slew limit
    gain_trim: float = 1.0                        # per-mount multiplier on kp

    def with_(self, **kw) -> "IsolationParams":
        if "accel_hp_hz" in kw:          # the first version's name of the low-frequency corner (now the blend)
            kw["blend_hz"] = kw.pop("accel_hp_hz")
        return replace(self, **kw)


def params_from_config(cfg, mount: int = 0) -> IsolationParams:
    """IsolationParams of one mount from cfg.controller (rig/config.py), cfg.safety and the actuator's DC gain
    (the physics model's figure for the configured Table 1 values)."""
    c = cfg.controller
    names = {f.name for f in fields(IsolationParams)}
    design = {f.name: getattr(c, f.name) for f in fields(c) if f.name in names and f.name != "gain_trim"}
    trim = c.gain_trim[mount] if len(c.gain_trim) > mount else 1.0
    return IsolationParams(**design, gain_trim=trim, dc_gain_m_per_V=ActuatorParams.from_config(cfg).dc_gain_m_per_V,
                           limit_V=cfg.safety.valve_limit_V, slew_V_per_s=cfg.safety.slew_V_per_s)


class IsolationController:
    """One mount: step(state, (accel_mps2, stroke_m), dt) -> (valve_cmd_V, state).

    The state list is updated in place and returned (the caller hands the returned list back next period)."""

    def __init__(self, params: IsolationParams, dt: float, *, compensator: bool = True, name: str = ""):
        self.p = params
        self.dt = float(dt)
        self.name = name
        self.compensator = compensator
        p, pw = params, params.prewarp_hz
        self.continuous = {"h_acc": [], "f_str": [], "comp": []}    # (num, den) of each factor, for checks

        def tustin_section(num, den, dt_, pw_, _group=[None]):
            self.continuous[_group[0]].append((list(num), list(den)))
            return _tustin(num, den, dt_, pw_)
        grp = tustin_section.__defaults__[0]
        grp[0] = "h_acc"
        w = 2 * math.pi * p.blend_hz
        # D(s) = 4th-order Butterworth at w = s^4 + c3 s^3 + c2 s^2 + c1 s + w^4 (distinct poles: a 4-fold
        # pole near z = 1 would make the closed-loop eigenvalues numerically meaningless)
        q1, q2 = [1.0, 1.8478 * w, w * w], [1.0, 0.7654 * w, w * w]
        c3, c2, c1 = 2.6131 * w, 3.4142 * w * w, 2.6131 * w ** 3
        # (no prewarp for the blend: its frequencies are far below Nyquist, Tustin is exact enough there and a
        # prewarp at the crossover would scale the double integration by ~1 %)
        self.h_acc = [tustin_section([1.0, 0.0], q1, dt, None),    # H/s^2 = s (s + c3) / D
                      tustin_section([1.0, c3], q2, dt, None)]
        grp[0] = "f_str"
        self.f_str = [tustin_section([c2, c1, w ** 4], q1, dt, None),   # F = 1 - H = (c2 s^2 + c1 s + w^4) / D
                      tustin_section([1.0], q2, dt, None)]
        grp[0] = "comp"
        comp = []
        if compensator:
            for fz, fp in ((p.lead1_zero_hz, p.lead1_pole_hz), (p.lead2_zero_hz, p.lead2_pole_hz)):
                if fz > 0 and fp > 0:
                    wz, wp = 2 * math.pi * fz, 2 * math.pi * fp
                    comp.append(tustin_section([1 / wz, 1.0], [1 / wp, 1.0], dt, pw))   # (1+s/wz)/(1+s/wp)
            for fn, zz, zp in ((p.notch_hz, p.notch_zeta_zero, p.notch_zeta_pole),
                               (p.notch2_hz, p.notch2_zeta_zero, p.notch2_zeta_pole)):
                if fn > 0:                             # (s^2 + 2 zz wn s + wn^2) / (s^2 + 2 zp wn s + wn^2)
                    wn = 2 * math.pi * fn
                    comp.append(tustin_section([1.0, 2 * zz * wn, wn * wn], [1.0, 2 * zp * wn, wn * wn], dt, fn))
            if p.rolloff_hz > 0:
                wr = 2 * math.pi * p.rolloff_hz
                comp.append(tustin_section([wr * wr], [1.0, 2 * p.rolloff_zeta * wr, wr * wr], dt, pw))
        self.comp = comp
        self.kp = p.kp_V_per_m * p.gain_trim
        self.ki = self.kp * 2 * math.pi * p.pi_corner_hz            # Kp w_i
        self.kc = 2 * math.pi * p.centring_hz / p.dc_gain_m_per_V  # slow centring crossover ~ centring_hz
        self.fade = math.exp(-dt / p.fade_s)
        self.limit = p.limit_V
        self.slew = p.slew_V_per_s * dt
        self._o = 2 * (len(self.h_acc) + len(self.f_str) + len(self.comp))   # the scalar states start here
        self.sections = tuple(self.h_acc + self.f_str + self.comp)
        # saturation recovery (see step): clamp periods before suspending, in-range periods before resuming
        self.sat_n = max(1, int(round(p.sat_reset_s / dt))) if p.sat_reset_s > 0 else 0
        self.resume_n = max(1, int(round(p.sat_resume_s / dt)))
        # resume when the mean of v is within half the stroke the valve can hold (limit x DC gain):
        # what is left of the estimate's error then fits the actuator's range
        self.resume_m = 0.5 * p.limit_V * p.dc_gain_m_per_V
        self.resume_a = dt / p.sat_resume_s          # mean over ~sat_resume_s (first-order)
        # suspended after lost conversions: no resume before the blend has forgotten their error (five time
        # constants of its corner): until then the error is still growing, and its mean says nothing yet
        self.loss_n = int(round(5.0 / (2 * math.pi * p.blend_hz) / dt))
        self.state_names = tuple(f"{g}{k}_z{j}" for g, secs in (("h_acc", self.h_acc), ("f_str", self.f_str),
                                                                ("comp", self.comp))
                                 for k in range(len(secs)) for j in (1, 2)) + SCALAR_STATES
        self._coef = self.coefficients()

    def coefficients(self) -> np.ndarray:
        """The law's coefficients (COEFFICIENTS, then the sections): what rig/runtime/kernel.py copies into its
        block."""
        head = (len(self.sections), len(self.h_acc), len(self.f_str), 0.5 * self.dt, self.kp, self.ki, self.kc,
                self.fade, self.limit, self.slew, self.sat_n, self.resume_n, self.resume_m, self.resume_a,
                self.loss_n)
        return np.concatenate([np.array(head, dtype=np.float64), np.ravel(self.sections)])

    # ---- the runtime interface ---------------------------------------------------------------------
    kind = KIND

    def initial_state(self) -> list[float]:
        s = [0.0] * (self._o + _N)
        s[self._o + _ON] = 1.0
        return s

    def set_enabled(self, state: list, on: bool) -> list:
        """Bumpless isolation on/off: the filters keep running; a fading offset takes over the difference so
        the command does not jump. Centring stays active."""
        o = self._o
        was = state[o + _ON] > 0.5
        if state[o + _SUS] > 0.5:
            # suspended by the saturation recovery: isolation is already out of the output, so switching
            # off only clears the request; switching on waits for the recovery's own resume
            state[o + _ON] = 1.0 if on else 0.0
            if not on:
                state[o + _SUS] = 0.0
                state[o + _K] = 0.0
            return state
        state[o + _K] = 0.0
        if on and not was:
            # from now on u = u_iso + b - cent: start the PI from zero, let b absorb the step
            state[o + _I] = 0.0
            state[o + _B] -= -self.kp * state[o + _V]
            state[o + _ON] = 1.0
        elif not on and was:
            state[o + _B] += -(self.kp * state[o + _V] + state[o + _I])   # hold the last isolation output
            state[o + _I] = 0.0
            state[o + _ON] = 0.0
        return state

    def take_over(self, state, u_V: float) -> list:
        """Isolation on, taking the valve from a command u_V (another controller's) without a jump: the
        centring integral takes over u_V (held while isolating), the fading offset the isolation term."""
        st = list(state)
        o = self._o
        st[o + _ON], st[o + _SUS], st[o + _K], st[o + _I] = 1.0, 0.0, 0.0, 0.0
        st[o + _C] = -u_V
        st[o + _B] = self.kp * st[o + _V]
        st[o + _U] = u_V
        return st

    def enabled(self, state: list) -> bool:
        return state[self._o + _ON] > 0.5

    def step(self, state, meas, dt: float):
        """One period through the compiled law (design tools and tests; the runtime's period calls the law
        itself). state: a float64 array or a list, updated in place and returned."""
        check_step(self.dt, dt)
        return step_law(isolation_step, state, self._coef, float(meas[0]), float(meas[1])), state

    def suspended(self, state: list) -> bool:
        """True while the saturation recovery holds isolation off (the request stays on)."""
        return state[self._o + _SUS] > 0.5

    # ---- the same controller as transfer functions (analysis) --------------------------------------
    def _pi_section(self):
        h = 0.5 * self.dt
        return (self.kp + self.ki * h, self.ki * h - self.kp, 0.0, -1.0, 0.0)   # Kp + Ki Tustin(1/s)

    def frf(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K_a, K_s): discrete responses at z = exp(j w dt) of u to accel [V/(m/s^2)] and to stroke [V/m],
        isolation on, in the linear range (no clamp or slew active)."""
        dt = self.dt
        front = -sos_frf(self.comp + [self._pi_section()], w, dt)
        return front * sos_frf(self.h_acc, w, dt), front * sos_frf(self.f_str, w, dt)

    def ss(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Discrete state space (A, B, C, D), inputs (accel, stroke), output u (isolation on, linear range)."""
        Aa, Ba, Ca, Da = sos_ss(self.h_acc)
        As, Bs, Cs, Ds = sos_ss(self.f_str)
        Ac, Bc, Cc, Dc = sos_ss(self.comp + [self._pi_section()])
        na, ns_, nc = Aa.shape[0], As.shape[0], Ac.shape[0]
        n = na + ns_ + nc
        A = np.zeros((n, n))
        B = np.zeros((n, 2))
        A[:na, :na], B[:na, 0:1] = Aa, Ba
        A[na:na + ns_, na:na + ns_], B[na:na + ns_, 1:2] = As, Bs
        # y = Ca xa + Da a + Cs xs + Ds s feeds the compensator + PI
        k = na + ns_
        A[k:, k:] = Ac
        A[k:, :na] = Bc @ Ca
        A[k:, na:k] = Bc @ Cs
        B[k:, 0:1] = Bc * Da[0, 0]
        B[k:, 1:2] = Bc * Ds[0, 0]
        C = -np.hstack([Dc[0, 0] * Ca, Dc[0, 0] * Cs, Cc])
        D = -Dc[0, 0] * np.array([[Da[0, 0], Ds[0, 0]]])
        return A, B, C, D

    def css(self):
        """Continuous-time twin (A, B, C, D) of ss(): the factors before discretisation, isolation on. Used to
        check the slow closed-loop poles (near z = 1 discrete eigenvalues lose their digits)."""
        import control
        wi = 2 * math.pi * self.p.pi_corner_hz

        def chain(factors):
            g = control.ss([], [], [], [[1.0]])
            for num, den in factors:
                g = control.series(g, control.ss(control.tf(num, den)))
            return g
        front = control.series(chain(self.continuous["comp"]), control.ss(control.tf([self.kp, self.kp * wi],
                                                                                        [1.0, 0.0])))
        ga, gs = chain(self.continuous["h_acc"]), chain(self.continuous["f_str"])
        na, ns_, nf = ga.nstates, gs.nstates, front.nstates
        n = na + ns_ + nf
        A = np.zeros((n, n))
        B = np.zeros((n, 2))
        A[:na, :na], B[:na, 0] = ga.A, ga.B[:, 0]
        A[na:na + ns_, na:na + ns_], B[na:na + ns_, 1] = gs.A, gs.B[:, 0]
        k = na + ns_                                 # one PI + compensator fed by y = H/s^2 a + F stroke
        A[k:, k:] = front.A
        A[k:, :na] = np.outer(front.B[:, 0], ga.C[0])
        A[k:, na:k] = np.outer(front.B[:, 0], gs.C[0])
        B[k:, 0] = front.B[:, 0] * ga.D[0, 0]
        B[k:, 1] = front.B[:, 0] * gs.D[0, 0]
        fd = front.D[0, 0]
        C = -np.hstack([fd * ga.C[0], fd * gs.C[0], front.C[0]])[None, :]
        D = -fd * np.array([[ga.D[0, 0], gs.D[0, 0]]])
        return A, B, C, D

    def tf(self):
        """(K_a, K_s) as python-control discrete transfer functions with dt (for plots; poles near z = 1 make
        the polynomial form ill-conditioned: use ss() for eigenvalues)."""
        front = -sos_tf(self.comp + [self._pi_section()], self.dt)
        return front * sos_tf(self.h_acc, self.dt), front * sos_tf(self.f_str, self.dt)


# ---- the law (compiled; the one implementation) ---------------------------------------------------------
@numba.njit(cache=True)
def isolation_step(st, cf, a, s):
    """One mount, one period: acceleration a [m/s^2] and stroke s [m] -> valve command [V]. st: the named
    state (state_names), updated in place; cf: coefficients() (COEFFICIENTS, then the sections)."""
    nsec = int(cf[_CF_NSEC])
    na = int(cf[_CF_NH])
    ns = int(cf[_CF_NF])
    h = cf[_CF_H]
    o = 2 * nsec
    # y = H/s^2 a + F stroke, then v = Comp y
    y, i, c = _sections(st, cf, 0, _CF_SECTIONS, na, a)
    x, i, c = _sections(st, cf, i, c, ns, s)
    x, i, c = _sections(st, cf, i, c, nsec - na - ns, x + y)
    v = x
    kp = cf[_CF_KP]
    on = st[o + _ON] > 0.5 and st[o + _SUS] < 0.5
    if on:
        d_i = cf[_CF_KI] * h * (v + st[o + _V])         # Tustin PI integral
        d_c = 0.0                                      # centring: the blend does it
    else:
        d_i = 0.0
        d_c = cf[_CF_KC] * h * (s + st[o + _S])         # slow centring integrator
    integ = st[o + _I] + d_i
    cent = st[o + _C] + d_c
    b = st[o + _B] * cf[_CF_FADE]
    if on:
        u = -(kp * v + integ) + b - cent
    else:
        u = 0.0 + b - cent
    u, sat = slew(u, st[o + _U], cf[_CF_SLEW], 0.0)
    lim = cf[_CF_LIM]
    u, sat = clamp(u, lim, sat)
    if sat != 0.0:
        # anti-windup (conditional integration): drop increments that push further into the limit
        if d_i * sat < 0.0:
            integ -= d_i
        if d_c * sat < 0.0:
            cent -= d_c
    st[o + _V] = v
    st[o + _I] = integ
    st[o + _C] = cent
    st[o + _S] = s
    st[o + _B] = b
    st[o + _U] = u
    if cf[_CF_SATN] > 0.0:
        _saturation_recovery(st, cf, o, on, u, lim, v, b, cent, kp)
    return u


@numba.njit(cache=True, inline="always")
def _suspend(st, o, u, cent, v):
    """Isolation suspended the bumpless way: the output u held (b takes over, then fades), centring alone."""
    st[o + _B] = u + cent
    st[o + _I] = 0.0
    st[o + _SUS] = 1.0
    st[o + _A] = v


@numba.njit(cache=True)
def isolation_suspend(st, cf):
    """Conversions were lost (estimated across a gap): the double integration's velocity is off by what they
    would have added, and the piston would run to the clamp before the saturation recovery caught it. So
    isolation is suspended now, as that recovery would (and resumed by it, once the estimate has settled).
    Not before loss_n periods though (the count starts below zero): the error grows at first, and its mean is
    no sign of having settled. Nothing while not isolating or without the recovery (sat_reset_s 0)."""
    o = 2 * int(cf[_CF_NSEC])
    if cf[_CF_SATN] > 0.0 and st[o + _ON] > 0.5:
        if st[o + _SUS] < 0.5:
            _suspend(st, o, st[o + _U], st[o + _C], st[o + _V])
        st[o + _K] = -cf[_CF_LOSSN]


@numba.njit(cache=True, inline="always")
def _saturation_recovery(st, cf, o, on, u, lim, v, b, cent, kp):
    """Isolating at the clamp for sat_reset_s: the loop is not following its estimate of the absolute motion
    (typically a velocity error in the double integration after a scheduling gap: with a slow blend a few
    um/s already drive the piston to its full stroke, and the estimate forgets it only at the blend's pace).
    Re-seeding the filters cannot fix that (the true velocity is unknown), so isolation is suspended the
    bumpless way (b takes over, centring alone), the filters keep running, and isolation resumes bumplessly
    once the mean of v (over ~sat_resume_s: the estimate's error, not the floor motion the loop is there to
    isolate) has stayed within resume_m for sat_resume_s. Inert in the linear range."""
    if on:
        if u >= lim or u <= -lim:
            k = st[o + _K] + 1.0
            if k >= cf[_CF_SATN]:
                _suspend(st, o, u, cent, v)               # hold the output (at the clamp)
                k = 0.0
            st[o + _K] = k
        else:
            st[o + _K] = 0.0
    elif st[o + _SUS] > 0.5:
        mv = st[o + _A]
        mv += cf[_CF_RESA] * (v - mv)
        st[o + _A] = mv
        rv = cf[_CF_RESM]
        k = st[o + _K]
        if k < 0.0 or -rv < mv < rv:                 # (below zero: the hold after lost conversions)
            k += 1.0
        else:
            k = 0.0
        if k >= cf[_CF_RESN]:
            st[o + _B] = b + kp * v                       # the PI restarts from zero, no jump
            st[o + _I] = 0.0
            st[o + _SUS] = 0.0
            k = 0.0
        st[o + _K] = k


def make_isolation_controllers(cfg, dt: float, *, compensator: bool = True) -> list[IsolationController]:
    """One controller per mount of the layout (rig.config.layout_mounts: MOUNTS order on the machine), from
    cfg.controller (the runtime's entry point)."""
    return [IsolationController(params_from_config(cfg, i), dt, compensator=compensator, name=m)
            for i, m in enumerate(layout_mounts(cfg))]

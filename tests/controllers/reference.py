"""Pure-Python references of the compiled laws (the runtime's are in controllers/*.py, numba): written
the plain way, as the first versions were, so property tests can hold the compiled ones against them."""
from __future__ import annotations

import math

from controllers import tracking as T
from controllers.isolation import _A, _B, _C, _I, _K, _ON, _S, _SUS, _U, _V


def _sos_step(sections, state: list, i0: int, x: float) -> float:
    """One sample through the cascade (transposed direct form II); state[i0 : i0 + 2 n] updated in place."""
    i = i0
    for b0, b1, b2, a1, a2 in sections:
        y = b0 * x + state[i]
        state[i] = b1 * x - a1 * y + state[i + 1]
        state[i + 1] = b2 * x - a2 * y
        x = y
        i += 2
    return x


def isolation_step(c, state: list, meas, dt: float):
    """IsolationController c, one period, the plain way: (u, state), state (a list) updated in place."""
    if abs(dt - c.dt) > 1e-6 * c.dt:
        raise ValueError(f"controller built for dt={c.dt} s, stepped with dt={dt} s")
    a, s = meas
    o = c._o
    # y = H/s^2 a + F stroke, then v = Comp y (the compiled law runs the same operations in the same order)
    y = _sos_step(c.h_acc, state, 0, a)
    x = _sos_step(c.f_str, state, 2 * len(c.h_acc), s)
    v = _sos_step(c.comp, state, 2 * (len(c.h_acc) + len(c.f_str)), x + y)
    h = 0.5 * dt
    on = state[o + _ON] > 0.5 and state[o + _SUS] < 0.5
    if on:
        d_i = c.ki * h * (v + state[o + _V])                 # Tustin PI integral
        d_c = 0.0                                              # centring: the blend does it
    else:
        d_i = 0.0
        d_c = c.kc * h * (s + state[o + _S])                # slow centring integrator
    integ = state[o + _I] + d_i
    cent = state[o + _C] + d_c
    b = state[o + _B] * c.fade
    u = (-(c.kp * v + integ) if on else 0.0) + b - cent
    up = state[o + _U]
    sat = 0.0
    if u - up > c.slew:
        u, sat = up + c.slew, 1.0
    elif up - u > c.slew:
        u, sat = up - c.slew, -1.0
    lim = c.limit
    if u > lim:
        u, sat = lim, 1.0
    elif u < -lim:
        u, sat = -lim, -1.0
    if sat != 0.0:
        # anti-windup (conditional integration): drop increments that push further into the limit
        if d_i * sat < 0.0:
            integ -= d_i
        if d_c * sat < 0.0:
            cent -= d_c
    state[o + _V] = v
    state[o + _I] = integ
    state[o + _C] = cent
    state[o + _S] = s
    state[o + _B] = b
    state[o + _U] = u
    if c.sat_n:
        # Saturation recovery. Isolating at the clamp for sat_reset_s: the loop is not following its
        # estimate of the absolute motion (typically a velocity error in the double integration after a
        # scheduling gap: with the 0.1 Hz blend a few um/s already drive the piston to its full stroke,
        # and the estimate forgets it only at the blend's pace, seconds). Re-seeding the filters cannot fix
        # that (the true velocity is unknown), so isolation is suspended the bumpless way (b takes over,
        # centring alone), the filters keep running, and isolation resumes bumplessly once the mean of v
        # (over ~sat_resume_s: the estimate's error, not the 1-50 Hz floor motion the loop is there to
        # isolate) has stayed within resume_m for sat_resume_s. Inert in the linear range (brief clamping
        # under shocks, tens of ms, recovers by itself and does not trigger it).
        if on:
            if u >= lim or u <= -lim:
                k = state[o + _K] + 1.0
                if k >= c.sat_n:
                    state[o + _B] = u + cent                      # hold the output (at the clamp)
                    state[o + _I] = 0.0
                    state[o + _SUS] = 1.0
                    state[o + _A] = v
                    k = 0.0
                state[o + _K] = k
            else:
                state[o + _K] = 0.0
        elif state[o + _SUS] > 0.5:
            m = state[o + _A]
            m += c.resume_a * (v - m)
            state[o + _A] = m
            k = state[o + _K]
            k = k + 1.0 if k < 0.0 or -c.resume_m < m < c.resume_m else 0.0     # (< 0: held after a loss)
            if k >= c.resume_n:
                state[o + _B] = b + c.kp * v                   # the PI restarts from zero, no jump
                state[o + _I] = 0.0
                state[o + _SUS] = 0.0
                k = 0.0
            state[o + _K] = k
    return u, state


def feedforward_step(f, state: list, g: float) -> float:
    """FeedforwardFilter f, one period, the plain way: the sections but the last on the floor acceleration g; the
    last, the DC block, as out = y - z with z the command's level: set to y at switch-on, then the mean of y since
    switch-on until that window reaches 1 / (1 - pole) periods; times the output gain, which moves towards the
    switch request with factor f.fade (state a list, updated in place; the block keeps -z, as the cascade would).
    A restart (controllers/feedforward.py feedforward_restart) holds the request off for its periods and adds the
    output it held, fading at the same pace."""
    n = len(f.sections)
    o = 2 * n
    y = _sos_step(f.sections[:-1], state, 0, g)
    i = 2 * (n - 1)
    waiting = state[o + 3] > 0.0
    if waiting:
        state[o + 3] -= 1.0
    on = state[o + 1] > 0.5 and not waiting
    if on and state[o + 2] == 0.0:
        state[i] = -y
    state[o + 2] = state[o + 2] + 1.0 if on else 0.0
    z = -state[i]
    out = y - z
    weight = 1.0 + f.sections[-1][3]                    # 1 - pole: the settled block's step
    if state[o + 2] > 0.0:
        weight = max(weight, 1.0 / state[o + 2])
    state[i] = -(z + weight * out)
    request = 1.0 if on else 0.0
    gain = request + (state[o] - request) * f.fade
    state[o] = gain
    held = state[o + 4]
    state[o + 4] = held * f.fade
    state[o + 5] = gain * out + held
    return state[o + 5]


def track_step(c, state: list, x: float, cf=None) -> float:
    """TrackingPID c, one period, the plain way (the reference generator, its feedforward, the PID);
    state (a list, c.state_names) updated in place; cf: where a profile table was written (default none).
    Returns the command."""
    dt = c.dt
    cf = c.coefficients() if cf is None else cf
    st = state
    tgt, o, do = st[T._TGT], st[T._O], st[T._OV]
    # hold position towards its target: speed <= rate, change <= accel per period, able to stop at the target
    if o != tgt or do != 0.0:
        amax, vmax = c.ref.accel_m_per_s2, c.ref.rate_m_per_s
        if amax * dt > 1e30:
            o, do = tgt, 0.0
        else:
            d = tgt - o
            s = math.sqrt(2.0 * amax * abs(d) + (amax * dt) ** 2) - amax * dt
            vd = math.copysign(min(vmax, s, abs(d) / dt), d)
            do += min(max(vd - do, -amax * dt), amax * dt)
            o += do * dt
            if abs(tgt - o) <= 0.5 * amax * dt * dt and abs(do) <= amax * dt:
                o, do = tgt, 0.0
    w = wd = 0.0
    if st[T._WAVE] > 0.5:
        tw = st[T._WT]
        if tw < 0.0 and o == tgt and do == 0.0:
            tw = 0.0
        if tw >= 0.0:
            w, wd, done = _wave(st, cf, tw, dt)
            if done:
                o, do = o + w, do + wd
                st[T._TGT] = o
                w = wd = 0.0
                st[T._WAVE] = 0.0
                tw = 0.0
            else:
                tw += dt
        st[T._WT] = tw
    st[T._O], st[T._OV] = o, do
    lead = o + w
    st[T._LEAD], st[T._LV] = lead, do + wd
    ff = c.ff_V_per_mps * (do + wd + c.ref.lag_rad_s * lead)
    ring = T._RING
    n = c.preview + 1
    at = int(st[T._AT])
    st[ring + at] = lead
    at = (at + 1) % n
    st[T._AT] = at
    r = st[ring + at]
    e = r - x
    if x == st[T._XP] and st[T._HELD] < max(1, int(round(T.HOLD_MAX_S / dt))):   # no new sample: hold
        st[T._HELD] += 1.0
        u = st[T._FB] + ff
        if u > c.p.limit_V:
            u = c.p.limit_V
        elif u < -c.p.limit_V:
            u = -c.p.limit_V
        up = st[T._U]
        if u - up > c.slew:
            u = up + c.slew
        elif up - u > c.slew:
            u = up - c.slew
        st[T._U], st[T._R], st[T._FF] = u, r, ff
        return u
    d_i = c.hi * (e + st[T._E])
    integ = st[T._I] + d_i
    d = c.ad * st[T._D] + c.bd * (e - st[T._E])
    u = c.p.kp_V_per_m * e + integ + d + ff
    sat = 0.0
    if u > c.p.limit_V:
        u, sat = c.p.limit_V, 1.0
    elif u < -c.p.limit_V:
        u, sat = -c.p.limit_V, -1.0
    up = st[T._U]
    if u - up > c.slew:
        u, sat = up + c.slew, 1.0
    elif up - u > c.slew:
        u, sat = up - c.slew, -1.0
    fb = c.p.kp_V_per_m * e + integ + d
    if sat * d_i > 0.0:
        integ -= d_i
        fb -= d_i
    st[T._I], st[T._E], st[T._D], st[T._U], st[T._R], st[T._FF] = integ, e, d, u, r, ff
    st[T._XP], st[T._FB], st[T._HELD] = x, fb, 0.0
    return u


def _wave(st, cf, tw, dt):
    kind, amp = int(st[T._WAVE]), st[T._AMP]

    def env(t, ramp, span):
        if ramp > 0 and t < ramp:
            return 0.5 - 0.5 * math.cos(math.pi * t / ramp), 0.5 * math.pi / ramp * math.sin(math.pi * t / ramp)
        if ramp > 0 and span > 0 and span - t < ramp:
            return (0.5 - 0.5 * math.cos(math.pi * (span - t) / ramp),
                    -0.5 * math.pi / ramp * math.sin(math.pi * (span - t) / ramp))
        return 1.0, 0.0
    if kind == T.WAVE_SINE:
        span = st[T._SPAN]
        if span > 0 and tw >= span:
            return 0.0, 0.0, True
        om = 2 * math.pi * st[T._F0]
        e, de = env(tw, 1.0 / st[T._F0], span)
        return amp * e * math.sin(om * tw), amp * (de * math.sin(om * tw) + e * om * math.cos(om * tw)), False
    if kind == T.WAVE_CHIRP:
        f0, f1, span = st[T._F0], st[T._F1], st[T._SPAN]
        t = min(tw, span)
        ph = 2 * math.pi * (f0 * t + 0.5 * (f1 - f0) / span * t * t)
        e, de = env(t, min(1.0 / f0, 0.1 * span), 0.0)
        if tw >= span:
            return amp * math.sin(ph), 0.0, True
        dph = 2 * math.pi * (f0 + (f1 - f0) * t / span)
        return amp * e * math.sin(ph), amp * (de * math.sin(ph) + e * dph * math.cos(ph)), False
    n = int(st[T._SPAN])
    tab = cf[len(T.COEFFICIENTS):]
    xk = tw / dt
    k = int(xk + 1e-6)
    if k >= n - 1:
        return tab[n - 1] - tab[0], 0.0, True
    return tab[k] + (xk - k) * (tab[k + 1] - tab[k]) - tab[0], (tab[k + 1] - tab[k]) / dt, False

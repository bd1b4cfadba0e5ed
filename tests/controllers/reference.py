"""Pure-Python references of the compiled laws (the runtime's are in controllers/*.py, numba): written
the plain way, as the first versions were, so property tests can hold the compiled ones against them."""
from __future__ import annotations

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
            k = state[o + _K] + 1.0 if -c.resume_m < m < c.resume_m else 0.0
            if k >= c.resume_n:
                state[o + _B] = b + c.kp * v                   # the PI restarts from zero, no jump
                state[o + _I] = 0.0
                state[o + _SUS] = 0.0
                k = 0.0
            state[o + _K] = k
    return u, state


def feedforward_step(f, state: list, g: float) -> float:
    """FeedforwardFilter f, one period, the plain way: the sections on the floor acceleration g, times the
    output gain, which moves towards the switch request with factor f.fade (state a list, updated in place)."""
    o = 2 * len(f.sections)
    y = _sos_step(f.sections, state, 0, g)
    gain = state[o + 1] + (state[o] - state[o + 1]) * f.fade
    state[o] = gain
    return gain * y

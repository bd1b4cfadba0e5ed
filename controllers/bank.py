"""The four mounts' isolation controllers as one compiled call (numba): the arithmetic of
IsolationController.step (controllers/isolation.py) for every mount over a float64 state array, so the loop
pays one dispatch per period instead of four Python steps (~10 us -> ~1-2 us at 5 kHz).

One source of truth: the coefficients are read from the IsolationController objects (their Tustin sections,
gains, limits and saturation-recovery settings), the state layout is theirs (row i = mount i's state list), and
switching isolation uses their own set_enabled on each row. tests/test_controllers_bank.py checks the bank
against the Python controllers sample for sample.

Interface (the loop's controller-manager contract, for all mounts at once):
  initial_state() -> ndarray (mounts, state_len)
  step(state, (accel_mps2, stroke_m), dt) -> (valve_cmd_V list, state)      state updated in place
  set_enabled(state, on) -> state;  enabled(state) -> bool (all mounts)
The loop's hot path is step_into(state, acc, xs): one compiled call with the inputs as scalars (four mounts;
cheaper than copying them into an array, measured), the commands left in a preallocated float64 array, which
can be the loop's recording row (bind).
"""
from __future__ import annotations

import numba
import numpy as np

from controllers.isolation import _A, _B, _C, _I, _K, _N, _ON, _S, _SUS, _U, _V, IsolationController

# Coefficient array `cf` (float64, flat, so a call unboxes few arrays: dispatch cost ~0.1 us per array):
#   cf[0:4] = n_sections, n_h_acc, n_f_str, h = dt / 2;  then per mount a block of `stride` values:
#   the sections (b0, b1, b2, a1, a2) in state order, then the scalar parameters below.
_HDR = 4
_P_KP, _P_KI, _P_KC, _P_FADE, _P_LIM, _P_SLEW, _P_SATN, _P_RESN, _P_RESM, _P_RESA = range(10)
_NP = 10


@numba.njit(cache=True, inline="always")
def _sections(st, cf, m, i, c, count, x):
    """count biquads in series (transposed direct form II), states from st[m, i], coefficients from cf[c]."""
    for _ in range(count):
        yk = cf[c] * x + st[m, i]
        st[m, i] = cf[c + 1] * x - cf[c + 3] * yk + st[m, i + 1]
        st[m, i + 1] = cf[c + 2] * x - cf[c + 4] * yk
        x = yk
        i += 2
        c += 5
    return x, i, c


@numba.njit(cache=True)
def _step_mount(st, cf, m, a, s):
    """One mount, one period: IsolationController.step, the same operations in the same order."""
    nsec = int(cf[0])
    na = int(cf[1])
    ns = int(cf[2])
    h = cf[3]
    c = _HDR + m * (5 * nsec + _NP)                        # this mount's sections
    p = c + 5 * nsec                                       # and its parameters
    o = 2 * nsec
    y, i, c = _sections(st, cf, m, 0, c, na, a)                  # H/s^2 on the acceleration
    x, i, c = _sections(st, cf, m, i, c, ns, s)                  # F on the stroke
    x, i, c = _sections(st, cf, m, i, c, nsec - na - ns, x + y)  # compensator
    v = x
    kp = cf[p + _P_KP]
    on = st[m, o + _ON] > 0.5 and st[m, o + _SUS] < 0.5
    if on:
        d_i = cf[p + _P_KI] * h * (v + st[m, o + _V])     # Tustin PI integral
        d_c = 0.0
    else:
        d_i = 0.0
        d_c = cf[p + _P_KC] * h * (s + st[m, o + _S])     # slow centring integrator
    integ = st[m, o + _I] + d_i
    cent = st[m, o + _C] + d_c
    b = st[m, o + _B] * cf[p + _P_FADE]
    if on:
        u = -(kp * v + integ) + b - cent
    else:
        u = 0.0 + b - cent
    up = st[m, o + _U]
    slew = cf[p + _P_SLEW]
    sat = 0.0
    if u - up > slew:
        u = up + slew
        sat = 1.0
    elif up - u > slew:
        u = up - slew
        sat = -1.0
    lim = cf[p + _P_LIM]
    if u > lim:
        u = lim
        sat = 1.0
    elif u < -lim:
        u = -lim
        sat = -1.0
    if sat != 0.0:                                         # conditional integration
        if d_i * sat < 0.0:
            integ -= d_i
        if d_c * sat < 0.0:
            cent -= d_c
    st[m, o + _V] = v
    st[m, o + _I] = integ
    st[m, o + _C] = cent
    st[m, o + _S] = s
    st[m, o + _B] = b
    st[m, o + _U] = u
    sat_n = cf[p + _P_SATN]
    if sat_n > 0.0:                                        # saturation recovery (IsolationController.step)
        if on:
            if u >= lim or u <= -lim:
                k = st[m, o + _K] + 1.0
                if k >= sat_n:
                    st[m, o + _B] = u + cent
                    st[m, o + _I] = 0.0
                    st[m, o + _SUS] = 1.0
                    st[m, o + _A] = v
                    k = 0.0
                st[m, o + _K] = k
            else:
                st[m, o + _K] = 0.0
        elif st[m, o + _SUS] > 0.5:
            mv = st[m, o + _A]
            mv += cf[p + _P_RESA] * (v - mv)
            st[m, o + _A] = mv
            rv = cf[p + _P_RESM]
            if -rv < mv < rv:
                k = st[m, o + _K] + 1.0
            else:
                k = 0.0
            if k >= cf[p + _P_RESN]:
                st[m, o + _B] = b + kp * v
                st[m, o + _I] = 0.0
                st[m, o + _SUS] = 0.0
                k = 0.0
            st[m, o + _K] = k
    return u


@numba.njit(cache=True, inline="always")
def put_inputs4(io, ia, a0, a1, a2, a3, s0, s1, s2, s3):
    """The four accelerations, then the four strokes, into io[ia:ia+8]."""
    io[ia] = a0
    io[ia + 1] = a1
    io[ia + 2] = a2
    io[ia + 3] = a3
    io[ia + 4] = s0
    io[ia + 5] = s1
    io[ia + 6] = s2
    io[ia + 7] = s3


@numba.njit(cache=True)
def _step4(st, cf, io, ia, iu, ist, a0, a1, a2, a3, s0, s1, s2, s3):
    """Four mounts, one period, inputs as scalars (cheaper to pass than to copy into an array). io gets the
    inputs at ia (accelerations, strokes), the commands at iu and, if ist >= 0, a copy of the states at ist:
    io can be the loop's recording row, so the period is recorded without another pass."""
    put_inputs4(io, ia, a0, a1, a2, a3, s0, s1, s2, s3)
    io[iu] = _step_mount(st, cf, 0, a0, s0)
    io[iu + 1] = _step_mount(st, cf, 1, a1, s1)
    io[iu + 2] = _step_mount(st, cf, 2, a2, s2)
    io[iu + 3] = _step_mount(st, cf, 3, a3, s3)
    if ist >= 0:
        k = ist
        for m in range(st.shape[0]):
            for j in range(st.shape[1]):
                io[k] = st[m, j]
                k += 1


@numba.njit(cache=True)
def _step_n(st, cf, io):
    """Any number of mounts, one period: io = accelerations (n), strokes (n), commands out (n)."""
    n = st.shape[0]
    for m in range(n):
        io[2 * n + m] = _step_mount(st, cf, m, io[m], io[n + m])


@numba.njit(cache=True)
def _replay(st, cf, io, miss, first):
    """Periods first..miss-1 of `miss` skipped ones, inputs interpolated from the previous period's
    (io[3n:5n]) to this period's (io[0:2n]); outputs discarded."""
    n = st.shape[0]
    for j in range(first, miss):
        f = (j + 1) / (miss + 1)
        for m in range(n):
            pa = io[3 * n + m]
            px = io[4 * n + m]
            _step_mount(st, cf, m, pa + f * (io[m] - pa), px + f * (io[n + m] - px))


class IsolationBank:
    """The isolation controllers of all mounts in one compiled step (see the module docstring)."""

    def __init__(self, controllers: list) -> None:
        ctrls = list(controllers)
        if not ctrls or not all(type(c) is IsolationController for c in ctrls):
            raise TypeError("IsolationBank: expected a list of IsolationController")
        c0 = ctrls[0]
        shape = (len(c0.h_acc), len(c0.f_str), len(c0.comp))
        for c in ctrls:
            if (len(c.h_acc), len(c.f_str), len(c.comp)) != shape or c.dt != c0.dt:
                raise ValueError("IsolationBank: the controllers differ in structure or dt")
        self.ctrls = ctrls
        self.n = n = len(ctrls)
        self.dt = c0.dt
        nsec = sum(shape)
        stride = 5 * nsec + _NP
        cf = np.zeros(_HDR + n * stride)
        cf[0:_HDR] = nsec, shape[0], shape[1], 0.5 * self.dt
        for m, c in enumerate(ctrls):
            b = _HDR + m * stride
            cf[b:b + 5 * nsec] = np.ravel(c.sections)
            p = b + 5 * nsec
            cf[p + _P_KP], cf[p + _P_KI], cf[p + _P_KC] = c.kp, c.ki, c.kc
            cf[p + _P_FADE], cf[p + _P_LIM], cf[p + _P_SLEW] = c.fade, c.limit, c.slew
            cf[p + _P_SATN], cf[p + _P_RESN] = c.sat_n, c.resume_n
            cf[p + _P_RESM], cf[p + _P_RESA] = c.resume_m, c.resume_a
        self.cf = cf
        self.state_len = 2 * nsec + _N
        self.io = np.zeros(5 * n)          # inputs (2n), commands (n), previous inputs (2n)
        self.bind(self.io, 0, 2 * n, -1)
        # compile (or load from the cache) now, not in the first period
        st = self.initial_state()
        if n == 4:
            _step4(st, cf, np.zeros(12 + st.size), 0, 8, 12, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            _step4(st, cf, self.io, 0, 8, -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _step_n(st, cf, self.io)
        _replay(st, cf, self.io, 1, 0)

    def bind(self, buf: np.ndarray, ia: int, iu: int, ist: int) -> None:
        """Where step_into leaves its results (four mounts): the inputs at buf[ia:ia+2n], the commands at
        buf[iu:iu+n] (self.out) and the states at buf[ist:] (ist < 0: not copied)."""
        n = self.n
        if ia < 0 or iu < 0 or max(ia + 2 * n, iu + n, ist + n * self.state_len if ist >= 0 else 0) > len(buf):
            raise ValueError("IsolationBank.bind: offsets outside the buffer")
        self._buf, self._ia, self._iu, self._ist = buf, ia, iu, ist
        self.out = buf[iu:iu + n]

    # ---- the controller-manager interface (all mounts) ---------------------------------------------------
    def initial_state(self) -> np.ndarray:
        return np.array([c.initial_state() for c in self.ctrls], dtype=np.float64)

    def set_enabled(self, state: np.ndarray, on: bool) -> np.ndarray:
        """Bumpless isolation on/off of every mount, by each controller's own set_enabled (not in the period)."""
        for m, c in enumerate(self.ctrls):
            state[m] = c.set_enabled(state[m].tolist(), on)
        return state

    def enabled(self, state: np.ndarray) -> bool:
        return all(c.enabled(state[m].tolist()) for m, c in enumerate(self.ctrls))

    def suspended(self, state: np.ndarray) -> list[bool]:
        return [c.suspended(state[m].tolist()) for m, c in enumerate(self.ctrls)]

    def step(self, state: np.ndarray, meas, dt: float):
        """(accel_list, stroke_list) -> (commands list, state), state updated in place."""
        if abs(dt - self.dt) > 1e-6 * self.dt:
            raise ValueError(f"controller bank built for dt={self.dt} s, stepped with dt={dt} s")
        self.step_into(state, meas[0], meas[1])
        return self.out.tolist(), state

    def step_into(self, state: np.ndarray, acc, xs) -> np.ndarray:
        """The loop's hot path: one compiled call; inputs and commands are left in self.io (inputs 2n, then
        the commands, self.out)."""
        if self.n == 4:
            a0, a1, a2, a3 = acc
            s0, s1, s2, s3 = xs
            _step4(state, self.cf, self._buf, self._ia, self._iu, self._ist, a0, a1, a2, a3, s0, s1, s2, s3)
            return self.out
        io, n = self.io, self.n
        io[:n] = acc
        io[n:2 * n] = xs
        _step_n(state, self.cf, io)
        return io[2 * n:3 * n]

    def replay(self, state: np.ndarray, prev_meas, meas, miss: int, max_steps: int) -> None:
        """Step the last min(miss, max_steps) of `miss` skipped periods, inputs interpolated from prev_meas
        to meas (the double integration must see the time pass; outputs are not written)."""
        io, n = self.io, self.n
        io[:n] = meas[0]
        io[n:2 * n] = meas[1]
        io[3 * n:4 * n] = prev_meas[0]
        io[4 * n:5 * n] = prev_meas[1]
        _replay(state, self.cf, io, miss, max(0, miss - max_steps))


def make_bank(controllers) -> IsolationBank | None:
    """A bank for a list of IsolationControllers of one structure, else None (the caller steps them one by
    one in Python)."""
    try:
        return IsolationBank(controllers)
    except (TypeError, ValueError):
        return None

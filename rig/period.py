"""The compiled period of the four-mount bank path: sensor check -> controller bank -> command limit -> record
in one numba call, so the loop pays one dispatch per period for the arithmetic of four stages.

The stages keep their meaning and their owners: the check and the limit are rig/safety.py's SensorCheck and
CommandLimiter (KernelCheck / KernelLimiter below are those classes with their state in one float64 array and
the same decisions, property-tested against them in tests/test_runtime_period.py), and the controllers are
controllers/bank.py's compiled bank. A nonzero return code names the stage, the mount and the reason; the
loop turns it into the same one-line fault text the Python stages give (off the hot path).

Safety state array `sv` (n mounts): check [last sample time stamp n | last accel n | last stroke n |
same-accel count n | same-stroke count n], then limiter [last command n | sat_run | clamped | limited].
Time stamps are kept as float64: exact below 2**53 ns (104 days of monotonic time), and beyond that still
distinct for samples a period apart, which is all the stuck check asks of them.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from controllers.bank import _step4, put_inputs4
from rig.safety import CommandLimiter, SensorCheck

# return codes: 0 ok; CHECK_* + mount; LIMIT_NAN + mount; LIMIT_LATCHED
CHECK_IMPLAUSIBLE, CHECK_STUCK_ACCEL, CHECK_STUCK_STROKE = 100, 200, 300
LIMIT_NAN, LIMIT_LATCHED = 400, 500


@numba.njit(cache=True, inline="always")
def _check_mount(sv, n, i, a, x, tsi, ar, xb, oldest, stuck_n):
    """SensorCheck.check for mount i (the same tests in the same order); 0 or a code."""
    if not (-ar <= a <= ar and -xb <= x <= xb and tsi >= oldest):      # also false for NaN
        return CHECK_IMPLAUSIBLE + i
    if tsi != sv[i]:                                                  # a new sample: stuck check
        sv[i] = tsi
        if a == sv[n + i]:
            sv[3 * n + i] += 1.0
            if sv[3 * n + i] >= stuck_n:
                return CHECK_STUCK_ACCEL + i
        else:
            sv[3 * n + i] = 0.0
            sv[n + i] = a
        if x == sv[2 * n + i]:
            sv[4 * n + i] += 1.0
            if sv[4 * n + i] >= stuck_n:
                return CHECK_STUCK_STROKE + i
        else:
            sv[4 * n + i] = 0.0
            sv[2 * n + i] = x
    return 0


@numba.njit(cache=True, inline="always")
def _limit(sv, n, raw, iraw, out, iout, max_v, step_v, sat_limit):
    """CommandLimiter.limit: raw[iraw:iraw+n] -> out[iout:iout+n]; 0 or a code."""
    o = 5 * n
    hit = False
    at_clamp = False
    for i in range(n):
        u = raw[iraw + i]
        if u != u:
            return LIMIT_NAN + i
        if u >= max_v:
            u = max_v
            hit = at_clamp = True
        elif u <= -max_v:
            u = -max_v
            hit = at_clamp = True
        p = sv[o + i]
        if u - p > step_v:
            u = p + step_v
            hit = True
        elif p - u > step_v:
            u = p - step_v
            hit = True
        out[iout + i] = u
        sv[o + i] = u
    sv[o + n + 2] = 1.0 if hit else 0.0
    if hit:
        sv[o + n + 1] += 1.0
    if at_clamp:
        sv[o + n] += 1.0
        if sv[o + n] >= sat_limit:
            return LIMIT_LATCHED
    else:
        sv[o + n] = 0.0
    return 0


@numba.njit(cache=True)
def _check_n(sv, acc, xs, ts, t_ns, ar, xb, stale_ns, stuck_n):
    n = acc.shape[0]
    oldest = t_ns - stale_ns
    for i in range(n):
        c = _check_mount(sv, n, i, acc[i], xs[i], ts[i], ar, xb, oldest, stuck_n)
        if c:
            return c
    return 0


@numba.njit(cache=True)
def _limit_n(sv, raw, out, max_v, step_v, sat_limit):
    return _limit(sv, raw.shape[0], raw, 0, out, 0, max_v, step_v, sat_limit)


# header of the memory block (float64 slots): row offsets, limits, where each part starts
_H_IA, _H_IU, _H_IST, _H_ICMD, _H_ILIM = 0, 1, 2, 3, 4
_H_LIMITS = 5                       # 7 slots: accel range, stroke bound, stale ns, stuck n, max V, step V, sat n
_H_CF, _H_NCF, _H_SV, _H_ST, _H_L, _H_ROW, _H_NROW = 12, 13, 14, 15, 16, 17, 18
_HDR = 20


@numba.njit(cache=True)
def _period4(mem, ring, slot, a0, a1, a2, a3, s0, s1, s2, s3, t0, t1, t2, t3, t_ns, t_s, wake_us, comp_us,
             step, active):
    """One period of four mounts on the memory block `mem` (CompiledPeriod: header, bank coefficients, safety
    state, controller states, the recording row in the loop's layout): check the measurement; step the bank
    if `step` (inputs, raw commands and states into the row, as IsolationBank.step_into), else put the inputs
    in the row (the controllers hold); limit the raw commands into the row's command columns if `active`,
    else null there; then the limiter's flag, time, wake-up latency and the previous compute time; with
    slot >= 0 copy the row into ring[slot] (Recorder.next_row; the caller commits). A nonzero code (a check
    or limit fault) returns before the copy: the caller records that period itself. One block and the ring
    are the only arrays passed: each array argument costs ~0.1 us of dispatch, measured."""
    ia = int(mem[_H_IA])
    iu = int(mem[_H_IU])
    ist = int(mem[_H_IST])
    icmd = int(mem[_H_ICMD])
    ilim = int(mem[_H_ILIM])
    ar = mem[_H_LIMITS]
    xb = mem[_H_LIMITS + 1]
    stale_ns = int(mem[_H_LIMITS + 2])
    stuck_n = mem[_H_LIMITS + 3]
    max_v = mem[_H_LIMITS + 4]
    step_v = mem[_H_LIMITS + 5]
    sat_limit = mem[_H_LIMITS + 6]
    o_cf = int(mem[_H_CF])
    o_sv = int(mem[_H_SV])
    o_st = int(mem[_H_ST])
    nst = int(mem[_H_L])
    o_row = int(mem[_H_ROW])
    cf = mem[o_cf:o_cf + int(mem[_H_NCF])]
    sv = mem[o_sv:o_st]
    st = mem[o_st:o_st + 4 * nst].reshape((4, nst))
    row = mem[o_row:o_row + int(mem[_H_NROW])]
    oldest = t_ns - stale_ns
    c = _check_mount(sv, 4, 0, a0, s0, t0, ar, xb, oldest, stuck_n)
    if c == 0:
        c = _check_mount(sv, 4, 1, a1, s1, t1, ar, xb, oldest, stuck_n)
    if c == 0:
        c = _check_mount(sv, 4, 2, a2, s2, t2, ar, xb, oldest, stuck_n)
    if c == 0:
        c = _check_mount(sv, 4, 3, a3, s3, t3, ar, xb, oldest, stuck_n)
    if c:
        return c
    if step:
        _step4(st, cf, row, ia, iu, ist, a0, a1, a2, a3, s0, s1, s2, s3)
    else:
        put_inputs4(row, ia, a0, a1, a2, a3, s0, s1, s2, s3)      # the controllers hold
    if active:
        c = _limit(sv, 4, row, iu, row, icmd, max_v, step_v, sat_limit)
        if c:
            return c
    else:
        for i in range(4):
            row[icmd + i] = 0.0
    row[ilim] = sv[4 * 5 + 4 + 2]                      # the limiter's `limited` (sv layout above)
    row[0] = t_s
    row[ilim + 1] = wake_us
    row[ilim + 2] = comp_us
    if slot >= 0:
        ring[slot, :] = row
    return 0


def native_entry(dispatcher):
    """The compiled function's own entry point (argument unboxing only) for its one compiled signature,
    skipping the dispatcher's type resolution: 1.2 -> 0.7 us per _period4 call, measured. The caller must
    pass exactly those types (values convert as Python's float()/int() would, numeric text included; None or
    any other object is a TypeError) and arrays of the compiled layout: C-contiguous float64, never a strided
    view (ring_ok). Falls back to the dispatcher where numba does not offer this."""
    try:
        (sig,) = dispatcher.signatures
        return dispatcher.overloads[sig].entry_point
    except (AttributeError, KeyError, TypeError, ValueError):
        return dispatcher


def ring_ok(ring) -> bool:
    """A recorder ring the compiled period may write: 2-D C-contiguous float64 (native_entry checks nothing)."""
    return (isinstance(ring, np.ndarray) and ring.ndim == 2 and ring.dtype == np.float64
            and ring.flags.c_contiguous and ring.flags.writeable)


class KernelCheck(SensorCheck):
    """SensorCheck with its state in the shared array `sv` (the compiled period's), same decisions."""

    def __init__(self, cfg, n_mounts: int, names=None, sv: np.ndarray | None = None) -> None:
        self.sv = sv if sv is not None else np.zeros(6 * n_mounts + 3)
        super().__init__(cfg, n_mounts, names)

    def reset(self) -> None:
        n = self.n
        self.sv[0:3 * n] = math.nan            # no sample seen yet
        self.sv[3 * n:5 * n] = 0.0

    def check(self, m, t_ns: int) -> str | None:
        if m.device_fault:
            return f"device fault: {m.device_fault}"
        f64 = np.float64
        c = _check_n(self.sv, np.asarray(m.accel_mps2, dtype=f64), np.asarray(m.stroke_m, dtype=f64),
                     np.asarray(m.sample_t_ns, dtype=f64), t_ns, self.accel_range, self._x_bound,
                     self.stale_ns, self.stuck_n)
        return self.reason(c, m.accel_mps2, m.stroke_m, m.sample_t_ns, t_ns) if c else None

    def reason(self, code: int, acc, xs, ts, t_ns: int) -> str:
        """The fault text of a check code (the words of SensorCheck.check)."""
        i = code % 100
        n = self.n
        if code - i == CHECK_STUCK_ACCEL:
            return (f"{self.names[i]}: accelerometer stuck at {acc[i]!r} m/s^2 "
                    f"for {int(self.sv[3 * n + i])} samples")
        if code - i == CHECK_STUCK_STROKE:
            return (f"{self.names[i]}: displacement transducer stuck at {xs[i]!r} m "
                    f"for {int(self.sv[4 * n + i])} samples")
        return self._reason(i, acc[i], xs[i], ts[i], t_ns)


class KernelLimiter(CommandLimiter):
    """CommandLimiter with its state in the shared array `sv` (the compiled period's), same decisions."""

    def __init__(self, cfg, n_mounts: int, dt: float, sv: np.ndarray | None = None) -> None:
        self.sv = sv if sv is not None else np.zeros(6 * n_mounts + 3)
        self._o = 5 * n_mounts
        super().__init__(cfg, n_mounts, dt)

    # the CommandLimiter attributes, read from and written to the array
    last = property(lambda self: self.sv[self._o:self._o + self.n].tolist(),
                    lambda self, v: self.sv.__setitem__(slice(self._o, self._o + self.n), v))
    sat_run = property(lambda self: int(self.sv[self._o + self.n]),
                       lambda self, v: self.sv.__setitem__(self._o + self.n, v))
    clamped = property(lambda self: int(self.sv[self._o + self.n + 1]),
                       lambda self, v: self.sv.__setitem__(self._o + self.n + 1, v))
    limited = property(lambda self: bool(self.sv[self._o + self.n + 2]),
                       lambda self, v: self.sv.__setitem__(self._o + self.n + 2, 1.0 if v else 0.0))

    def reset(self) -> None:
        self.sv[self._o:self._o + self.n + 1] = 0.0      # last commands (the valve is at null) and sat_run

    def limit(self, raw: list, out: list) -> str | None:
        res = np.zeros(self.n)
        c = _limit_n(self.sv, np.asarray(raw, dtype=np.float64), res, self.max_V, self.step_V, self.sat_limit)
        if c >= LIMIT_NAN and c < LIMIT_LATCHED:
            return self.reason(c)
        out[:] = res.tolist()
        return self.reason(c) if c else None

    def reason(self, code: int) -> str:
        if code == LIMIT_LATCHED:
            return (f"valve command at the +-{self.max_V:g} V clamp for {self.sat_run} periods: "
                    f"the loop is not in control")
        return f"controller {code - LIMIT_NAN}: valve command is NaN"


class CompiledPeriod:
    """The loop's four-mount bank path: one call per period (see the module docstring). Owns one float64
    memory block holding the bank's coefficients (the bank steps with the same ones), the safety state, the
    controller states (`states`, the loop's) and the recording row (`row`, the loop's)."""

    IA, IU, IST, ICMD = 1, 13, 17, 9      # the loop's row: time, accel 4, stroke 4, cmd 4, raw 4, states, flags

    def __init__(self, cfg, bank, names, dt: float, n_flags: int, i_limited: int) -> None:
        n = bank.n
        if n != 4:
            raise ValueError("CompiledPeriod: four mounts")
        nst = bank.state_len
        ncf = len(bank.cf)
        nrow = 1 + 16 + n * nst + n_flags
        o_cf = _HDR
        o_sv = o_cf + ncf
        o_st = o_sv + 6 * n + 3
        o_row = o_st + n * nst
        self.mem = mem = np.zeros(o_row + nrow)
        mem[o_cf:o_sv] = bank.cf
        bank.cf = mem[o_cf:o_sv]
        self.sv = mem[o_sv:o_st]
        self.states = mem[o_st:o_row].reshape(n, nst)
        self.row = mem[o_row:]
        self.check = KernelCheck(cfg, n, names, self.sv)
        self.limiter = KernelLimiter(cfg, n, dt, self.sv)
        self.bank = bank
        self.ilim = i_limited
        c, lim = self.check, self.limiter
        mem[_H_IA], mem[_H_IU], mem[_H_IST], mem[_H_ICMD], mem[_H_ILIM] = (self.IA, self.IU, self.IST,
                                                                          self.ICMD, i_limited)
        mem[_H_LIMITS:_H_LIMITS + 7] = (c.accel_range, c._x_bound, c.stale_ns, c.stuck_n, lim.max_V,
                                        lim.step_V, lim.sat_limit)
        mem[_H_CF], mem[_H_NCF], mem[_H_SV], mem[_H_ST], mem[_H_L], mem[_H_ROW], mem[_H_NROW] = (
            o_cf, ncf, o_sv, o_st, nst, o_row, nrow)
        self.states[:] = bank.initial_state()
        bank.bind(self.row, self.IA, self.IU, self.IST)
        self.no_ring = np.zeros((1, nrow))          # stands in for the ring without a recorder (slot -1)
        # compiled before the first period, with the argument types the loop passes, on a scratch copy
        _period4(mem.copy(), self.no_ring, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0, 0, 0.0, 0.0,
                 0.0, True, True)
        self.call = native_entry(_period4)           # the loop's per-period call

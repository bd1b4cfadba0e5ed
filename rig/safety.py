"""Safety rules run inside the period: sensor plausibility (`check_sensors`) and command limits
(`limit_commands`), compiled (numba) and called by the period kernel (rig/kernel.py); plus a watchdog thread
that sends the valve to null if the loop itself stops.

SensorCheck and CommandLimiter are the rules' builders: their limits from the config, their named state
(initial values; the kernel owns the memory), and the one-line fault texts (off the hot path). A rule returns
0 or a code that names the rule and the mount (CHECK_* + mount, LIMIT_NAN + mount, LIMIT_LATCHED).
"""
from __future__ import annotations

import logging
import math
import threading
import time

import numba
import numpy as np

from rig.config import Config, mount_names

log = logging.getLogger("rig.safety")

CHECK_IMPLAUSIBLE, CHECK_STUCK_ACCEL, CHECK_STUCK_STROKE = 100, 200, 300
LIMIT_NAN, LIMIT_LATCHED = 400, 500
CHECK_FLOOR = 900                     # + mount: a floor accelerometer NaN or out of its range

# Named limits (one float64 array, the kernel's): the check's, then the limiter's
LIMITS = ("accel_range_mps2", "stroke_bound_m", "stale_ns", "stuck_n", "max_V", "step_V", "sat_n")
_L_AR, _L_XB, _L_STALE, _L_STUCK, _L_MAX, _L_STEP, _L_SAT = range(7)
# Named state of the check (rows of a (5, n) array) and of the limiter (last command per mount, then flags)
CHECK_STATE = ("last_sample_t_ns", "last_accel_mps2", "last_stroke_m", "same_accel_count", "same_stroke_count")
_C_TS, _C_A, _C_X, _C_SA, _C_SX = range(5)
LIMITER_FLAGS = ("sat_run", "clamped", "limited")
_F_SATRUN, _F_CLAMPED, _F_LIMITED = range(3)


@numba.njit(cache=True)
def check_sensors(cs, lim, acc, xs, ts, t_ns):
    """Plausibility of one period's measurement, mount by mount: NaN/inf, out of sensor range, beyond the
    stroke limit, stale (time stamp older than stale_s at the loop time), stuck (the same value over stuck_n
    NEW samples: the time stamp moved on but the value did not; a held sample is caught as stale instead).
    0 or a code. Time stamps are float64: exact below 2**53 ns (104 days of monotonic time)."""
    ar = lim[_L_AR]
    xb = lim[_L_XB]
    oldest = t_ns - lim[_L_STALE]
    stuck_n = lim[_L_STUCK]
    for i in range(acc.shape[0]):
        a = acc[i]
        x = xs[i]
        tsi = ts[i]
        if not (-ar <= a <= ar and -xb <= x <= xb and tsi >= oldest):      # also false for NaN
            return CHECK_IMPLAUSIBLE + i
        if tsi != cs[_C_TS, i]:                                           # a new sample: stuck check
            cs[_C_TS, i] = tsi
            if _stuck(cs, _C_A, _C_SA, i, a, stuck_n):
                return CHECK_STUCK_ACCEL + i
            if _stuck(cs, _C_X, _C_SX, i, x, stuck_n):
                return CHECK_STUCK_STROKE + i
    return 0


@numba.njit(cache=True)
def check_floor(floor, range_mps2):
    """The floor accelerometers (the feedforward's input): NaN/inf or beyond +-range_mps2 -> CHECK_FLOOR +
    mount. Their time stamp is the mount accelerometers' (one conversion of the same module): staleness is
    check_sensors'."""
    for i in range(floor.shape[0]):
        g = floor[i]
        if not (-range_mps2 <= g <= range_mps2):
            return CHECK_FLOOR + i
    return 0


@numba.njit(cache=True, inline="always")
def _stuck(cs, last, count, i, v, stuck_n):
    """Count a new sample equal to the last one; True once stuck_n of them came in a row."""
    if v == cs[last, i]:
        cs[count, i] += 1.0
        return cs[count, i] >= stuck_n
    cs[count, i] = 0.0
    cs[last, i] = v
    return False


@numba.njit(cache=True)
def limit_commands(last, flags, lim, raw, out):
    """Clamp (+-max_V) and slew limit (step_V per period, from the last written command) raw -> out. 0, or a
    code: a NaN command, or a command held at the clamp for sat_n periods (the loop is no longer in control)."""
    max_v = lim[_L_MAX]
    step_v = lim[_L_STEP]
    hit = False
    at_clamp = False
    for i in range(raw.shape[0]):
        u = raw[i]
        if u != u:
            return LIMIT_NAN + i
        if u >= max_v:
            u = max_v
            hit = at_clamp = True
        elif u <= -max_v:
            u = -max_v
            hit = at_clamp = True
        p = last[i]
        if u - p > step_v:
            u = p + step_v
            hit = True
        elif p - u > step_v:
            u = p - step_v
            hit = True
        out[i] = u
        last[i] = u
    flags[_F_LIMITED] = 1.0 if hit else 0.0
    if hit:
        flags[_F_CLAMPED] += 1.0
    if at_clamp:
        flags[_F_SATRUN] += 1.0
        if flags[_F_SATRUN] >= lim[_L_SAT]:
            return LIMIT_LATCHED
    else:
        flags[_F_SATRUN] = 0.0
    return 0


class SensorCheck:
    """Builder of the sensor check: limits from [safety], the named state's initial values, the fault texts."""

    def __init__(self, cfg: Config, n_mounts: int, names: tuple[str, ...] | None = None) -> None:
        s = cfg.safety
        self.n = n_mounts
        self.names = names or mount_names(n_mounts)
        self.accel_range = s.accel_range_mps2
        self.stroke_range = s.stroke_range_m
        self.stroke_limit = s.stroke_limit_m
        self.stale_ns = int(round(s.stale_s * 1e9))
        self.stuck_n = s.stuck_samples
        self.x_bound = min(self.stroke_range, self.stroke_limit)   # one test in the common case

    def limits(self) -> tuple:
        return (self.accel_range, self.x_bound, float(self.stale_ns), float(self.stuck_n))

    def initial_state(self) -> np.ndarray:
        st = np.zeros((len(CHECK_STATE), self.n))
        st[_C_TS:_C_X + 1] = math.nan            # no sample seen yet
        return st

    def reason(self, code: int, state, acc, xs, ts, t_ns: int) -> str:
        """The one-line fault text of a check code (state: the check's state after the check)."""
        i = code % 100
        if code - i == CHECK_STUCK_ACCEL:
            return f"{self.names[i]}: accelerometer stuck at {acc[i]!r} m/s^2 for {int(state[_C_SA, i])} samples"
        if code - i == CHECK_STUCK_STROKE:
            return (f"{self.names[i]}: displacement transducer stuck at {xs[i]!r} m "
                    f"for {int(state[_C_SX, i])} samples")
        a, x = acc[i], xs[i]
        ar, xr, xl = self.accel_range, self.stroke_range, self.stroke_limit
        if not (-ar <= a <= ar):
            return f"{self.names[i]}: accelerometer implausible: {a!r} m/s^2 (NaN or outside +-{ar:g} m/s^2)"
        if not (-xr <= x <= xr):
            return (f"{self.names[i]}: displacement transducer implausible: {x!r} m "
                    f"(NaN or outside +-{xr:g} m)")
        if not (-xl <= x <= xl):
            return f"{self.names[i]}: stroke limit: {x * 1e3:.4f} mm beyond +-{xl * 1e3:g} mm"
        age = t_ns - ts[i]
        return f"{self.names[i]}: stale sample: {age / 1e6:.3f} ms old (limit {self.stale_ns / 1e6:g} ms)"


def floor_reason(code: int, names, floor, range_mps2: float) -> str:
    """The one-line fault text of a check_floor code."""
    i = code - CHECK_FLOOR
    return (f"{names[i]}: floor accelerometer implausible: {floor[i]!r} m/s^2 (NaN or outside "
            f"+-{range_mps2:g} m/s^2, [sensors] floor_range_mps2)")


class CommandLimiter:
    """Builder of the command limits: clamp +-valve_limit_V, slew slew_V_per_s, latched saturation after
    saturation_s. Starting (and re-activating) from the null written while inactive means activation ramps,
    never jumps. The state (last command per mount, LIMITER_FLAGS) is the kernel's; `view` reads it."""

    def __init__(self, cfg: Config, n_mounts: int, dt: float) -> None:
        self.n = n_mounts
        self.max_V = cfg.safety.valve_limit_V
        self.step_V = cfg.safety.slew_V_per_s * dt
        self.sat_limit = max(1, int(round(cfg.safety.saturation_s / dt)))
        self._last = self._flags = None

    def limits(self) -> tuple:
        return (self.max_V, self.step_V, float(self.sat_limit))

    def view(self, last: np.ndarray, flags: np.ndarray) -> "CommandLimiter":
        """Read the state at these arrays (the kernel's) from now on."""
        self._last, self._flags = last, flags
        return self

    last = property(lambda self: self._last.tolist())
    sat_run = property(lambda self: int(self._flags[_F_SATRUN]))
    clamped = property(lambda self: int(self._flags[_F_CLAMPED]))
    limited = property(lambda self: bool(self._flags[_F_LIMITED]))

    def reason(self, code: int) -> str:
        if code == LIMIT_LATCHED:
            return (f"valve command at the +-{self.max_V:g} V clamp for {self.sat_run} periods: "
                    f"the loop is not in control")
        return f"controller {code - LIMIT_NAN}: valve command is NaN"


class Watchdog:
    """A thread that sends the valve to null when the loop has not kicked it for timeout_s (a hung
    controller or driver call). It trips once; the loop sees `tripped` and enters FAULT.
    Real clock only: in simulated time the loop's own gap check does this job."""

    def __init__(self, timeout_s: float, on_trip) -> None:
        self.timeout_s = timeout_s
        self._on_trip = on_trip
        self.beat = 0
        self.tripped: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rig-watchdog", daemon=True)

    def start(self) -> "Watchdog":
        self._thread.start()
        return self

    def kick(self) -> None:
        self.beat += 1

    def _run(self) -> None:
        last_beat = self.beat
        last_change = time.monotonic()
        poll = max(self.timeout_s / 4, 0.001)
        while not self._stop.wait(poll):
            b = self.beat
            now = time.monotonic()
            if b == 0:                      # armed by the first period, not during set-up
                last_change = now
            elif b != last_beat:
                last_beat, last_change = b, now
            elif now - last_change > self.timeout_s and self.tripped is None:
                self.tripped = f"watchdog: loop silent for {(now - last_change) * 1e3:.1f} ms " \
                               f"(limit watchdog_s = {self.timeout_s * 1e3:g} ms)"
                try:
                    self._on_trip()
                except Exception as e:   # the valve call failed: say so, the loop faults anyway
                    log.error("watchdog: safe_state failed: %s", e)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)

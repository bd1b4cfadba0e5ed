"""Safety rules run inside the period: sensor plausibility (`check_sensors`) and command limits
(`limit_commands`), compiled (numba) and called by the period kernel (rig/runtime/kernel.py); plus a watchdog thread
that sends the valve to null if the loop itself stops.

SensorCheck, CommandLimiter and OscillationRule are the rules' builders: their limits from the config, their
named state (initial values; the kernel owns the memory), and the one-line fault texts (off the hot path). A
rule returns 0 or a code that names the rule and the mount (CHECK_* + mount, LIMIT_NAN + mount,
LIMIT_LATCHED, LIMIT_OSC + mount).

The oscillation rule (`check_oscillation`) catches a limit cycle in the valve command: the latched-saturation
limit needs saturation_s of *continuous* clamping, and the controllers' own saturation recovery suspends
isolation after sat_reset_s of it, but an unstable loop (a gain far too high, a notch near Nyquist) cycles
through the clamp at a few hundred Hz and is never held there. A swing is the limited command passing from
beyond +level to beyond -level or back (level = oscillation_level of the clamp: the command's energy is near
the clamp); swings at oscillation_hz or faster over oscillation_window_s are a FAULT, not a suspension: the
cycle comes from the loop itself (its design or its gains), so resuming would only start it again, and the
operator has to change the configuration. The floor's band (1-50 Hz) moves the command far less than the clamp
(README: command rms about 1 V); open-loop playback (a chirp) is not checked.
"""
from __future__ import annotations

import logging
import math
import threading
import time

import numba
import numpy as np

from rig.config import Config, mount_names
from rig.runtime.rt import raise_priority

log = logging.getLogger("rig.safety")

CHECK_IMPLAUSIBLE, CHECK_STUCK_ACCEL, CHECK_STUCK_STROKE = 100, 200, 300
LIMIT_NAN, LIMIT_LATCHED, LIMIT_OSC = 400, 500, 600
CHECK_FLOOR = 900                     # + mount: a floor accelerometer NaN or out of its range

# Named limits (one float64 array, the kernel's): the check's, the limiter's, the oscillation rule's
LIMITS = ("accel_range_mps2", "stroke_bound_m", "stale_ns", "stuck_n", "max_V", "step_V", "sat_n",
          "osc_level_V", "osc_window_ns", "osc_swings")
_L_AR, _L_XB, _L_STALE, _L_STUCK, _L_MAX, _L_STEP, _L_SAT, _L_OSC_LEVEL, _L_OSC_WIN, _L_OSC_N = range(10)
# Named state of the check (rows of a (5, n) array) and of the limiter (last command per mount, then flags)
CHECK_STATE = ("last_sample_t_ns", "last_accel_mps2", "last_stroke_m", "same_accel_count", "same_stroke_count",
               "last_stroke_t_ns")
_C_TS, _C_A, _C_X, _C_SA, _C_SX, _C_XTS = range(6)
LIMITER_FLAGS = ("sat_run", "clamped", "limited")
_F_SATRUN, _F_CLAMPED, _F_LIMITED = range(3)
# Named state of the oscillation rule, per mount (a row of (n, len(OSC_STATE) + osc_swings)): whether the rule
# checks this mount, the side of the last excursion beyond the level (-1, 0, +1), the next slot of the ring
# of swing times that follows
OSC_STATE = ("checked", "side", "next")
_O_ON, _O_SIDE, _O_NEXT = range(3)
_NO_SWING = -1e30          # an empty slot of the ring: no swing ever


@numba.njit(cache=True)
def check_sensors(cs, lim, acc, xs, ts, xts, t_ns):
    """Plausibility of one period's measurement, mount by mount: NaN/inf, out of sensor range, beyond the
    stroke limit, stale (the accelerometer's time stamp older than stale_s at the loop time), stuck (the same
    value over stuck_n NEW samples: the time stamp moved on but the value did not; a held sample is caught as
    stale instead). The transducer's samples have their own time stamps xts (a transducer slower than the
    loop is held between its frames: only its new samples count). 0 or a code. Time stamps are float64: exact
    below 2**53 ns (104 days of monotonic time)."""
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
        if xts[i] != cs[_C_XTS, i]:                                       # a new transducer sample
            cs[_C_XTS, i] = xts[i]
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


@numba.njit(cache=True)
def check_oscillation(osc, lim, cmd, t_ns):
    """Limit cycle in the limited commands `cmd` of this period: per checked mount, a swing is a change of
    side beyond +-osc_level_V; osc_swings of them within osc_window_ns is a cycle at osc_swings / (2 window)
    or faster. 0 or LIMIT_OSC + mount. Nothing to do in a period without a swing but two compares."""
    level = lim[_L_OSC_LEVEL]
    nsw = int(lim[_L_OSC_N])
    for i in range(cmd.shape[0]):
        if osc[i, _O_ON] == 0.0:
            continue
        u = cmd[i]
        if u >= level:
            side = 1.0
        elif u <= -level:
            side = -1.0
        else:
            continue
        prev = osc[i, _O_SIDE]
        if side == prev:
            continue
        osc[i, _O_SIDE] = side
        if prev == 0.0:                  # the first excursion is not a swing
            continue
        k = int(osc[i, _O_NEXT])
        j = len(OSC_STATE) + k
        oldest = osc[i, j]               # the swing nsw swings before this one
        osc[i, j] = t_ns
        osc[i, _O_NEXT] = (k + 1) % nsw
        if t_ns - oldest <= lim[_L_OSC_WIN]:
            return LIMIT_OSC + i
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
        st[_C_XTS] = math.nan
        return st

    def reason(self, code: int, state, acc, xs, ts, t_ns: int) -> str:
        """The one-line fault text of a check code (state: the check's state after the check)."""
        i = code % 100
        if code - i == CHECK_STUCK_ACCEL:
            return f"{self.names[i]}: accelerometer stuck at {accel_text(acc[i])} for {int(state[_C_SA, i])} samples"
        if code - i == CHECK_STUCK_STROKE:
            return (f"{self.names[i]}: displacement transducer stuck at {length_text(xs[i])} "
                    f"for {int(state[_C_SX, i])} samples")
        a, x = acc[i], xs[i]
        ar, xr, xl = self.accel_range, self.stroke_range, self.stroke_limit
        if not (-ar <= a <= ar):
            return f"{self.names[i]}: accelerometer implausible: {accel_text(a)} (NaN or outside +-{ar:g} m/s^2)"
        if not (-xr <= x <= xr):
            return (f"{self.names[i]}: displacement transducer implausible: {length_text(x)} "
                    f"(NaN or outside +-{xr * 1e3:g} mm)")
        if not (-xl <= x <= xl):
            return f"{self.names[i]}: stroke limit: {x * 1e3:.4f} mm beyond +-{xl * 1e3:g} mm"
        age = t_ns - ts[i]
        return f"{self.names[i]}: stale sample: {age / 1e6:.3f} ms old (limit {self.stale_ns / 1e6:g} ms)"


def accel_text(a: float) -> str:
    """An acceleration in a fault text: four significant digits and the unit."""
    return f"{a:.4g} m/s^2"


def length_text(x: float) -> str:
    """A transducer reading in a fault text: four significant digits in mm (the stroke limit's unit)."""
    return f"{x * 1e3:.4g} mm"


def floor_reason(code: int, names, floor, range_mps2: float) -> str:
    """The one-line fault text of a check_floor code."""
    i = code - CHECK_FLOOR
    return (f"{names[i]}: floor accelerometer implausible: {accel_text(floor[i])} (NaN or outside "
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


class OscillationRule:
    """Builder of the oscillation rule: level, window and swing count from [safety], the per-mount state
    (`checked` for the feedback kinds only: open-loop playback is exempt) and the fault text."""

    def __init__(self, cfg: Config, n_mounts: int, names: tuple[str, ...] | None = None) -> None:
        s = cfg.safety
        self.n = n_mounts
        self.names = names or mount_names(n_mounts)
        self.level_V = s.oscillation_level * s.valve_limit_V
        self.window_s = s.oscillation_window_s
        self.min_hz = s.oscillation_hz
        self.swings = max(2, math.ceil(2 * s.oscillation_hz * s.oscillation_window_s - 1e-9))

    @property
    def width(self) -> int:
        """Columns of one mount's row of state."""
        return len(OSC_STATE) + self.swings

    def limits(self) -> tuple:
        return (self.level_V, self.window_s * 1e9, float(self.swings))

    def initial_state(self, checked) -> np.ndarray:
        """The state with no swing seen; checked: per mount, whether the rule applies to it."""
        st = np.full((self.n, self.width), _NO_SWING)
        st[:, _O_ON] = [1.0 if c else 0.0 for c in checked]
        st[:, _O_SIDE] = 0.0
        st[:, _O_NEXT] = 0.0
        return st

    def reason(self, code: int, state) -> str:
        i = code - LIMIT_OSC
        ring = state[i, len(OSC_STATE):]
        newest = ring[(int(state[i, _O_NEXT]) - 1) % self.swings]
        oldest = ring[int(state[i, _O_NEXT])]          # swings - 1 swings before the newest
        span_s = (newest - oldest) * 1e-9 if oldest > _NO_SWING else math.nan
        f = (self.swings - 1) / (2 * span_s) if span_s > 0 else math.nan
        return (f"{self.names[i]}: valve command oscillating at about {f:.0f} Hz between +-{self.level_V:g} V "
                f"({self.swings} swings within {self.window_s * 1e3:g} ms; limit oscillation_hz = "
                f"{self.min_hz:g} Hz): the loop is unstable, valves to null")


class Watchdog:
    """A thread that sends the valve to null when the loop has not kicked it for timeout_s (a hung
    controller or driver call). It trips once; the loop sees `tripped` and enters FAULT.
    Real clock only: in simulated time the loop's own gap check does this job.
    With `priority` (real-time runs: above the loop) it runs at SCHED_FIFO: at normal priority on a busy
    machine it waited 150 ms for a CPU while a 50 ms limit was long past."""

    def __init__(self, timeout_s: float, on_trip, priority: int = 0) -> None:
        self.timeout_s = timeout_s
        self.priority = priority
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
        raise_priority(self.priority)
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

"""Pure-Python references of the safety rules (the runtime's are rig/runtime/safety.py's compiled check_sensors and
limit_commands): the first versions, kept so property tests can hold the compiled rules against them."""
from __future__ import annotations

from rig.config import Config
from rig.runtime.safety import SensorCheck, accel_text, length_text


class RefSensorCheck(SensorCheck):
    """Plausibility of one Measurements per period. `check` returns None or a one-line fault reason.

    NaN/inf, out of sensor range, stroke beyond the stroke limit, stale (sample time stamp older than
    stale_s at the loop time), stuck (the same value over stuck_samples NEW samples, i.e. the time stamp
    moved on but the value did not; a held sample is caught as stale instead), device fault.
    """

    def __init__(self, cfg: Config, n_mounts: int, names: tuple[str, ...] | None = None) -> None:
        super().__init__(cfg, n_mounts, names)        # the limits from [safety], as the runtime's builder reads them
        self._x_bound = self.x_bound
        self.reset()

    def reset(self) -> None:
        n = self.n
        self._last_ts = [None] * n
        self._last_a = [float("nan")] * n
        self._last_x = [float("nan")] * n
        self._same_a = [0] * n
        self._same_x = [0] * n
        self._last_xts = [None] * n

    def check(self, m, t_ns: int, xts=None) -> str | None:
        """xts: the transducer's own time stamps (default the accelerometers': a Measurements has one)."""
        if m.device_fault:
            return f"device fault: {m.device_fault}"
        acc, xs, ts = m.accel_mps2, m.stroke_m, m.sample_t_ns
        xts = ts if xts is None else xts
        ar = self.accel_range
        xb = self._x_bound                      # min(stroke range, stroke limit): one test in the common case
        oldest = t_ns - self.stale_ns
        last_ts = self._last_ts
        for i in range(self.n):
            a = acc[i]
            x = xs[i]
            tsi = ts[i]
            if not (-ar <= a <= ar and -xb <= x <= xb and tsi >= oldest):   # also false for NaN
                return self._reason(i, a, x, tsi, t_ns)
            if tsi != last_ts[i]:               # a new sample: stuck check
                last_ts[i] = tsi
                if a == self._last_a[i]:
                    self._same_a[i] += 1
                    if self._same_a[i] >= self.stuck_n:
                        return (f"{self.names[i]}: accelerometer stuck at {accel_text(a)} "
                                f"for {self._same_a[i]} samples")
                else:
                    self._same_a[i] = 0
                    self._last_a[i] = a
            if xts[i] != self._last_xts[i]:     # a new transducer sample
                self._last_xts[i] = xts[i]
                if x == self._last_x[i]:
                    self._same_x[i] += 1
                    if self._same_x[i] >= self.stuck_n:
                        return (f"{self.names[i]}: displacement transducer stuck at {length_text(x)} "
                                f"for {self._same_x[i]} samples")
                else:
                    self._same_x[i] = 0
                    self._last_x[i] = x
        return None

    def _reason(self, i: int, a: float, x: float, tsi: int, t_ns: int) -> str:
        """The fault text of mount i, in the order of the checks (off the hot path)."""
        ar, xr, xl = self.accel_range, self.stroke_range, self.stroke_limit
        if not (-ar <= a <= ar):
            return (f"{self.names[i]}: accelerometer implausible: {accel_text(a)} "
                    f"(NaN or outside +-{ar:g} m/s^2)")
        if not (-xr <= x <= xr):
            return (f"{self.names[i]}: displacement transducer implausible: {length_text(x)} "
                    f"(NaN or outside +-{xr * 1e3:g} mm)")
        if not (-xl <= x <= xl):
            return f"{self.names[i]}: stroke limit: {x * 1e3:.4f} mm beyond +-{xl * 1e3:g} mm"
        age = t_ns - tsi
        return (f"{self.names[i]}: stale sample: {age / 1e6:.3f} ms old "
                f"(limit {self.stale_ns / 1e6:g} ms)")


class RefCommandLimiter:
    """Valve command clamp (+-valve_limit_V) and slew limit (slew_V_per_s), from the last written command.

    Starting (and re-activating) from the null written while inactive means activation ramps, never jumps.
    `limit` writes the limited commands into `out` and returns None, or a fault reason: a NaN command, or a
    command held at the clamp for saturation_s (the loop is no longer in control: a latched saturation).
    """

    def __init__(self, cfg: Config, n_mounts: int, dt: float) -> None:
        self.n = n_mounts
        self.max_V = cfg.safety.valve_limit_V
        self.step_V = cfg.safety.slew_V_per_s * dt
        self.sat_limit = max(1, int(round(cfg.safety.saturation_s / dt)))
        self.sat_run = 0          # consecutive periods with some command at the clamp
        self.last = [0.0] * n_mounts
        self.clamped = 0          # periods in which some command was clamped or slew-limited
        self.limited = False

    def reset(self) -> None:
        """The valve is at null (written while inactive, or safe state)."""
        for i in range(self.n):
            self.last[i] = 0.0
        self.sat_run = 0

    def limit(self, raw: list, out: list) -> str | None:
        mx = self.max_V
        st = self.step_V
        last = self.last
        hit = False
        at_clamp = False
        for i in range(self.n):
            u = raw[i]
            if u != u:
                return f"controller {i}: valve command is NaN"
            if u >= mx:
                u = mx
                hit = at_clamp = True
            elif u <= -mx:
                u = -mx
                hit = at_clamp = True
            p = last[i]
            if u - p > st:
                u = p + st
                hit = True
            elif p - u > st:
                u = p - st
                hit = True
            out[i] = u
            last[i] = u
        self.limited = hit
        if hit:
            self.clamped += 1
        if at_clamp:
            self.sat_run += 1
            if self.sat_run >= self.sat_limit:
                return (f"valve command at the +-{mx:g} V clamp for {self.sat_run} periods: "
                        f"the loop is not in control")
        else:
            self.sat_run = 0
        return None


class RefOscillation:
    """Limit cycle in the valve command: per checked mount, a swing is the command passing from beyond
    +level to beyond -level or back; `swings` swings within `window_ns` are a cycle (a fault naming the
    mount). The first excursion beyond the level is not a swing."""

    def __init__(self, level_V: float, window_ns: float, swings: int, checked) -> None:
        self.level, self.window, self.swings = level_V, window_ns, swings
        self.checked = list(checked)
        self.reset()

    def reset(self) -> None:
        n = len(self.checked)
        self.side = [0] * n
        self.times = [[] for _ in range(n)]         # the swing times of each mount, newest last

    def check(self, cmd, t_ns) -> int | None:
        """None, or the index of the mount that cycles."""
        for i, u in enumerate(cmd):
            if not self.checked[i]:
                continue
            side = 1 if u >= self.level else -1 if u <= -self.level else 0
            if side == 0 or side == self.side[i]:
                continue
            first = self.side[i] == 0
            self.side[i] = side
            if first:
                continue
            self.times[i].append(t_ns)
            if len(self.times[i]) > self.swings and t_ns - self.times[i][-1 - self.swings] <= self.window:
                return i
        return None

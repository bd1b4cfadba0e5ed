"""The simulated backend behind rig.port.Port (SIL), with fault knobs.

`read(t_ns)` advances the plant, one loop period per plant step with the last written command held (ZOH),
up to t_ns, then returns the sensors. The same code runs in lockstep with simulated time (SimClock: the loop
jumps from deadline to deadline) and in real time (MonotonicClock: the plant keeps pace with the wall
clock; a late loop makes the plant take several steps with the held command, as the real rig would).

Plants (any object with these):
  .step(valve_cmd_V: list[float])  one loop period with the command held
  .accel_mps2, .stroke_m           sensor values after the step (lists, one per mount; new list objects
                                   every step, never edited in place: read() hands them on without a copy)
  .floor_sensors, .floor_accel_mps2 optional: the floor accelerometers ([sensors] floor_accel)
Four mounts: sim_backend.rig_plant.RigPlant. Actuators alone on their stands (the `stand` layout, one mount
the prototype): sim_backend.actuator.StandBank. One stand for a chirp: StandPlant wrapped by `StandAdapter`
(n_mounts = 1; stroke_m is the stand's position_m).

Fault knobs (`inject`), each from time at_s on (ns resolution), per mount:
  drop     the sample is no longer refreshed: values and time stamp held        -> stale
  stale    time stamps lag by age_s (a driver delivering old samples)           -> stale
  nan      the sensor ("accel", "stroke" or "floor") reads NaN                 -> implausible
  stuck    the sensor value freezes while the time stamp stays fresh           -> stuck
  range    the sensor reads `value` (default far outside the range)            -> implausible
  device   the backend reports a device fault text                             -> device fault
  overrun  read() costs extra_s more (once; every period with `every=True`)     -> overrun / watchdog
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from rig.errors import RigError
from rig.port import Commands, Measurements, PortContext
from rig.config import layout_mounts
from sim_backend.actuator import Effects, StandBank, StandPlant
from sim_backend.linear import ActuatorParams
from sim_backend.rig_plant import FloorMotion, RigPlant

KINDS = ("drop", "stale", "nan", "stuck", "range", "device", "overrun")
_NO_SPOOL = ()                 # Measurements.spool_actual of the simulated backend: no spool feedback
_NO_FLOOR: list = []           # Measurements.floor_accel_mps2 without floor sensors (never written to)


@dataclass
class _Fault:
    kind: str
    mount: int
    at_ns: int
    sensor: str = "accel"
    age_ns: int = 10_000_000
    value: float = 1e3
    extra_ns: int = 0
    every: bool = False
    text: str = ""
    fired: bool = False
    held: tuple | None = None


class StandAdapter:
    """One actuator on its test stand as a one-mount plant: stroke_m <- position_m."""

    def __init__(self, stand) -> None:
        self.stand = stand
        self.accel_mps2 = [float(getattr(stand, "accel_mps2", 0.0))]
        self.stroke_m = [float(getattr(stand, "position_m", 0.0))]

    def step(self, valve_cmd_V) -> None:
        pos, acc = self.stand.step(float(valve_cmd_V[0]))
        self.accel_mps2 = [float(acc)]          # fresh lists every step (the backend does not copy them)
        self.stroke_m = [float(pos)]


class SimBackend(PortContext):
    """Port over a stepped plant. dt is the loop period (one plant step); noise is added here (seeded,
    Gaussian, rms accel_noise_mps2 / stroke_noise_m) unless set to 0: real sensors are never bit-exact
    constant, and the stuck check relies on that."""

    name = "sim"

    def __init__(self, plant, dt: float, *, n_mounts: int | None = None, clock=None, seed: int = 0,
                 accel_noise_mps2: float = 1e-4, stroke_noise_m: float = 2e-9,
                 cmd_delay_periods: int = 0, sample_driven: bool = False) -> None:
        self.plant = plant
        self.dt = float(dt)
        self.dt_ns = int(round(dt * 1e9))
        self.n_mounts = int(n_mounts if n_mounts is not None else len(plant.accel_mps2))
        self.floor_sensors = bool(getattr(plant, "floor_sensors", False))
        self.clock = clock
        self.cmd_delay_periods = int(cmd_delay_periods)
        n = self.n_mounts
        self._cmd = [0.0] * n
        self._pipe = [[0.0] * n for _ in range(self.cmd_delay_periods)]
        self._t0_ns: int | None = None
        self._k = 0                               # plant steps taken
        self._k_read = 0                          # plant step of the last read
        self._older: list = []                    # accelerations of steps not read (sample-driven)
        self._faults: list[_Fault] = []
        rng = np.random.default_rng(seed)
        self._noise_len = 65521                  # prime: the table does not line up with the period
        self._na = (accel_noise_mps2 * rng.standard_normal(self._noise_len)).tolist()
        self._nx = (stroke_noise_m * rng.standard_normal(self._noise_len)).tolist()
        self._ni = 0
        self._noiseless = accel_noise_mps2 == 0.0 and stroke_noise_m == 0.0   # the rig plant adds its own
        # sample-driven (like the FIFO accelerometer module, drivers/port.py): every plant step is a conversion,
        # and a read after skipped periods hands over the ones in between, so the controllers' integration of
        # acceleration sees them all (Measurements.new_samples / accel_older); noiseless plants only
        self.sample_driven = bool(sample_driven) and self._noiseless
        self._first_read = True
        self.opened = False
        self.safe_calls = 0
        self.writes = 0
        self.last_written = [0.0] * n           # what the valve(s) got last (null after safe_state)

    # ---- Port ---------------------------------------------------------------------------------------
    def open(self) -> None:
        self.opened = True

    def close(self) -> None:
        self.opened = False

    def safe_state(self) -> None:
        n = self.n_mounts
        self._cmd = [0.0] * n
        self._pipe = [[0.0] * n for _ in range(self.cmd_delay_periods)]
        self.last_written = [0.0] * n
        self.safe_calls += 1

    def write(self, t_ns: int, commands: Commands) -> None:
        c = list(commands.valve_cmd_V)
        if len(c) != self.n_mounts:
            raise RigError(f"sim backend: {len(c)} valve commands for {self.n_mounts} mounts")
        self._cmd = c
        self.last_written = c
        self.writes += 1

    def _step(self) -> None:
        """One plant period with the held command (delayed by cmd_delay_periods)."""
        plant = self.plant
        if self.sample_driven and self._k > self._k_read:      # a conversion the loop did not read
            self._older.append(plant.accel_mps2 + plant.floor_accel_mps2 if self.floor_sensors
                               else plant.accel_mps2)                    # (a fresh list either way)
        if self.cmd_delay_periods:
            self._pipe.append(self._cmd)
            plant.step(self._pipe.pop(0))
        else:
            plant.step(self._cmd)
        self._k += 1

    def read(self, t_ns: int) -> Measurements:
        if self._t0_ns is None:
            self._t0_ns = t_ns
        target = (t_ns - self._t0_ns) // self.dt_ns
        while self._k < target:
            self._step()
        plant = self.plant
        n = self.n_mounts
        acc = plant.accel_mps2
        xs = plant.stroke_m
        if self._noiseless:
            if self.sample_driven:
                new = self._k - self._k_read
                if self._first_read:
                    new += 1
                    self._first_read = False
                older = ()
                if self._older:
                    older = tuple(self._older)
                    self._older.clear()
            else:
                new, older = None, ()
            self._k_read = self._k
            fl = plant.floor_accel_mps2 if self.floor_sensors else _NO_FLOOR
            if not self._faults:
                # the plant publishes fresh lists every step: handed on without a copy
                return Measurements(t_ns, acc, xs, [t_ns] * n, _NO_SPOOL, None, new, older, fl)
            meas = Measurements(t_ns, list(acc), list(xs), [t_ns] * n, [], None, new, older, list(fl))
            self._apply_faults(t_ns, meas)             # (the knobs edit the lists in place)
            return meas
        self._k_read = self._k
        i = self._ni
        na, nx, L = self._na, self._nx, self._noise_len
        a_out = [0.0] * n
        x_out = [0.0] * n
        for m in range(n):
            j = (i + m) % L
            a_out[m] = float(acc[m]) + na[j]
            x_out[m] = float(xs[m]) + nx[j]
        self._ni = (i + n) % L
        meas = Measurements(t_ns=t_ns, accel_mps2=a_out, stroke_m=x_out, sample_t_ns=[t_ns] * n)
        if self._faults:
            self._apply_faults(t_ns, meas)
        return meas

    # ---- fault knobs --------------------------------------------------------------------------------
    def idle(self) -> None:
        """The loop's slack after a period (real clock): the plant takes the coming period's step now, with
        the command just written, as real hardware moves while the controller sleeps (read then finds it
        done; the sequence is the same as stepping in read), and draws its next block of floor motion and
        noise."""
        if self._t0_ns is not None and self._k == self._k_read:
            self._step()
        pre = getattr(self.plant, "prefetch", None)
        if pre is not None:
            pre()

    def inject(self, kind: str, *, mount: int = 0, at_s: float = 0.0, sensor: str = "accel",
               age_s: float = 0.01, value: float = 1e3, extra_s: float = 0.0, every: bool = False,
               text: str = "valve amplifier reports over-temperature") -> None:
        """Schedule a fault from loop time at_s (seconds after the first read)."""
        if kind not in KINDS:
            raise RigError(f"sim backend: unknown fault knob {kind!r} (expected one of {', '.join(KINDS)})")
        if not 0 <= mount < self.n_mounts:
            raise RigError(f"sim backend: fault knob mount {mount} outside 0..{self.n_mounts - 1}")
        if sensor not in ("accel", "stroke", "floor") or (sensor == "floor" and not self.floor_sensors):
            raise RigError(f"sim backend: fault knob sensor {sensor!r} (expected accel, stroke"
                           f"{', floor' if self.floor_sensors else ''})")
        self._faults.append(_Fault(kind, mount, int(round(at_s * 1e9)), sensor, int(round(age_s * 1e9)),
                                   float(value), int(round(extra_s * 1e9)), every, text))

    def clear_faults(self) -> None:
        self._faults.clear()

    def _apply_faults(self, t_ns: int, m: Measurements) -> None:
        rel = t_ns - (self._t0_ns or 0)
        for f in self._faults:
            if rel < f.at_ns:
                continue
            i = f.mount
            field = {"accel": m.accel_mps2, "stroke": m.stroke_m, "floor": m.floor_accel_mps2}[f.sensor]
            k = f.kind
            if k == "drop":
                if f.held is None:                         # the last delivered sample, before the drop
                    f.held = (m.accel_mps2[i], m.stroke_m[i], t_ns - self.dt_ns)
                m.accel_mps2[i], m.stroke_m[i], m.sample_t_ns[i] = f.held
            elif k == "stale":
                m.sample_t_ns[i] = t_ns - f.age_ns
            elif k == "nan":
                field[i] = math.nan
            elif k == "stuck":
                if f.held is None:
                    f.held = (field[i],)
                field[i] = f.held[0]
            elif k == "range":
                field[i] = f.value
            elif k == "device":
                m.device_fault = f"sim mount {i}: {f.text}"
            elif k == "overrun":
                if f.every or not f.fired:
                    f.fired = True
                    if self.clock is None:
                        raise RigError("sim backend: the overrun knob needs the loop's clock (clock=...)")
                    self.clock.spend(f.extra_ns)


def stand_bank(cfg, dt: float, *, n: int | None = None, effects: Effects | None = None, floor=True) -> StandBank:
    """The `stand` layout's plant: one actuator on its stand per mount ([layout] load_kg on each piston,
    the [stand] effects and sensor noise, seeds apart per stand), on a floor moving with [stand]
    base_motion_rms_m (band, spectrum and seed of [vibration]; floor=False: still, or a FloorMotion)."""
    n = len(layout_mounts(cfg)) if n is None else n
    p = ActuatorParams.from_config(cfg, loaded_mass_kg=cfg.actuator.M + cfg.layout.load_kg)
    fx = effects or Effects.from_config(cfg)
    if floor is True:
        v = cfg.vibration
        floor = (FloorMotion(dt, band_hz=(v.band_lo_hz, v.band_hi_hz), rms_m=fx.base_motion_rms_m, seed=v.seed,
                             spectrum=v.spectrum, n_mounts=n) if fx.base_motion_rms_m > 0 else None)
    return StandBank([StandPlant(p, replace(fx, seed=fx.seed + i), 1.0 / dt) for i in range(n)], floor or None)


def make_sim_port(cfg, dt: float, *, mode: str | None = None, clock=None, seed: int | None = None,
                  stand_params=None, stand_effects=None, floor=True, **kw) -> SimBackend:
    """The simulated backend for a config: mode "rig" (four mounts, RigPlant under the [vibration] floor
    motion; floor=False for none, or a FloorMotion), "stands" (the stand layout: StandBank, one actuator on
    its stand per mount, the floor of [stand] base_motion_rms_m, commands applied one period after they are
    written as in rig mode) or "stand" (one actuator, StandPlant, for a chirp); default: the [layout]'s.

    The plants add their own sensor noise, so the backend adds none unless asked (accel_noise_mps2=...,
    stroke_noise_m=...), except a 1e-10 m / 1e-6 m/s^2 floor on a noiseless stand (the stuck check).
    Rig mode applies each command one period after it is written (cmd_delay_periods=1), as the controller
    analysis assumes (ZOH plus one period of computation), and is sample-driven (every plant step reaches the
    controllers, also across skipped periods; sample_driven=False for a latest-value sensor); stand mode applies
    it at once, as
    simulate_stand does, so a chirp recording matches the stand model without an extra delay."""
    seed = cfg.vibration.seed if seed is None else seed
    if mode is None:
        mode = "rig" if cfg.layout.plant == "machine" else "stands"
    kw.setdefault("accel_noise_mps2", 0.0)
    kw.setdefault("stroke_noise_m", 0.0)
    if mode == "stands":
        plant = stand_bank(cfg, dt, effects=stand_effects, floor=floor)
        kw.setdefault("cmd_delay_periods", 1)
        if plant.stands[0].fx.position_noise_m == 0:
            kw["stroke_noise_m"] = kw["stroke_noise_m"] or 1e-10   # never bit-exact (stuck check)
        if plant.stands[0].fx.accel_noise_mps2 == 0:
            kw["accel_noise_mps2"] = kw["accel_noise_mps2"] or 1e-6
        return SimBackend(plant, dt, n_mounts=plant.n_mounts, clock=clock, seed=seed, **kw)
    if mode == "rig":
        if floor is True:
            floor = FloorMotion.from_config(cfg, dt)
        plant = RigPlant(cfg, dt, floor=floor or None, seed=seed)
        kw.setdefault("cmd_delay_periods", 1)
        kw.setdefault("sample_driven", True)
        return SimBackend(plant, dt, n_mounts=4, clock=clock, seed=seed, **kw)
    if mode == "stand":
        p = stand_params or ActuatorParams.from_config(cfg)
        fx = stand_effects or Effects()
        if not fx.position_noise_m:
            kw["stroke_noise_m"] = kw["stroke_noise_m"] or 1e-10   # never bit-exact (stuck check)
        if not fx.accel_noise_mps2:
            kw["accel_noise_mps2"] = kw["accel_noise_mps2"] or 1e-6
        plant = StandAdapter(StandPlant(p, fx, 1.0 / dt))
        return SimBackend(plant, dt, n_mounts=1, clock=clock, seed=seed, **kw)
    raise RigError(f"sim backend: mode {mode!r} (expected rig, stands or stand)")

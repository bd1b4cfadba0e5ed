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

from drivers.protocol.modbus_map import raw_to_volts, volts_to_raw
from rig.config import layout_mounts
from rig.errors import RigError
from rig.port import Commands, Measurements, PortContext
from rig.runtime.exchange import (A_COUNTED, A_NEWEST, A_SLOTS, C_ACK, C_SEQ, C_VALUES, H_ACAP, H_AWIDTH, H_SCAP,
                                  H_SWIDTH, S_NEWEST, S_SLOTS, S_STALE, Block, Layout, put_commands, put_step_entry,
                                  safe)
from sim_backend.actuator import Effects, StandBank, StandPlant
from sim_backend.linear import ActuatorParams
from sim_backend.rig_plant import FloorMotion, RigPlant

KINDS = ("drop", "stale", "nan", "stuck", "range", "device", "overrun")
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
    constant, and the stuck check relies on that.

    The loop reaches it through its exchange block (rig/runtime/exchange.py), as it reaches the drivers: every
    plant step publishes a conversion (sample-driven: counted, each one reaches the controllers; else the
    period's latest value) and the strokes, stamped with the loop time of the step (t0 + k dt: the deadline of
    the period that reads it); the kernel writes its commands there and the next step applies them.
    `update(t)` steps the plant up to the period at t (usually `idle` already did, in the slack before it);
    `read`/`write` are the same through the Port protocol, for callers of their own."""

    name = "sim"

    def __init__(self, plant, dt: float, *, n_mounts: int | None = None, clock=None, seed: int = 0,
                 accel_noise_mps2: float = 1e-4, stroke_noise_m: float = 2e-9,
                 cmd_delay_periods: int = 0, sample_driven: bool = False, stroke_stale_s: float = 0.0,
                 adc: tuple[float, float] | None = None, stroke_timing: tuple[int, int] = (0, 1)) -> None:
        self.plant = plant
        self.dt = float(dt)
        self.dt_ns = int(round(dt * 1e9))
        self.n_mounts = int(n_mounts if n_mounts is not None else len(plant.accel_mps2))
        self.floor_sensors = bool(getattr(plant, "floor_sensors", False))
        self.clock = clock
        self.cmd_delay_periods = int(cmd_delay_periods)
        n = self.n_mounts
        nf = n if self.floor_sensors else 0
        self._cmd = [0.0] * n
        self._pipe = [[0.0] * n for _ in range(self.cmd_delay_periods)]
        self._t0_ns: int | None = None
        self._k = 0                               # plant steps taken
        self._faults: list[_Fault] = []
        rng = np.random.default_rng(seed)
        self._noise_len = 65521                  # prime: the table does not line up with the period
        self._na = (accel_noise_mps2 * rng.standard_normal(self._noise_len)).tolist()
        self._nx = (stroke_noise_m * rng.standard_normal(self._noise_len)).tolist()
        self._ni = 0
        self._noiseless = accel_noise_mps2 == 0.0 and stroke_noise_m == 0.0   # the rig plant adds its own
        # sample-driven (like the FIFO accelerometer module, drivers/): every plant step is a conversion, and the
        # kernel takes the ones a late period did not see, so the controllers' integration of acceleration sees
        # them all; noiseless plants only
        self.sample_driven = bool(sample_driven) and self._noiseless
        self.exchange = Block.local(Layout(n, nf, devices=("sim",)))
        io = self._io = self.exchange.io
        self._a, self._c = self.exchange.part("accel"), self.exchange.part("cmd")
        io[self._a + A_COUNTED] = 1.0 if self.sample_driven else 0.0
        io[self.exchange.part("stroke") + S_STALE] = stroke_stale_s * 1e9
        self._safe = self.exchange.part("safe")
        self._n, self._nf = n, nf
        # adc: (accelerometer, floor accelerometer) V per m/s^2 through the analog module's 16-bit converter
        # (drivers/protocol/modbus_map.py), as the drivers read them; None: the plant's values as they are
        self._adc = adc
        self._vals, self._ts, self._xs = np.zeros(n + nf), np.zeros(n), np.zeros(n)   # what _publish hands over
        self._put = put_step_entry()                    # (the compiled rule's own entry: exactly these types)
        self._plain = self._noiseless and adc is None and stroke_timing[0] == 0 and stroke_timing[1] <= 1
        # stroke_timing: (delay, every): the transducer's sample taken every `every` plant steps and held between,
        # arriving `delay` steps after it was taken (the drivers' serial line: rig.config.channel_delays)
        self._x_delay, self._x_every = int(stroke_timing[0]), max(1, int(stroke_timing[1]))
        self._x_line: list = []                   # the strokes of the last steps, newest last
        self._x_held = None
        self._conv = -1                           # the last conversion published (its counter)
        self._pub = (-1, -1)                      # (plant step, time stamp) of the last published sample
        self._draw = None                         # (read, noise index) of a read's noise draw
        self._reads = 0                           # update() calls so far
        self._cmd_seq = 0.0                       # the commands' sequence last applied
        self._device = None                       # the device knob's text published
        self._seen = -1                           # read(): the last conversion handed over
        self.opened = False
        self.safe_calls = 0

    # ---- Port ---------------------------------------------------------------------------------------
    def open(self) -> None:
        self.opened = True

    def close(self) -> None:
        self.opened = False

    def safe_state(self) -> None:
        n = self.n_mounts
        self._cmd = [0.0] * n
        self._pipe = [[0.0] * n for _ in range(self.cmd_delay_periods)]
        self.safe_calls += 1
        safe(self.exchange)                        # null until the kernel writes again

    def write(self, t_ns: int, commands: Commands) -> None:
        c = list(commands.valve_cmd_V)
        if len(c) != self.n_mounts:
            raise RigError(f"sim backend: {len(c)} valve commands for {self.n_mounts} mounts")
        put_commands(self._io, float(t_ns), np.asarray(c, dtype=np.float64))

    def _take_commands(self) -> None:
        """The commands last written into the block (by the kernel, or write()) for the steps from now on."""
        io, c = self._io, self._c
        seq = io[c + C_SEQ]
        if seq != self._cmd_seq:
            self._cmd_seq = seq
            if io[self._safe] == io[c + C_ACK]:
                self._cmd = io[c + C_VALUES:c + C_VALUES + self._n].tolist()

    @property
    def writes(self) -> int:
        """Command sets written so far (by the kernel, or write())."""
        return int(self._io[self._c + C_SEQ]) // 2

    @property
    def last_written(self) -> list[float]:
        """What the valve(s) got last: the commands last written, null after safe_state until the next."""
        io, c = self._io, self._c
        if io[self._safe] != io[c + C_ACK]:
            return [0.0] * self._n
        return io[c + C_VALUES:c + C_VALUES + self._n].tolist()

    def _step(self) -> None:
        """One plant period with the held command (delayed by cmd_delay_periods); sample-driven, its conversion
        published (stamped with its loop time)."""
        self._take_commands()
        plant = self.plant
        if self.cmd_delay_periods:
            self._pipe.append(self._cmd)
            plant.step(self._pipe.pop(0))
        else:
            plant.step(self._cmd)
        self._k += 1
        if self.sample_driven:
            self._publish(self._t0_ns + self._k * self.dt_ns)

    def update(self, t_ns: int) -> None:
        """The plant up to the period at t_ns (the steps idle() did not take) and its samples published: what
        the period's kernel then takes from the block."""
        if self._t0_ns is None:
            self._t0_ns = t_ns
        self._reads += 1
        target = (t_ns - self._t0_ns) // self.dt_ns
        while self._k < target:
            self._step()
        if self._pub != (self._k, t_ns) or self._faults:
            self._publish(t_ns)
        for f in self._faults:
            if f.kind == "overrun" and t_ns - self._t0_ns >= f.at_ns and (f.every or not f.fired):
                f.fired = True
                if self.clock is None:
                    raise RigError("sim backend: the overrun knob needs the loop's clock (clock=...)")
                self.clock.spend(f.extra_ns)

    def _publish(self, t_ns: int, read: int | None = None) -> None:
        """The plant's sensors now as the period at t_ns reads them (the read-th update: one noise draw each,
        also when its sample is published twice), the fault knobs; a conversion (sample-driven: the step's
        own, counted) and the transducer's sample."""
        plant, n = self.plant, self._n
        acc, xs = plant.accel_mps2, plant.stroke_m
        if self._plain and not self._faults:         # the common case, without the knobs' work
            vals = self._vals
            vals[:n] = acc
            if self._nf:
                vals[n:] = plant.floor_accel_mps2
            self._xs[:] = xs
            self._ts.fill(t_ns)
            if not (self.sample_driven and self._pub[0] == self._k):
                self._conv += 1
            self._put(self._io, float(self._conv), self._ts, vals, float(self._k), float(t_ns), self._xs)
            self._pub = (self._k, t_ns)
            return
        fl = plant.floor_accel_mps2 if self._nf else _NO_FLOOR
        if not self._noiseless:
            read = self._reads if read is None else read
            if self._draw is None or self._draw[0] != read:        # one draw per read (a re-stamp reuses it)
                self._draw = (read, self._ni)
                self._ni = (self._ni + n) % self._noise_len
            i, na, nx, L = self._draw[1], self._na, self._nx, self._noise_len
            acc = [float(acc[m]) + na[(i + m) % L] for m in range(n)]
            xs = [float(xs[m]) + nx[(i + m) % L] for m in range(n)]
        ts = [t_ns] * n
        if self._x_delay or self._x_every > 1:
            xs = self._stroke_as_read(xs)
        if self._adc is not None:
            ka, kf = self._adc
            acc = [raw_to_volts(volts_to_raw(a * ka)) / ka for a in acc]
            fl = [raw_to_volts(volts_to_raw(g * kf)) / kf for g in fl]
        if self._faults:
            meas = Measurements(t_ns, list(acc), list(xs), ts, [], None, None, (), list(fl))
            self._apply_faults(t_ns, meas)             # (the knobs edit the lists in place)
            acc, xs, ts, fl = meas.accel_mps2, meas.stroke_m, meas.sample_t_ns, meas.floor_accel_mps2
            if meas.device_fault != self._device:
                self._device = meas.device_fault
                self.exchange.fault(0, 1 if meas.device_fault else 0, meas.device_fault or "")
        vals, a_ts, a_xs = self._vals, self._ts, self._xs
        vals[:n] = acc
        if self._nf:
            vals[n:] = fl
        a_ts[:] = ts
        a_xs[:] = xs
        if not (self.sample_driven and self._pub[0] == self._k):
            self._conv += 1                            # else the step's conversion again, re-stamped
        self._put(self._io, float(self._conv), a_ts, vals, float(self._k), float(max(ts)), a_xs)
        self._pub = (self._k, t_ns)

    def _stroke_as_read(self, xs):
        """The transducer's sample as the drivers deliver it (stroke_timing): taken at steps that are multiples
        of `every`, `delay` steps before it is read, held between."""
        line = self._x_line
        if not line or line[-1][0] != self._k:
            line.append((self._k, list(xs)))
            del line[:-self._x_delay - self._x_every - 1]
        want = self._k - self._x_delay
        taken = [x for k, x in line if k <= want and k % self._x_every == 0]
        if taken:
            self._x_held = taken[-1]
        return self._x_held if self._x_held is not None else line[0][1]

    def read(self, t_ns: int) -> Measurements:
        """The Port protocol's read (callers of their own; the loop takes the block): update, then the newest
        sample, and sample-driven the conversions since the last read."""
        self.update(t_ns)
        io, a, n, nf = self._io, self._a, self._n, self._nf
        cap, w = int(io[H_ACAP]), int(io[H_AWIDTH])
        newest = int(io[a + A_NEWEST])

        def conv(c):
            s = a + A_SLOTS + (c % cap) * w
            return io[s + 1:s + 1 + n].tolist(), io[s + 1 + n:s + 1 + 2 * n + nf].tolist()
        ts, vals = conv(newest)
        so = self.exchange.part("stroke")
        ss = so + S_SLOTS + (int(io[so + S_NEWEST]) % int(io[H_SCAP])) * int(io[H_SWIDTH])
        new, older = None, ()
        if self.sample_driven:
            new = newest - self._seen if self._seen >= 0 else 1
            older = tuple(tuple(conv(c)[1]) for c in range(max(self._seen + 1, newest - new + 1), newest))
        self._seen = newest
        return Measurements(t_ns, vals[:n], io[ss + 2:ss + 2 + n].tolist(), [int(t) for t in ts], [],
                            self._device, new, older, vals[n:])

    # ---- fault knobs --------------------------------------------------------------------------------
    def idle(self) -> None:
        """The loop's slack after a period (real clock): the plant takes the coming period's step now, with
        the command just written, as real hardware moves while the controller sleeps (update then finds it
        done; the sequence is the same as stepping in update), publishes what the coming period reads, and
        draws its next block of floor motion and noise."""
        if self._t0_ns is not None and self._k == self._pub[0]:
            self._step()
            if self._pub[0] != self._k:
                self._publish(self._t0_ns + self._k * self.dt_ns, self._reads + 1)
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
        if self._device is not None:
            self._device = None
            self.exchange.fault(0, 0, "")

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

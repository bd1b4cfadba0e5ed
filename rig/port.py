"""The one port every backend implements (drivers/ for hardware, sim_backend/ for the simulated plant).

The loop only ever sees this protocol: read -> check -> update -> limit -> write -> record. Values are plain
Python floats in fixed-size lists (index = mount, in `rig.config.MOUNTS` order) so the hot path stays cheap.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable


@dataclass(slots=True)
class Measurements:
    """One set of sensor values; all lists have one entry per mount."""
    t_ns: int                          # loop time of the read (monotonic clock, integer ns)
    accel_mps2: list[float]            # absolute vertical acceleration at the mount (low-frequency accelerometer)
    stroke_m: list[float]              # displacement transducer: piston relative to housing, + = extend
    sample_t_ns: list[int]             # time stamp of the newest device sample behind each mount's values
    spool_actual: list[float] = field(default_factory=list)  # valve-reported spool value, -1..1 (if available)
    device_fault: str | None = None    # a device reported a fault: one line naming the device and the reason
    # Sample-driven ports (a converter counting its conversions, one per period): how many conversions were
    # made since the last read (0 = none: the values are the previous ones again), and the accelerations of the
    # conversions before the newest, oldest first. None: one new sample per read (period-driven).
    new_samples: int | None = None
    accel_older: tuple = ()
    # Floor accelerometers (ports with floor_sensors = True: [sensors] floor_accel), one per mount, read with
    # the mount accelerometers (same conversion); the older conversions in accel_older then carry them too,
    # after the mount accelerations. Empty: no floor sensors.
    floor_accel_mps2: list[float] = field(default_factory=list)


@dataclass(slots=True)
class Commands:
    valve_cmd_V: list[float]           # valve amplifier command per mount, volts (0 = null)


class PortContext:
    """Ports are context managers: opened on entry, closed on exit (for ports used on their own; the loop
    opens its port at configure and the Session closes it)."""

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@runtime_checkable
class Port(Protocol):
    """What the loop needs from a backend. `open` may do slow configuration (SDO, register set-up);
    `read` and `write` run inside the control period and must not block on a bus request. Optional:
    `idle()`, work that does not depend on the period's data, which the loop runs after a period when at least
    half a period is left (the simulated plant draws its next block of floor motion there).
    Optional, the loop's fast path: `exchange`, the port's exchange block (rig/runtime/exchange.py), which the
    period's kernel reads and writes itself instead of calling read and write, with `update(t_ns)` (before
    the kernel) and `commit(t_ns)` (after it) if the port needs a step there. The drivers and the simulated
    backend have one; for a port without it the loop keeps one of its own (rig/runtime/measured.py)."""

    n_mounts: int
    name: str
    # optional: floor_sensors = True when read() fills Measurements.floor_accel_mps2 (the feedforward's input)

    def open(self) -> None: ...

    def read(self, t_ns: int) -> Measurements: ...

    def write(self, t_ns: int, commands: Commands) -> None: ...

    def safe_state(self) -> None:
        """Valve(s) to null: the actuator is then passive and stiff. Must be safe to call at any time."""

    def close(self) -> None: ...

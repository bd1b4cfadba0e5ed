"""The hardware port: CANopen valves + Modbus TCP accelerometers + serial displacement transducers as one
rig.port.Port. The same class drives the real rig ("hardware") and the emulated one ("hil").

Per period: read() sends the SYNC (valves apply the last setpoint and answer by TPDO) and picks up the
latest Modbus and serial samples kept by the driver threads; write() sends one RPDO per valve. Neither waits
on a bus request. Each device checks itself; the first fault found is returned as Measurements.device_fault,
one line naming the device.

Sample-driven (accelerometer module converting on SYNC into a conversion FIFO, `[drivers] accel_sync_fifo`):
the isolation controller double-integrates acceleration, so a sample that arrives a period late and is then
skipped, or a period without a new sample, is a velocity error that the integration keeps (on a loaded
machine Modbus replies come late in a few per cent of the periods, and a slip a second is enough to undo the
isolation; tests/rig/runtime/test_sample_driven.py). read() therefore reports
how many conversions the module made since the last read (Measurements.new_samples; 0 = none yet) and hands
over the ones before the newest (accel_older), so the loop steps the controllers once per conversion, in order.

Floor accelerometers (floor_sensors): the same module's further channels, after the mount accelerometers in
each sample and conversion; read() splits them off into Measurements.floor_accel_mps2 (the older conversions
keep them, after the mount values, as the kernel takes them).
"""
from __future__ import annotations

import time

from rig.port import Commands, Measurements, PortContext


class DriverPort(PortContext):
    transports = ("canopen", "modbus_tcp", "serial")

    def __init__(self, name: str, valves, accel, stroke, *, n_mounts: int = 4, on_close=None,
                 sample_driven: bool = False, floor_sensors: bool = False):
        self.name = name
        self.floor_sensors = bool(floor_sensors)
        self.sample_driven = sample_driven and getattr(accel, "fifo", False)
        self._last_conv = -1
        self.n_mounts = n_mounts
        self.valves = valves
        self.accel = accel
        self.stroke = stroke
        self._on_close = on_close
        self.opened = False

    def open(self) -> None:
        if self.opened:
            return
        opened = []
        try:
            for dev in (self.accel, self.stroke, self.valves):
                dev.open()
                opened.append(dev)
        except BaseException:
            for dev in reversed(opened):
                dev.close()
            raise
        self.opened = True

    def read(self, t_ns: int) -> Measurements:
        v = self.valves
        v.sync()
        self.accel.trigger()
        self.stroke.trigger()
        now = time.monotonic_ns()
        acc, ta, _raw = self.accel.sample
        pos, _tx, _st = self.stroke.sample
        fault = v.check(now) or self.accel.check(now) or self.stroke.check(now)
        # the time stamp is the accelerometer sample's (the control signal); the slower serial transducer
        # is checked for staleness by its own driver, against its own limit
        n = self.n_mounts
        fl = n if self.floor_sensors else 0
        if not self.sample_driven:
            return Measurements(t_ns=t_ns, accel_mps2=list(acc[:n]), stroke_m=list(pos), sample_t_ns=[ta] * n,
                                spool_actual=list(v.actual), device_fault=fault,
                                floor_accel_mps2=list(acc[n:n + fl]))
        new, self._last_conv, acc, older = self.accel.conversions_since(self._last_conv)
        return Measurements(t_ns=t_ns, accel_mps2=list(acc[:n]), stroke_m=list(pos), sample_t_ns=[ta] * n,
                            spool_actual=list(v.actual), device_fault=fault, new_samples=new,
                            accel_older=tuple(older), floor_accel_mps2=list(acc[n:n + fl]))

    def write(self, t_ns: int, commands: Commands) -> None:
        self.valves.write(commands.valve_cmd_V)

    def reset_faults(self) -> None:
        """Acknowledge valve faults (controlword R edge). Not part of the Port protocol: for operators/tests."""
        self.valves.reset_fault()

    def safe_state(self) -> None:
        self.valves.null()

    def close(self) -> None:
        try:
            if self.opened:
                try:
                    self.valves.null()
                except Exception:          # noqa: BLE001 - closing: best effort
                    pass
            for dev in (self.valves, self.accel, self.stroke):
                dev.close()
        finally:
            self.opened = False
            if self._on_close is not None:
                cb, self._on_close = self._on_close, None
                cb()

    def round_trips_us(self) -> dict[str, list[float]]:
        return {"canopen_sync_to_tpdo": self.valves.latencies_us(), "modbus_read": self.accel.latencies_us(),
                "serial_frame": self.stroke.latencies_us()}

"""Hardware I/O behind one port (rig.port.Port): CANopen valves, Modbus TCP accelerometers, serial displacement
transducers. Hardware libraries (canopen, pymodbus, pyserial) are imported only when a port is built.
Backends are chosen by name in rig/backends.py ("hardware": these drivers against the configured devices;
"hil": the same drivers against the emulated rig, sim_backend/emulators).

Device maps: drivers/devicemaps/ (valve408_canopen.md + valve408.eds, adam6024_modbus.md, dta4_serial.md);
the protocol maps the emulators share: drivers/protocol/.
"""
from __future__ import annotations

from drivers.port import DriverPort
from rig.config import layout_mounts
from rig.errors import ConfigError

MAX_MOUNTS = 4          # one 4-channel transducer amplifier (DTA-4), AI ch0-3 of the I/O module
# AI ch0-3 = the mount accelerometers, layout order; ch4-7: the floor accelerometers, [sensors] floor_channels


def build_driver_port(cfg, name: str, *, can_interface: str, can_channel: str, modbus_host: str,
                      modbus_port: int, serial_port: str, stale_s: float, serial_stale_s: float | None = None,
                      poll_s: float | None = None, on_close=None, priority: int | None = None,
                      sample_driven: bool | None = None):
    """The three drivers as one port for the layout's mounts (nothing is opened here; the hardware libraries
    load here). Mount i (rig.config.layout_mounts order): valve node valve_node_id_base + i, accelerometer AI
    ch i, transducer channel i + 1 (drivers/devicemaps/: the four-mount map in README.md, the prototype's
    in prototype.md). With floor accelerometers ([sensors] floor_accel) the analog module also reads
    [sensors] floor_channels, one per mount."""
    from drivers.canopen_valves import CanopenValves           # lazy: loads canopen and python-can
    from drivers.modbus_io import ModbusAnalogIO               # lazy: loads pymodbus
    from drivers.serial_dta import DisplacementAmplifier       # lazy: loads pyserial
    d = cfg.drivers
    names = list(layout_mounts(cfg))
    if len(names) > MAX_MOUNTS:
        raise ConfigError(f"{cfg.source}: layout.mounts: {len(names)} mounts; the drivers' devices carry at most "
                          f"{MAX_MOUNTS} (one DTA-4 amplifier, AI ch0-3)")
    prio = d.thread_priority if priority is None else priority
    fifo = d.accel_sync_fifo if sample_driven is None else sample_driven
    poll = poll_s if poll_s is not None else 1.0 / cfg.loop.rate_hz      # triggered each period by read()
    valves = CanopenValves(interface=can_interface, channel=can_channel, bitrate=d.can_bitrate,
                           node_ids=[d.valve_node_id_base + i for i in range(len(names))], names=names,
                           max_V=cfg.valve.max_V, stale_s=stale_s, priority=prio)
    s = cfg.sensors
    floor = list(s.floor_channels)[:len(names)] if s.floor_accel else []
    accel = ModbusAnalogIO(host=modbus_host, port=modbus_port, unit=d.modbus_unit,
                           channels=list(range(len(names))) + floor,
                           names=names + [f"floor {m}" for m in names][:len(floor)],
                           V_per_mps2=[d.accel_V_per_mps2] * len(names) + [s.floor_V_per_mps2] * len(floor),
                           timeout_s=d.modbus_timeout_s, watchdog_s=d.modbus_watchdog_s, stale_s=stale_s, poll_s=poll,
                           priority=prio, fifo=fifo)
    stroke = DisplacementAmplifier(port=serial_port, baud=d.serial_baud, names=names, channels=list(range(len(names))),
                                   stale_s=serial_stale_s if serial_stale_s is not None else stale_s, poll_s=poll,
                                   priority=prio)
    return DriverPort(name, valves, accel, stroke, n_mounts=len(names), on_close=on_close,
                      sample_driven=fifo, floor_sensors=bool(floor))

"""Hardware I/O behind one port (rig.port.Port): CANopen valves, Modbus TCP accelerometers, serial displacement
transducers, each in an I/O process of its own (drivers/process.py) that meets the loop in an exchange block
(rig/runtime/exchange.py). Hardware libraries (canopen, pymodbus, pyserial) load only in those processes.
Backends are chosen by name in rig/backends.py ("hardware": these drivers against the configured devices;
"hil": the same drivers against the emulated rig, sim_backend/emulators).

Device maps: drivers/devicemaps/ (valve408_canopen.md + valve408.eds, adam6024_modbus.md, dta4_serial.md);
the protocol maps the emulators share: drivers/protocol/.
"""
from __future__ import annotations

from pathlib import Path

from drivers import conversion
from drivers.port import ANALOG, DEVICES, TRANSDUCER, VALVES, DriverPort
from rig.config import layout_mounts
from rig.errors import ConfigError

MAX_MOUNTS = 4          # one 4-channel transducer amplifier (DTA-4), AI ch0-3 of the I/O module
# AI ch0-3 = the mount accelerometers, layout order; ch4-7: the floor accelerometers, [sensors] floor_channels
# (the calibration's [accel.*] and [floor.*] tables: drivers/conversion.py calibrated)


def calibration_path(cfg) -> Path:
    """[drivers] calibration, a relative path taken beside the configuration file."""
    p = Path(cfg.drivers.calibration)
    src = Path(cfg.source)
    return p if p.is_absolute() or not src.is_file() else src.parent / p


def accel_hold_s(d, period_s: float) -> float:
    """How long after its SYNC the module's I/O hands a conversion to the loop at the soonest, when the design
    takes it accel_delay_periods after its SYNC (2 or more): a quarter period after the loop's period before
    that one started (its wake-up and take done), so a fast reply is not taken a period early; 0 for 1."""
    if d.accel_delay_periods < 2:
        return 0.0
    return max(0.0, (d.accel_delay_periods - 1) * period_s - d.sync_offset_s + 0.25 * period_s)


def build_driver_port(cfg, name: str, *, can_interface: str, can_channel: str, modbus_host: str,
                      modbus_port: int, serial_port: str, stale_s: float, serial_stale_s: float | None = None,
                      on_close=None, priority: int | None = None, sample_driven: bool | None = None,
                      can_options: dict | None = None, silent_s: float | None = None,
                      period_s: float | None = None):
    """The three drivers as one port for the layout's mounts (nothing is opened here; the I/O processes start
    at open()). Mount i (rig.config.layout_mounts order): valve node valve_node_id_base + i, accelerometer AI
    ch i, transducer channel i + 1 (drivers/devicemaps/: the four-mount map in README.md, the prototype's in
    prototype.md). With floor accelerometers ([sensors] floor_accel) the analog module also reads [sensors]
    floor_channels, one per mount. can_options: further python-can arguments of the bus (a socketcand
    gateway's host and port, rig_stream's address); silent_s: how long an I/O process may go without reporting (default stale_s);
    period_s: the loop's period (default [loop] rate_hz's): the valves' SYNC and the module's fetch follow it."""
    d = cfg.drivers
    names = list(layout_mounts(cfg))
    n = len(names)
    if n > MAX_MOUNTS:
        raise ConfigError(f"{cfg.source}: layout.mounts: {n} mounts; the drivers' devices carry at most "
                          f"{MAX_MOUNTS} (one DTA-4 amplifier, AI ch0-3)")
    prio = d.thread_priority if priority is None else priority
    fifo = d.accel_sync_fifo if sample_driven is None else sample_driven
    period_s = 1.0 / cfg.loop.rate_hz if period_s is None else period_s
    s = cfg.sensors
    floor = list(s.floor_channels)[:n] if s.floor_accel else []
    x_stale = serial_stale_s if serial_stale_s is not None else stale_s
    silent = stale_s if silent_s is None else silent_s
    common = {"period_s": period_s, "priority": prio}
    valves = {"kind": "valves", "device": VALVES, "name": f"canopen {can_interface}:{can_channel} valves",
              "interface": can_interface, "channel": can_channel, "bus": dict(can_options or {}),
              "bitrate": d.can_bitrate, "node_ids": [d.valve_node_id_base + i for i in range(n)], "names": names,
              "max_V": cfg.valve.max_V, "stale_s": stale_s, "silent_s": silent, "sync_offset_s": d.sync_offset_s,
              "sync_wait_s": d.sync_wait_s, **common}
    v_chs = conversion.channels(range(n), [1.0] * n)
    accel = {"kind": "analog", "device": ANALOG, "name": f"modbus_tcp {modbus_host}:{modbus_port}",
             "host": modbus_host, "port": modbus_port, "unit": d.modbus_unit,
             "names": names + [f"floor {m}" for m in names][:len(floor)], "timeout_s": d.modbus_timeout_s,
             "watchdog_s": d.modbus_watchdog_s, "stale_s": stale_s, "silent_s": silent, "fifo": fifo,
             "fetch_every": d.accel_fetch_every, "fetch_delay_s": d.accel_fetch_delay_s, "sync_device": VALVES,
             "hold_s": accel_hold_s(d, period_s), "hold_periods": max(0, d.accel_delay_periods - 1), **common}
    a_chs = conversion.channels(list(range(n)) + floor,
                                [1.0 / d.accel_V_per_mps2] * n + [1.0 / s.floor_V_per_mps2] * len(floor))
    x_chs = conversion.channels(range(n), [1.0] * n)
    if d.calibration:
        cal = conversion.read_calibration(calibration_path(cfg))
        a_chs = (conversion.calibrated(a_chs[:n], cal, "accel", names, "mps2")
                 + (conversion.calibrated(a_chs[n:], cal, "floor", names, "mps2") if floor else ()))
        x_chs = conversion.calibrated(x_chs, cal, "stroke", names, "m")
        v_chs = conversion.calibrated_valves(v_chs, cal, names)
    valves["channels"] = conversion.to_dict(v_chs)
    accel["channels"] = conversion.to_dict(a_chs)
    stroke = {"kind": "transducer", "device": TRANSDUCER, "name": f"serial DTA-4 {serial_port}",
              "port": serial_port, "baud": d.serial_baud, "names": names,
              "channels": conversion.to_dict(x_chs),
              "stale_s": x_stale, "silent_s": max(silent, x_stale), "rate_hz": min(d.serial_rate_hz, 1.0 / period_s),
              "offset_s": d.serial_offset_s, **common}
    return DriverPort(name, [valves, accel, stroke], n_mounts=n, floor_sensors=bool(floor), counted=fifo,
                      stroke_stale_s=x_stale, on_close=on_close)

"""Hardware I/O behind one port (rig.port.Port), chosen by name; hardware libraries are imported lazily.

  make_port(cfg, "sim")       the simulated plant (sim_backend.backend), no hardware library is imported
  make_port(cfg, "hil")       the three real drivers against the emulated rig (sim_backend.emulators)
  make_port(cfg, "hardware")  the same drivers against the configured devices ([drivers] section)

Device maps: drivers/devicemaps/ (valve408_canopen.md + valve408.eds, adam6024_modbus.md, dta4_serial.md).
"""
from __future__ import annotations

import logging

from rig.config import MOUNTS
from rig.errors import RigError

BACKENDS = ("sim", "hil", "hardware")
ACCEL_CHANNELS = (0, 1, 2, 3)          # AI ch0-3 = accelerometers, MOUNTS order (ch4-5 spare)


def make_port(cfg, backend_name: str):
    """The port for a backend name. Construction touches no device; open() does the slow set-up."""
    if backend_name == "sim":
        from sim_backend.backend import make_sim_port
        from sim_backend.rig_plant import FloorMotion
        dt = 1.0 / cfg.loop.rate_hz
        return make_sim_port(cfg, dt, floor=_floor(cfg, dt, FloorMotion))
    if backend_name == "hil":
        return make_hil_port(cfg)
    if backend_name == "hardware":
        d = cfg.drivers
        return build_driver_port(cfg, "hardware", can_interface=d.can_interface, can_channel=d.can_channel,
                                 modbus_host=d.modbus_host, modbus_port=d.modbus_port,
                                 serial_port=d.serial_port, stale_s=d.stale_s, serial_stale_s=d.serial_stale_s)
    raise RigError(f"{cfg.source}: backend.name: expected one of {', '.join(BACKENDS)}, got {backend_name!r}")


def _floor(cfg, dt, FloorMotion):
    return FloorMotion.from_config(cfg, dt)          # the configured band, level, spectrum and seed


def build_driver_port(cfg, name: str, *, can_interface: str, can_channel: str, modbus_host: str,
                      modbus_port: int, serial_port: str, stale_s: float, serial_stale_s: float | None = None,
                      poll_s: float | None = None, on_close=None, priority: int | None = None,
                      sample_driven: bool | None = None):
    """The three drivers as one port (nothing is opened here)."""
    from drivers.canopen_valves import CanopenValves
    from drivers.modbus_io import ModbusAnalogIO
    from drivers.port import DriverPort
    from drivers.serial_dta import DisplacementAmplifier
    d = cfg.drivers
    names = list(MOUNTS)
    prio = d.thread_priority if priority is None else priority
    fifo = d.accel_sync_fifo if sample_driven is None else sample_driven
    poll = poll_s if poll_s is not None else 1.0 / cfg.loop.rate_hz      # triggered each period by read()
    valves = CanopenValves(interface=can_interface, channel=can_channel, bitrate=d.can_bitrate,
                           node_ids=[d.valve_node_id_base + i for i in range(len(names))], names=names,
                           max_V=cfg.valve.max_V, stale_s=stale_s, priority=prio)
    accel = ModbusAnalogIO(host=modbus_host, port=modbus_port, unit=d.modbus_unit, channels=list(ACCEL_CHANNELS),
                           names=names, V_per_mps2=d.accel_V_per_mps2, timeout_s=d.modbus_timeout_s,
                           watchdog_s=d.modbus_watchdog_s, stale_s=stale_s, poll_s=poll, priority=prio,
                           fifo=fifo)
    stroke = DisplacementAmplifier(port=serial_port, baud=d.serial_baud, names=names,
                                   stale_s=serial_stale_s if serial_stale_s is not None else stale_s, poll_s=poll,
                                   priority=prio)
    return DriverPort(name, valves, accel, stroke, n_mounts=len(names), on_close=on_close,
                      sample_driven=fifo)


def make_hil_port(cfg, plant=None, *, dt: float | None = None, stale_s: float | None = None,
                  serial_stale_s: float | None = None, poll_s: float | None = None, priority: int | None = None):
    """The drivers against a freshly started emulated rig (the port's `.rig`; stopped by port.close()).
    plant: default the four-mount RigPlant under the configured floor vibration, stepped at the loop period.
    The emulated module converts at each plant step (each SYNC), so the port is sample-driven."""
    from sim_backend.emulators.rig import EmulatedRig
    if dt is None and cfg.loop.rate_hz > cfg.hil.rate_hz:
        logging.getLogger("rig.drivers").warning(
            "hil: loop.rate_hz %g Hz is above hil.rate_hz %g Hz: expect overruns and late samples (the HIL "
            "configuration is drivers/devicemaps/hil.toml)", cfg.loop.rate_hz, cfg.hil.rate_hz)
    dt = dt if dt is not None else 1.0 / cfg.loop.rate_hz
    if plant is None:
        try:
            from sim_backend.rig_plant import FloorMotion, RigPlant
        except ImportError as e:
            raise RigError(f"hil: the rig plant (sim_backend/rig_plant.py) is not available ({e})") from None
        plant = RigPlant(cfg, dt, floor=_floor(cfg, dt, FloorMotion), seed=cfg.vibration.seed)
    d = cfg.drivers
    emu = EmulatedRig(plant, dt, max_V=cfg.valve.max_V, w_spool=cfg.valve.w_nv, accel_V_per_mps2=d.accel_V_per_mps2,
                      node_ids=[d.valve_node_id_base + i for i in range(len(MOUNTS))],
                      priority=cfg.hil.device_priority if priority is None else priority).start()
    try:
        port = build_driver_port(cfg, "hil", can_interface="virtual", can_channel=emu.channel,
                                 modbus_host="127.0.0.1", modbus_port=emu.modbus_port, serial_port=emu.serial_path,
                                 stale_s=stale_s if stale_s is not None else cfg.hil.stale_s,
                                 serial_stale_s=serial_stale_s if serial_stale_s is not None else
                                 (stale_s if stale_s is not None else cfg.hil.serial_stale_s), poll_s=poll_s,
                                 on_close=emu.stop, priority=priority, sample_driven=True)
    except BaseException:
        emu.stop()
        raise
    port.rig = emu
    return port

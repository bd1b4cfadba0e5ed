"""Backends by name, python-can style: one registry of name -> lazily imported factory.

  "sim"       the simulated plant (sim_backend/backend.py): no hardware library is imported
  "hil"       the real drivers (drivers/) against the emulated rig (sim_backend/emulators/), on loopback
  "hardware"  the real drivers against the devices of the [drivers] section

Every factory is factory(cfg, *, dt, clock, **options) -> a rig.port.Port; construction touches no device,
open() does the slow set-up. Adding a backend: write its factory and add one line to BACKENDS.

`devices(cfg, name)` names the physical devices a backend drives (one lock each, rig/runtime/lock.py: one process
per rig); the sim and hil backends drive devices of their own, made for the run, and share none.
`default_config(name)` is the configuration a backend runs without --config (hil: its own design, at the HIL
rate).
"""
from __future__ import annotations

import importlib
import importlib.util
import logging
import os
from pathlib import Path

from rig.config import layout_mounts
from rig.errors import ConfigError

BACKENDS = {
    "sim": "rig.backends:_sim",
    "hil": "rig.backends:make_hil_port",
    "hardware": "rig.backends:_hardware",
}


def default_config(name: str) -> Path | None:
    """The configuration file of backend `name` when none is given (None: the Table 1 defaults). hil: the
    HIL rate and the isolation controller designed for it (drivers/devicemaps/hil.toml,
    controllers/tune_hil.py)."""
    if name != "hil":
        return None
    spec = importlib.util.find_spec("drivers")           # located, not imported (no hardware library loads)
    return Path(spec.origin).resolve().parent / "devicemaps" / "hil.toml"


def devices(cfg, name: str) -> tuple[str, ...]:
    """The physical devices backend `name` drives under cfg, as lock names (none for sim and hil)."""
    if name != "hardware":
        return ()
    d = cfg.drivers
    return (f"can-{d.can_interface}-{d.can_channel}", f"modbus-{d.modbus_host}-{d.modbus_port}",
            f"serial-{os.path.realpath(d.serial_port)}")


def make_port(cfg, name: str, *, dt: float | None = None, clock=None, **options):
    """The port of backend `name` (ConfigError naming the choices for an unknown one); dt: the loop period
    (default [loop] rate_hz), clock: the loop's (the simulated plant keeps pace with it)."""
    target = BACKENDS.get(name)
    if target is None:
        raise ConfigError(f"{cfg.source}: backend.name: expected one of {', '.join(BACKENDS)}, got {name!r}")
    module, attr = target.split(":")
    factory = getattr(importlib.import_module(module), attr)
    return factory(cfg, dt=dt, clock=clock, **options)


def _sim(cfg, *, dt: float | None = None, clock=None, **options):
    from sim_backend.backend import make_sim_port
    return make_sim_port(cfg, dt if dt is not None else 1.0 / cfg.loop.rate_hz, clock=clock, **options)


def _hardware(cfg, *, dt: float | None = None, clock=None):
    from drivers import build_driver_port
    d = cfg.drivers
    return build_driver_port(cfg, "hardware", can_interface=d.can_interface, can_channel=d.can_channel,
                             modbus_host=d.modbus_host, modbus_port=d.modbus_port, serial_port=d.serial_port,
                             stale_s=d.stale_s, serial_stale_s=d.serial_stale_s)


def make_hil_port(cfg, plant=None, *, dt: float | None = None, clock=None, stale_s: float | None = None,
                  serial_stale_s: float | None = None, priority: int | None = None, trace_s: float = 0.0):
    """The drivers against a freshly started emulated rig (the port's `.rig`; stopped by port.close()).
    plant: default the layout's, stepped at the loop period: the four-mount RigPlant under the configured floor
    vibration, or on the stand layout the actuators on their stands (the prototype: one) on the floor of
    [stand] base_motion_rms_m. The emulated module converts at each plant step (each SYNC), so the port is
    sample-driven. The valves' bus reaches the emulated nodes through their gateway ([hil] can_transport: binary
    frames on a local socket, python-can interface rig_stream, drivers/can_stream.py; or socketcand on
    127.0.0.1: sim_backend/emulators/canopen_valve.py says why). trace_s: seconds of the
    plant's table motion kept for band-limited isolation figures (EmulatedRig.trace)."""
    from drivers import build_driver_port
    from sim_backend.backend import stand_bank
    from sim_backend.emulators.rig import EmulatedRig
    from sim_backend.rig_plant import FloorMotion, RigPlant
    if dt is None and cfg.loop.rate_hz > cfg.hil.rate_hz:
        logging.getLogger("rig.backends").warning(
            "hil: loop.rate_hz %g Hz is above hil.rate_hz %g Hz: expect overruns and late samples (the HIL "
            "configuration is drivers/devicemaps/hil.toml)", cfg.loop.rate_hz, cfg.hil.rate_hz)
    dt = dt if dt is not None else 1.0 / cfg.loop.rate_hz
    if plant is None and cfg.layout.plant == "stand":
        plant = stand_bank(cfg, dt)
    elif plant is None:
        plant = RigPlant(cfg, dt, floor=FloorMotion.from_config(cfg, dt), seed=cfg.vibration.seed)
    d = cfg.drivers
    prio = cfg.hil.device_priority if priority is None else priority
    emu = EmulatedRig(plant, dt, max_V=cfg.valve.max_V, w_spool=cfg.valve.w_nv, accel_V_per_mps2=d.accel_V_per_mps2,
                      node_ids=_valve_node_ids(cfg), priority=prio,
                      floor_V_per_mps2=cfg.sensors.floor_V_per_mps2, floor_channels=cfg.sensors.floor_channels,
                      trace_s=trace_s, ai_faults=_ai_faults(cfg.hil), dt_faults=_dt_faults(cfg.hil),
                      extra_delay_s=cfg.hil.extra_delay_s, valve_faults=_valve_faults(cfg)).start()
    try:
        stale = stale_s if stale_s is not None else cfg.hil.stale_s
        stream = cfg.hil.can_transport == "rig_stream"
        port = build_driver_port(cfg, "hil", can_interface=cfg.hil.can_transport,
                                 can_channel="can0", can_options={"address": emu.can_stream} if stream else
                                 {"host": "127.0.0.1", "port": emu.can_port},
                                 modbus_host="127.0.0.1", modbus_port=emu.modbus_port, serial_port=emu.serial_path,
                                 stale_s=stale, serial_stale_s=serial_stale_s if serial_stale_s is not None else
                                 (stale_s if stale_s is not None else cfg.hil.serial_stale_s),
                                 on_close=emu.stop, priority=priority, sample_driven=True, period_s=dt)
    except BaseException:
        emu.stop()
        raise
    port.rig = emu
    return port


def _valve_node_ids(cfg) -> list[int]:
    """The CAN node each emulated mount's valve answers to ([hil] valve_node_id, shifted with [drivers]
    valve_node_id_base): as documented base + mount index."""
    n, base = len(layout_mounts(cfg)), cfg.drivers.valve_node_id_base
    ids = [base - 1 + k for k in cfg.hil.valve_node_id[:n]]
    if len(set(ids)) != n:
        raise ConfigError(f"{cfg.source}: hil.valve_node_id: expected {n} different node numbers, got "
                          f"{list(cfg.hil.valve_node_id[:n])}")
    return ids


def _valve_faults(cfg):
    """The emulated valves' null offsets and gain factors ([hil] valve_null_V, valve_gain), None when right."""
    n, h = len(layout_mounts(cfg)), cfg.hil
    faults = (list(h.valve_null_V[:n]), list(h.valve_gain[:n]))
    return None if faults == ([0.0] * n, [1.0] * n) else faults


def _ai_faults(hil):
    """The emulated module's wiring faults ([hil] ai_*), None when it is wired as documented."""
    faults = (hil.ai_source, hil.ai_factor, hil.ai_offset_mps2, hil.ai_noise_mps2)
    return None if faults == (tuple(range(8)), (1.0,) * 8, (0.0,) * 8, (0.0,) * 8) else faults


def _dt_faults(hil):
    """The emulated amplifier's wiring faults ([hil] dt_*), None when it is wired as documented."""
    faults = (hil.dt_source, hil.dt_factor, hil.dt_offset_m, hil.dt_noise_m)
    return None if faults == (tuple(range(4)), (1.0,) * 4, (0.0,) * 4, (0.0,) * 4) else faults

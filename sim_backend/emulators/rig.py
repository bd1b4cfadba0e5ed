"""The emulated rig behind the real drivers: plant + CANopen valve nodes + Modbus I/O module + serial amplifier.

  main process   plant (stepped at each CAN SYNC to the wall-clock instant, command held = ZOH), the four
                 valve LocalNodes on a python-can virtual channel (served by the emulator's notifier thread)
  child process  pymodbus TCP server on 127.0.0.1:<ephemeral>   (accelerometers, ADAM-6024-style map)
  child process  DTA-4 amplifier on a pty pair                    (displacement transducers, ASCII)

The plant state reaches the children through one shared array (sim_backend/emulators/shared.py, seqlock);
valve setpoints come from the CAN nodes. Fault knobs: `set_modbus`, `set_serial`, `set_serial_channel`,
`set_valve`. `phase(name)` starts metering the true table motion (plant.table_m) for isolation figures.
"""
from __future__ import annotations

import itertools
import math
import multiprocessing as mp
import os
import threading
import time

from rig.errors import DeviceError
from sim_backend.emulators import shared as sh

_channels = itertools.count()


class EmulatedRig:
    def __init__(self, plant, dt: float, *, max_V: float = 10.0, w_spool: float = 524.0,
                 accel_V_per_mps2: float = 2.0, node_ids=(1, 2, 3, 4), channel: str | None = None,
                 start_timeout_s: float = 30.0):
        self.plant = plant
        self.dt = float(dt)
        self.max_V = max_V
        self.w_spool = w_spool
        self.accel_V_per_mps2 = accel_V_per_mps2
        self.node_ids = list(node_ids)
        self.channel = channel or f"rig-hil-{os.getpid()}-{next(_channels)}"
        self.start_timeout_s = start_timeout_s
        self.arr = sh.new_shared()
        self.modbus_port: int | None = None
        self.serial_path: str | None = None
        self.valves = None
        self._procs: list[tuple[mp.Process, object]] = []
        self._t0: float | None = None
        self._steps = 0
        self.last_cmd_V = [0.0] * 4
        self.lock = threading.Lock()
        self._phase: str | None = None
        self.meter: dict[str, list] = {}

    # ---- lifetime --------------------------------------------------------------------------------------
    def start(self) -> "EmulatedRig":
        from sim_backend.emulators import modbus_server, serial_device
        from sim_backend.emulators.canopen_valve import ValveBus
        self._publish()
        ctx = mp.get_context("spawn")
        try:
            self.modbus_port = self._spawn(ctx, modbus_server.serve, (self.accel_V_per_mps2,), "modbus")
            self.serial_path = self._spawn(ctx, serial_device.serve, (0,), "serial")
            self.valves = ValveBus(self.channel, self.node_ids, self.w_spool, self.max_V, self)
        except BaseException:
            self.stop()
            raise
        return self

    def _spawn(self, ctx, target, extra, what):
        here, there = ctx.Pipe()
        p = ctx.Process(target=target, args=(self.arr, there, *extra), daemon=True, name=f"rig-hil-{what}")
        p.start()
        self._procs.append((p, here))
        if not here.poll(self.start_timeout_s):
            raise DeviceError(f"hil: the emulated {what} device did not start within {self.start_timeout_s:g} s")
        return here.recv()

    def stop(self) -> None:
        if self.valves is not None:
            self.valves.close()
            self.valves = None
        for p, conn in self._procs:
            try:
                conn.send("stop")
            except (OSError, ValueError):
                pass
        for p, conn in self._procs:
            p.join(2.0)
            if p.is_alive():
                p.terminate()
                p.join(2.0)
            if p.is_alive():
                p.kill()
                p.join(1.0)
            conn.close()
        self._procs.clear()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def alive(self) -> bool:
        return bool(self._procs) and all(p.is_alive() for p, _ in self._procs)

    # ---- the plant, advanced at each SYNC --------------------------------------------------------------
    def apply_sync(self, valve_cmd_V: list[float]) -> None:
        """Called by the valve bus on SYNC with the commands the valves now apply. The plant keeps pace
        with the wall clock: normally one step per SYNC, extra steps when it fell behind, none when ahead."""
        now = time.monotonic()
        with self.lock:
            if self._t0 is None:
                self._t0 = now - self.dt
            behind = (now - self._t0) / self.dt - self._steps
            n = 1 if -1.5 <= behind <= 1.5 else (0 if behind < 0 else min(int(behind), 1000))
            plant = self.plant
            self.last_cmd_V = list(valve_cmd_V)
            for _ in range(n):
                plant.step(valve_cmd_V)
                self._steps += 1
                if self._phase is not None:
                    self._meter(plant.table_m)
            self._publish()

    def _publish(self) -> None:
        p = self.plant
        sh.publish(self.arr, float(getattr(p, "t_s", 0.0)), p.accel_mps2, p.stroke_m)

    # ---- table motion metering (true plant output, for isolation figures) ------------------------------
    def phase(self, name: str | None) -> None:
        with self.lock:
            self._phase = name
            if name is not None:
                self.meter[name] = [0, 0.0, 0.0]       # n, sum, sum of squares

    def _meter(self, table_m) -> None:
        x = float(table_m) if not isinstance(table_m, (list, tuple)) else math.fsum(table_m) / len(table_m)
        m = self.meter[self._phase]
        m[0] += 1
        m[1] += x
        m[2] += x * x

    def table_rms_m(self, name: str) -> float:
        n, s, ss = self.meter[name]
        if n < 2:
            return math.nan
        return math.sqrt(max(ss / n - (s / n) ** 2, 0.0))

    # ---- fault knobs --------------------------------------------------------------------------------------
    def set_modbus(self, mode: str) -> None:
        self.arr[sh.MODBUS_MODE] = sh.MODES[mode]

    def set_serial(self, mode: str) -> None:
        self.arr[sh.SERIAL_MODE] = sh.MODES[mode]

    def set_serial_channel(self, ch: int, status: str | None) -> None:
        code = {None: 0, "UR": 1, "OR": 2, "NP": 3}[status]
        self.arr[sh.SERIAL_CH + ch] = code

    def set_valve(self, mount: int, mode: str) -> None:
        from sim_backend.emulators.canopen_valve import VALVE_MODES
        if mode not in VALVE_MODES:
            raise ValueError(f"valve knob {mode!r} (expected one of {', '.join(VALVE_MODES)})")
        self.valves.nodes[mount].mode = mode

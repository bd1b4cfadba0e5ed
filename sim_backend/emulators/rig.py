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
import os
import select
import subprocess
import sys
import threading
import time

from rig.runtime.rt import raise_priority
from rig.errors import DeviceError
from sim_backend.emulators import shared as sh

_channels = itertools.count()


class EmulatedRig:
    def __init__(self, plant, dt: float, *, max_V: float = 10.0, w_spool: float = 524.0,
                 accel_V_per_mps2: float = 2.0, node_ids=(1, 2, 3, 4), channel: str | None = None,
                 start_timeout_s: float = 30.0, priority: int = 0, floor_V_per_mps2: float = 2.0,
                 floor_channels=(4, 5, 6, 7)):
        self.plant = plant
        self.dt = float(dt)
        self.max_V = max_V
        self.w_spool = w_spool
        self.accel_V_per_mps2 = accel_V_per_mps2
        # floor accelerometers: wired to the module when the plant has them (RigPlant.floor_sensors)
        self.floor_V_per_mps2, self.floor_channels = floor_V_per_mps2, tuple(floor_channels)
        self.floor_sensors = bool(getattr(plant, "floor_sensors", False))
        self.node_ids = list(node_ids)
        self.channel = channel or f"rig-hil-{os.getpid()}-{next(_channels)}"
        self.start_timeout_s = start_timeout_s
        self.priority = priority              # SCHED_FIFO of the device processes and threads (0 = normal)
        self.state = sh.SharedFile()
        self.arr = self.state.arr
        self.modbus_port: int | None = None
        self.serial_path: str | None = None
        self.valves = None
        self._procs: list[tuple[subprocess.Popen, str]] = []
        self._t0: float | None = None
        self._steps = 0
        self.last_cmd_V = [0.0] * len(self.node_ids)
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._keeper: threading.Thread | None = None
        self._phase: str | None = None
        self.meter: dict[str, list] = {}

    # ---- lifetime --------------------------------------------------------------------------------------
    def start(self) -> "EmulatedRig":
        from sim_backend.emulators.canopen_valve import ValveBus   # lazy: loads canopen and python-can
        self._publish()
        self._stop.clear()
        self._keeper = threading.Thread(target=self._keep_pace, name="hil-plant-keeper", daemon=True)
        self._keeper.start()
        try:
            self.modbus_port = int(self._spawn("modbus", str(self.accel_V_per_mps2), str(self.priority),
                                               str(self.floor_V_per_mps2), ",".join(map(str, self.floor_channels))))
            self.serial_path = self._spawn("serial", str(self.priority))
            self.state.unlink()                 # both devices have it mapped: nothing is left behind on a crash
            self.valves = ValveBus(self.channel, self.node_ids, self.w_spool, self.max_V, self,
                                   priority=self.priority)
        except BaseException:
            self.stop()
            raise
        return self

    def _spawn(self, what: str, *args: str) -> str:
        """Start `python -m sim_backend.emulators.device what ...`; returns what it announces (port / pty)."""
        p = subprocess.Popen([sys.executable, "-m", "sim_backend.emulators.device", what, self.state.path, *args],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self._procs.append((p, what))
        ready, _, _ = select.select([p.stdout], [], [], self.start_timeout_s)
        line = p.stdout.readline() if ready else ""
        if not line.strip():
            raise DeviceError(f"hil: the emulated {what} device did not start within {self.start_timeout_s:g} s"
                              f" (exit code {p.poll()})")
        return line.split(None, 1)[1].strip()

    def stop(self) -> None:
        self._stop.set()
        if self._keeper is not None:
            self._keeper.join(2.0)
            self._keeper = None
        if self.valves is not None:
            self.valves.close()
            self.valves = None
        for p, _ in self._procs:
            try:
                p.stdin.close()                 # the device's signal to stop
            except OSError:
                pass
        for p, _ in self._procs:
            try:
                p.wait(2.0)
            except subprocess.TimeoutExpired:
                p.terminate()
                try:
                    p.wait(2.0)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(1.0)
            p.stdout.close()
        self._procs.clear()
        if self.state is not None:
            self.arr = None
            self.state.close()
            self.state = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def alive(self) -> bool:
        return bool(self._procs) and all(p.poll() is None for p, _ in self._procs)

    def device_pid(self, what: str) -> int:
        return next(p.pid for p, w in self._procs if w == what)

    # ---- the plant, advanced at each SYNC --------------------------------------------------------------
    def apply_sync(self, valve_cmd_V: list[float]) -> None:
        """Called by the valve bus on SYNC with the commands the valves now apply. The plant keeps pace
        with the wall clock: normally one step per SYNC, extra steps when it fell behind, none when ahead."""
        with self.lock:
            self.last_cmd_V = list(valve_cmd_V)
            self._advance(time.monotonic(), sync=True)

    def _keep_pace(self) -> None:
        """Without SYNC (loop not started, stalled, stopped) the rig still runs: catch up with held commands."""
        raise_priority(self.priority)
        while not self._stop.wait(2 * self.dt):
            with self.lock:
                self._advance(time.monotonic(), sync=False)

    def _advance(self, now: float, sync: bool) -> None:
        if self._t0 is None:
            self._t0 = now - self.dt
        behind = (now - self._t0) / self.dt - self._steps
        if sync:
            n = 1 if -1.5 <= behind <= 1.5 else (0 if behind < 0 else min(int(behind), 1000))
        else:
            n = min(int(behind - 1.5), 1000) if behind > 2.5 else 0
        if n:
            plant = self.plant
            valve_cmd_V = self.last_cmd_V
            for _ in range(n):
                plant.step(valve_cmd_V)
                self._steps += 1
                if self._phase is not None:
                    self._meter(plant.table_m, plant.floor_m)
                self._publish()                 # every step is a conversion of the devices

    def _publish(self) -> None:
        p = self.plant
        # the devices convert at each plant step (the SYNC instants): their counters count plant steps
        sh.publish(self.arr, float(getattr(p, "t_s", 0.0)), p.accel_mps2, p.stroke_m, self._steps,
                   p.floor_accel_mps2 if self.floor_sensors else None)

    # ---- table motion metering (true plant output, for isolation figures) ------------------------------
    def phase(self, name: str | None) -> None:
        with self.lock:
            self._phase = name
            if name is not None:
                self.meter[name] = [0, 0.0, 0.0, 0.0, 0.0]       # n, sum, sum of squares (table, then floor)

    def _meter(self, table_m, floor_m=()) -> None:
        x = float(table_m) if not isinstance(table_m, (list, tuple)) else math.fsum(table_m) / len(table_m)
        g = math.fsum(floor_m) / len(floor_m) if floor_m else 0.0        # the floor under the machine (mean)
        m = self.meter[self._phase]
        m[0] += 1
        m[1] += x
        m[2] += x * x
        m[3] += g
        m[4] += g * g

    def table_rms_m(self, name: str) -> float:
        n, s, ss = self.meter[name][:3]
        if n < 2:
            return math.nan
        return math.sqrt(max(ss / n - (s / n) ** 2, 0.0))

    def floor_rms_m(self, name: str) -> float:
        """The floor's rms (mean of the four mounts) over the same periods as table_rms_m."""
        n, s, ss = self.meter[name][0], self.meter[name][3], self.meter[name][4]
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
        from sim_backend.emulators.canopen_valve import VALVE_MODES   # lazy: loads canopen and python-can
        if mode not in VALVE_MODES:
            raise ValueError(f"valve knob {mode!r} (expected one of {', '.join(VALVE_MODES)})")
        self.valves.nodes[mount].mode = mode

"""The emulated rig behind the real drivers: plant + CANopen valve nodes + Modbus I/O module + serial amplifier,
each in a process of its own, none in the loop's:

  process  the plant and the four valve LocalNodes behind a CAN gateway: binary frames on an abstract Unix
           socket (python-can interface rig_stream, drivers/can_stream.py) or socketcand on 127.0.0.1:<ephemeral>
           (sim_backend/emulators/canopen_valve.py): the plant steps at each CAN SYNC to the SYNC instant
  process  Modbus TCP server on 127.0.0.1:<ephemeral>    (accelerometers, ADAM-6024-style map)
  process  DTA-4 amplifier on a pty pair                    (displacement transducers, ASCII)

The plant's state reaches the two device processes through one shared array (sim_backend/emulators/shared.py,
seqlock): each plant step is a conversion of both. The fault knobs (`set_modbus`, `set_serial`,
`set_serial_channel`, `set_valve`) and the metering phase (`phase(name)`: the true table motion per phase,
and its trace for band-limited figures) are words of the same array, read by the device processes.
"""
from __future__ import annotations

import json
import math
import os
import pickle
import select
import subprocess
import sys
import tempfile

import numpy as np

from rig.errors import ConfigError, DeviceError
from sim_backend.emulators import shared as sh


class EmulatedRig:
    def __init__(self, plant, dt: float, *, max_V: float = 10.0, w_spool: float = 524.0,
                 accel_V_per_mps2: float = 2.0, node_ids=(1, 2, 3, 4), start_timeout_s: float = 60.0,
                 priority: int = 0, floor_V_per_mps2: float = 2.0, floor_channels=(4, 5, 6, 7),
                 trace_s: float = 0.0, ai_faults=None, dt_faults=None, extra_delay_s: float = 0.0,
                 valve_faults=None):
        self.plant = plant
        self.dt = float(dt)
        self.max_V = max_V
        self.w_spool = w_spool
        self.accel_V_per_mps2 = accel_V_per_mps2
        # floor accelerometers: wired to the module when the plant has them (RigPlant.floor_sensors)
        self.floor_V_per_mps2, self.floor_channels = floor_V_per_mps2, tuple(floor_channels)
        self.floor_sensors = bool(getattr(plant, "floor_sensors", False))
        self.ai_faults = ai_faults          # wiring faults of the module's channels: (sources, factors, offsets, noise)
        self.dt_faults = dt_faults          # the amplifier's: (sources, factors, offsets_m, noise_m)
        self.valve_faults = valve_faults    # the valves' (null offsets V, gain factors), mount order; None: right
        self.extra_delay_s = float(extra_delay_s)     # the module's signal lags the plant by this much
        from sim_backend.emulators.modbus_server import MAX_DELAY_STEPS     # lazy: the limit only
        if extra_delay_s / self.dt > MAX_DELAY_STEPS:
            raise ConfigError(f"[hil] extra_delay_s = {extra_delay_s:g} s: at most {MAX_DELAY_STEPS} conversions of "
                              f"{self.dt:g} s ({MAX_DELAY_STEPS * self.dt:g} s) at this rate")
        self.node_ids = list(node_ids)
        self.start_timeout_s = start_timeout_s
        self.priority = priority              # SCHED_FIFO of the device processes (0 = normal)
        self.state = sh.SharedFile(trace_steps=int(math.ceil(trace_s / self.dt)) if trace_s else 0)
        self.arr = self.state.arr
        self.can_port: int | None = None          # the valve nodes' socketcand gateway (127.0.0.1)
        self.can_stream: str | None = None        # ... and their rig_stream socket (drivers/can_stream.py)
        self.modbus_port: int | None = None
        self.serial_path: str | None = None
        self._procs: list[tuple[subprocess.Popen, str]] = []
        self._phases: dict[str, int] = {}

    # ---- lifetime --------------------------------------------------------------------------------------
    def start(self) -> "EmulatedRig":
        try:
            fd, spec = tempfile.mkstemp(prefix="rig-hil-plant-", dir=os.path.dirname(self.state.path))
            with os.fdopen(fd, "wb") as f:
                pickle.dump({"plant": self.plant, "dt": self.dt, "node_ids": self.node_ids, "w_spool": self.w_spool,
                             "max_V": self.max_V, "floor_sensors": self.floor_sensors,
                             "trace_steps": self.state.trace_steps, "valve_faults": self.valve_faults}, f)
            port, self.can_stream = self._spawn("plant", spec, str(self.priority)).split()
            self.can_port = int(port)
            wiring = json.dumps([list(f) for f in self.ai_faults] if self.ai_faults is not None else None)
            self.modbus_port = int(self._spawn("modbus", str(self.accel_V_per_mps2), str(self.priority),
                                               str(self.floor_V_per_mps2), ",".join(map(str, self.floor_channels)),
                                               wiring, repr(self.extra_delay_s / self.dt)))
            self.serial_path = self._spawn("serial", str(self.priority),
                                           json.dumps([list(f) for f in self.dt_faults] if self.dt_faults else None))
            self.state.unlink()                 # every device has it mapped: nothing is left behind on a crash
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
        for p, _ in self._procs:
            try:
                p.stdin.close()                 # the device's signal to stop
            except OSError:
                pass
        for p, _ in self._procs:
            try:
                p.wait(3.0)
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
            self._meter_copy = np.frombuffer(self.state._mm, dtype=np.float64).copy()
            self.arr = self._meter_copy
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

    @property
    def last_cmd_V(self) -> list[float]:
        """The commands the emulated valves apply now."""
        return list(self.arr[sh.LAST_CMD:sh.LAST_CMD + len(self.node_ids)])

    @property
    def steps(self) -> int:
        """Plant steps so far (= conversions of the devices)."""
        return int(self.arr[sh.COUNT])

    # ---- table motion metering (true plant output, for isolation figures) ------------------------------
    @property
    def meter(self) -> dict:
        return {name: self._sums(name) for name in self._phases}

    def phase(self, name: str | None) -> None:
        """Meter the true table motion as phase `name` from the plant's next step (None: stop metering)."""
        if name is None:
            self.arr[sh.PHASE] = 0.0
            return
        if name not in self._phases:
            if len(self._phases) >= sh.MAX_PHASES:
                raise ValueError(f"at most {sh.MAX_PHASES} metering phases")
            self._phases[name] = len(self._phases) + 1
            m = sh.METER + 5 * (self._phases[name] - 1)
            self.arr[m:m + 5] = [0.0] * 5
        self.arr[sh.PHASE] = float(self._phases[name])

    def _sums(self, name: str) -> list[float]:
        m = sh.METER + 5 * (self._phases[name] - 1)
        return list(self.arr[m:m + 5])

    def table_rms_m(self, name: str) -> float:
        n, s, ss = self._sums(name)[:3]
        if n < 2:
            return math.nan
        return math.sqrt(max(ss / n - (s / n) ** 2, 0.0))

    def floor_rms_m(self, name: str) -> float:
        """The floor's rms (mean of the mounts) over the same steps as table_rms_m."""
        n, _, _, s, ss = self._sums(name)
        if n < 2:
            return math.nan
        return math.sqrt(max(ss / n - (s / n) ** 2, 0.0))

    def trace(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(table_m, floor_m, phase code) per plant step traced so far (as long as the trace had room)."""
        k = int(self.arr[sh.TRACE])
        t = np.asarray(self.arr[sh.SIZE:sh.SIZE + sh.TRACE_WIDTH * k]).reshape(k, sh.TRACE_WIDTH)
        return t[:, 0].copy(), t[:, 1].copy(), t[:, 2].astype(int)

    def phase_code(self, name: str) -> int:
        return self._phases[name]

    # ---- fault knobs --------------------------------------------------------------------------------------
    def set_modbus(self, mode: str) -> None:
        self.arr[sh.MODBUS_MODE] = sh.MODES[mode]

    def set_serial(self, mode: str) -> None:
        self.arr[sh.SERIAL_MODE] = sh.MODES[mode]

    def set_serial_channel(self, ch: int, status: str | None) -> None:
        code = {None: 0, "UR": 1, "OR": 2, "NP": 3}[status]
        self.arr[sh.SERIAL_CH + ch] = code

    def set_valve(self, mount: int, mode: str) -> None:
        from sim_backend.emulators.canopen_valve import VALVE_MODES   # lazy: the mode names only
        if mode not in VALVE_MODES:
            raise ValueError(f"valve knob {mode!r} (expected one of {', '.join(VALVE_MODES)})")
        self.arr[sh.VALVE_MODE + mount] = float(VALVE_MODES.index(mode))

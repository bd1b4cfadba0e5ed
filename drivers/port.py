"""The hardware port: CANopen valves + Modbus TCP accelerometers + serial displacement transducers as one
rig.port.Port. The same class drives the real rig ("hardware") and the emulated one ("hil").

Processes: each device's blocking work runs in an I/O process of its own (drivers/process.py: the valves'
SYNC/PDO traffic and decoding, the module's Modbus requests, the amplifier's serial framing), so none of it
shares the loop's interpreter. They meet the loop in one exchange block in shared memory
(rig/runtime/exchange.py): the loop's kernel takes the newest conversions and transducer sample from it and
writes its commands into it; nothing in the period waits for a device or a lock another process holds. The
port has no call in the period: when the valves' I/O is waiting for the period's commands (the loop ran late),
the kernel says so and the loop wakes it (a futex wake).

Timing (the loop's period P): the valves' I/O sends the period's commands and then SYNC at `sync_offset_s`
after the period starts; the valves apply them from that SYNC on; the module converts on the SYNC (the
emulated plant steps to it) and its I/O fetches the conversion `fetch_delay_s` later, so the loop's next
period has it: the sample at SYNC k reaches the commands of SYNC k + 1, a ZOH plus one period of delay as the
controller analysis assumes. The transducer runs at its own rate, held between its frames.

Faults: each device's I/O checks its device and writes its one-line fault in the block; the kernel faults on
it, and on a device whose I/O stopped reporting for longer than its limit (its heartbeat).
"""
from __future__ import annotations

import json
import select
import subprocess
import sys
import time

import numpy as np

from rig.errors import DeviceError
from rig.port import Commands, Measurements, PortContext
from rig.runtime import exchange as ex

DEVICES = ("valves", "accelerometer module", "transducer amplifier")
VALVES, ANALOG, TRANSDUCER = range(len(DEVICES))
OPEN_ORDER = (ANALOG, TRANSDUCER, VALVES)


class DriverPort(PortContext):
    transports = ("canopen", "modbus_tcp", "serial")

    def __init__(self, name: str, specs: list[dict], *, n_mounts: int, floor_sensors: bool = False,
                 counted: bool = True, stroke_stale_s: float = 0.0, on_close=None, start_timeout_s: float = 60.0):
        self.name = name
        self.n_mounts = n_mounts
        self.floor_sensors = bool(floor_sensors)
        self.sample_driven = bool(counted)
        self.exchange = ex.Block.create(ex.Layout(n_mounts, n_mounts if floor_sensors else 0, devices=DEVICES))
        io = self.exchange.io
        io[self.exchange.part("accel") + ex.A_COUNTED] = 1.0 if counted else 0.0
        io[self.exchange.part("stroke") + ex.S_STALE] = stroke_stale_s * 1e9
        self.specs = [dict(s, block=self.exchange.path, devices=list(DEVICES)) for s in specs]
        self._procs: list[subprocess.Popen | None] = [None] * len(self.specs)
        self._on_close = on_close
        self.start_timeout_s = start_timeout_s
        self.opened = False
        self._seen = -1

    # ---- lifetime ------------------------------------------------------------------------------------------
    def open(self) -> None:
        """Start the I/O processes (all at once: each opens its device) and wait for each one's first line:
        `ready`, or its one-line error (DeviceError, the others stopped)."""
        if self.opened:
            return
        try:
            for i, spec in enumerate(self.specs):
                p = subprocess.Popen([sys.executable, "-m", "drivers.process"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
                self._procs[i] = p
                p.stdin.write(json.dumps(spec) + "\n")
                p.stdin.flush()
            for i in OPEN_ORDER:                    # the sensors' answers first: their faults are named first
                p = self._procs[i]
                ready, _, _ = select.select([p.stdout], [], [], self.start_timeout_s)
                line = p.stdout.readline().strip() if ready else ""
                if line != "ready":
                    name = self.specs[i]["name"]
                    raise DeviceError(line[len("error "):] if line.startswith("error ") else
                                      f"{name}: its I/O process did not start within {self.start_timeout_s:g} s "
                                      f"(exit code {p.poll()})")
        except BaseException:
            self._stop_processes()
            raise
        self.exchange.unlink()             # every process has it mapped: nothing is left behind on a crash
        self.opened = True

    def _stop_processes(self) -> None:
        for p in self._procs:
            if p is not None:
                try:
                    p.stdin.close()                 # the process's signal to stop
                except OSError:
                    pass
        for i, p in enumerate(self._procs):
            if p is None:
                continue
            try:
                p.wait(3.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(2.0)
            p.stdout.close()
            self._procs[i] = None

    def close(self) -> None:
        try:
            if self.opened:
                self.safe_state()
                time.sleep(3 * self.specs[VALVES]["period_s"])     # the null goes out with the next SYNCs
            self._stop_processes()
        finally:
            self.opened = False
            self.exchange.unlink()
            if self._on_close is not None:
                cb, self._on_close = self._on_close, None
                cb()

    def alive(self) -> list[str]:
        """The devices whose I/O process has ended, with how."""
        out = []
        for spec, p in zip(self.specs, self._procs):
            if p is not None and p.poll() is not None:
                out.append(f"{spec['name']}: its I/O process ended (exit code {p.returncode})")
        return out

    def stale_reason(self, t_ns: int, limit_ns: float) -> str | None:
        """A stale accelerometer sample in the loop's check, named as the module's fault when the module has
        delivered nothing new for as long (its I/O may not have said so yet): its line, with its last error."""
        row = self.exchange.device_row(ANALOG)
        age = t_ns - row[ex.D_SAMPLE]
        if row[ex.D_SAMPLE] <= 0 or age < limit_ns:
            return None
        why = self.exchange.text(ANALOG) if not row[ex.D_FAULT] else ""
        return (f"device fault: {self.specs[ANALOG]['name']} unit {self.specs[ANALOG]['unit']}: no new sample for "
                f"{age / 1e6:.1f} ms (limit {limit_ns / 1e6:g} ms); "
                f"{'last error: ' + why if why else 'values not updating'}")

    def silent_reason(self, d: int) -> str | None:
        """Why device d stopped reporting, when its process ended (the loop's fault text)."""
        p = self._procs[d] if d < len(self._procs) else None
        if p is not None and p.poll() is not None:
            return f"its I/O process ended (exit code {p.returncode})"
        return None

    # ---- the Port protocol, for callers of their own (the loop's kernel reads and writes the block itself) ----
    def write(self, t_ns: int, commands: Commands) -> None:
        """The commands into the block; the valves' I/O woken if it waits for them."""
        io = self.exchange.io
        ex.put_commands(io, float(t_ns), np.asarray(commands.valve_cmd_V, dtype=np.float64))
        if ex.take_waiter(io):
            self.exchange.wake(ex.FUTEX_CMD)

    def read(self, t_ns: int) -> Measurements:
        """The newest values in the block (the Port protocol, for callers of their own: the loop's kernel
        takes them itself): the conversions since the last read, the transducer's newest sample, a device's
        fault line."""
        b, io = self.exchange, self.exchange.io
        n, nf = b.n, b.nf
        a = b.part("accel")
        cap, w = int(io[ex.H_ACAP]), int(io[ex.H_AWIDTH])
        newest = int(io[a + ex.A_NEWEST])

        def conv(c):
            s = a + ex.A_SLOTS + (c % cap) * w
            return io[s + 1:s + 1 + n].tolist(), io[s + 1 + n:s + 1 + 2 * n + nf].tolist()
        ts, vals = conv(newest)
        so = b.part("stroke")
        ss = so + ex.S_SLOTS + (int(io[so + ex.S_NEWEST]) % int(io[ex.H_SCAP])) * int(io[ex.H_SWIDTH])
        new = newest - self._seen if self._seen >= 0 else 1
        older = tuple(tuple(conv(c)[1]) for c in range(max(self._seen + 1, newest - new + 1), newest))
        self._seen = newest
        fault = next((b.text(d) for d in range(len(DEVICES)) if b.device_row(d)[ex.D_FAULT]), None)
        return Measurements(t_ns, vals[:n], io[ss + 2:ss + 2 + n].tolist(), [int(t) for t in ts], [], fault,
                            new if self.sample_driven else None, older if self.sample_driven else (), vals[n:])

    def reset_faults(self) -> None:
        """Acknowledge valve faults (controlword R edge, sent by the valves' I/O). Not part of the Port protocol:
        for operators/tests."""
        row = self.exchange.device_row(VALVES)
        row[ex.D_REQUEST] += 1.0

    def safe_state(self) -> None:
        """Valves to null (their I/O sends null from its next SYNC until the loop writes again); any thread."""
        ex.safe(self.exchange)

    # ---- figures --------------------------------------------------------------------------------------------
    def round_trips_us(self) -> dict[str, list[float]]:
        b = self.exchange
        return {"canopen_sync_to_tpdo": b.stats(VALVES).tolist(), "modbus_read": b.stats(ANALOG).tolist(),
                "serial_frame": b.stats(TRANSDUCER).tolist()}

    def counts(self) -> dict[str, tuple[int, int]]:
        """Per device (samples or SYNCs so far, misses): the valves' late commands, the module's lost
        conversions, the amplifier's requests without a new frame."""
        return {name: (int(self.exchange.device_row(d)[ex.D_COUNT]), int(self.exchange.device_row(d)[ex.D_MISSED]))
                for d, name in enumerate(DEVICES)}

    def sample_ages_us(self) -> np.ndarray:
        """(periods, 2): the accelerometer conversion's and the transducer sample's age when the loop used them."""
        return self.exchange.ages_us()

    @property
    def pids(self) -> dict[str, int]:
        return {s["name"]: p.pid for s, p in zip(self.specs, self._procs) if p is not None}

    def __del__(self):
        try:
            self.exchange.unlink()
        except Exception:          # noqa: BLE001 - interpreter shutdown
            pass

"""An I/O process: one device's blocking work off the loop's interpreter (`python -m drivers.process`).

The loop's process (drivers/port.py) starts one per device and writes its spec (one JSON line) on the
process's stdin: the device's kind and settings, the path of the exchange block (rig/runtime/exchange.py)
and the device's row in it. The process attaches the block, opens the device (the slow set-up: SDO, register
writes, identification) and answers one line on stdout: `ready`, or `error <one line naming the device>`.
Then it runs the device's cycle until its stdin closes (the port closed it, or the loop's process died) and
closes the device. What it measures and finds goes into the block only: the loop never waits for it.

A device is a class with `open()`, `run(stop)` (its cycle until the threading.Event `stop`) and `close()`,
over an `IODevice` base that holds its row of the block (heartbeat, fault line, round trips); the same
class runs in a thread of a test process on a block of the test's own.
"""
from __future__ import annotations

import json
import logging
import os
import sys
import threading
import time

from rig.errors import DeviceError
from rig.runtime import exchange as ex
from rig.runtime.clock import MonotonicClock
from rig.runtime.rt import freeze_heap

log = logging.getLogger("rig.drivers")


class IODevice:
    """A device's side of the exchange block: its row (heartbeat, silence limit, fault), its round trips.
    spec: "device" (the row), "name", "silent_s" (the loop faults when the row's heartbeat is older)."""

    def __init__(self, spec: dict, block: ex.Block) -> None:
        self.spec = spec
        self.block = block
        self.io = block.io
        self.d = int(spec["device"])
        self.name = spec.get("name", f"device {self.d}")
        self.clock = MonotonicClock(0)
        self._fault_text = ""
        self._row = row = block.device_row(self.d)
        row[ex.D_SILENT] = float(spec.get("silent_s", 0.0)) * 1e9
        self.beat()

    def beat(self) -> None:
        self._row[ex.D_BEAT] = float(time.monotonic_ns())     # one aligned 8-byte store (ex.beat's rule)

    def report(self, text: str | None) -> None:
        """The device's fault line now (None: none): published when it changes."""
        text = text or ""
        if text != self._fault_text:
            self._fault_text = text
            self.block.fault(self.d, 1 if text else 0, text)

    def stat(self, value_us: float) -> None:
        ex.add_stat(self.io, self.d, value_us)

    def counted(self, samples: int = 1, missed: int = 0) -> None:
        """Samples (SYNCs) done and missed so far, for the figures (`rig hil --bench`)."""
        row = self._row
        row[ex.D_COUNT] += samples
        row[ex.D_MISSED] += missed

    def requests(self) -> float:
        """The count of the row's requests (the port's: e.g. a valve fault reset)."""
        return float(self._row[ex.D_REQUEST])

    def sleep_until(self, t_ns: int) -> None:
        self.clock.sleep_until(int(t_ns))


def _kinds():
    from drivers.canopen_valves import ValveIO          # lazy: each I/O process loads its own stack only
    from drivers.modbus_io import AnalogIO              # lazy: as above
    from drivers.serial_dta import TransducerIO         # lazy: as above
    return {"valves": ValveIO, "analog": AnalogIO, "transducer": TransducerIO}


def _watch_stdin(stop: threading.Event) -> None:
    try:
        while sys.stdin.buffer.read(1):
            pass
    except (OSError, ValueError):
        pass
    stop.set()


def _say(text: str) -> None:
    try:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    except OSError:
        pass


def main() -> int:
    logging.basicConfig(level=logging.WARNING, format="rig drivers: %(message)s", stream=sys.stderr)
    spec = json.loads(sys.stdin.readline())
    # the set-up (imports, SDO, register writes) at normal priority: at SCHED_FIFO it would hold the other
    # processes starting beside it off their CPU; each device's cycle raises itself (run)
    sys.setswitchinterval(2e-4)          # the device's threads (a CAN notifier) hand over the interpreter quickly
    block = ex.Block.attach(spec["block"], tuple(spec.get("devices", ())))
    kind = _kinds().get(spec["kind"])
    if kind is None:
        _say(f"error unknown device kind {spec['kind']!r}")
        return 2
    freeze_heap()                        # the libraries' heap, before the device's set-up starts its timers
    try:
        dev = kind(spec, block)
        dev.open()
    except DeviceError as e:
        _say(f"error {e}")
        return 1
    except Exception as e:              # noqa: BLE001 - one line back to the loop's process
        _say(f"error {spec.get('name', spec['kind'])}: set-up failed ({e.__class__.__name__}: {e})")
        return 1
    stop = threading.Event()
    threading.Thread(target=_watch_stdin, args=(stop,), daemon=True).start()
    dev.beat()                           # alive from now (the set-up took its time: the loop may start at once)
    _say("ready")
    try:
        dev.run(stop)
    finally:
        dev.close()
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:             # Ctrl-C reaches the whole process group: the port stops us
        os._exit(0)

"""Plant state shared between the emulated rig (main process) and the device processes.

One float64 shared array. The plant thread is the only writer of the sensor block and guards it with a
sequence lock (odd while writing), so a device process never serves half an update. Fault knobs live in the
same array: the test or the `rig hil` command sets them, the device processes read them on each request.
"""
from __future__ import annotations

import ctypes
import mmap
import os
import tempfile

N_MOUNTS = 4

SEQ = 0          # seqlock counter
T_S = 1          # plant time of the snapshot
COUNT = 2        # conversion counter: +1 per plant step
ACCEL = 3        # 4 x accel_mps2
STROKE = 7       # 4 x stroke_m
MODBUS_MODE = 11
SERIAL_MODE = 12
SERIAL_CH = 13   # 4 x forced channel status (0 none, 1 UR, 2 OR, 3 NP)
FLOOR = 17       # 4 x floor accel_mps2 (the floor accelerometers; 0 without them)
FIFO = 21        # the last FIFO_SLOTS conversions, slot = counter % FIFO_SLOTS: FIFO_WIDTH values each
FIFO_SLOTS = 64
FIFO_WIDTH = 1 + 2 * N_MOUNTS   # [counter, 4 x accel_mps2, 4 x floor accel_mps2]
VALVE_MODE = FIFO + FIFO_WIDTH * FIFO_SLOTS     # 4 x a valve node's knob (canopen_valve.VALVE_MODES index)
PHASE = VALVE_MODE + N_MOUNTS   # the metering phase (0: none; the loop's process names them)
LAST_CMD = PHASE + 1            # 4 x the commands the valves apply now (V)
SYNCS = LAST_CMD + N_MOUNTS     # SYNCs the valves have answered
METER = SYNCS + 1               # MAX_PHASES x [n, sum, sum of squares of the table, then of the floor]
MAX_PHASES = 8
TRACE = METER + 5 * MAX_PHASES  # [steps traced, then per step: table, floor (mean of the mounts), phase]
SIZE = TRACE + 1                # (the trace's steps follow: SharedFile(trace_steps=...))
TRACE_WIDTH = 3

# fault knob modes (same codes for every emulator)
OK, SILENCE, EXCEPTION, GARBAGE, STALE, FRAGMENT = 0, 1, 2, 3, 4, 5
MODES = {"ok": OK, "silence": SILENCE, "exception": EXCEPTION, "garbage": GARBAGE, "stale": STALE,
         "fragment": FRAGMENT}
CH_STATUS = {0: None, 1: "UR", 2: "OR", 3: "NP"}


def new_shared():
    """A process-local array (tests of a device entry point run in a thread)."""
    return (ctypes.c_double * SIZE)()


class SharedFile:
    """The array in a file-backed mmap under /dev/shm, so a device process started by path (python -m ...)
    attaches by name, independent of the parent's __main__. The creator removes the file. trace_steps: room for
    the plant's table and floor motion of that many steps (the metered phases' band-limited figures)."""

    def __init__(self, path: str | None = None, trace_steps: int = 0):
        self.owner = path is None
        if self.owner:
            d = "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()
            fd, path = tempfile.mkstemp(prefix="rig-hil-", suffix=".state", dir=d)
            os.ftruncate(fd, 8 * (SIZE + TRACE_WIDTH * trace_steps))
            os.close(fd)
        self.path = path
        with open(path, "r+b") as f:
            self._mm = mmap.mmap(f.fileno(), 0)
        size = len(self._mm) // 8
        self.arr = (ctypes.c_double * size).from_buffer(self._mm)
        self.trace_steps = (size - SIZE) // TRACE_WIDTH

    def unlink(self) -> None:
        """Remove the file (the mappings stay valid); done once every process has attached."""
        if self.owner:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
            self.owner = False

    def close(self) -> None:
        self.arr = None
        try:
            self._mm.close()
        except BufferError:          # a view is still alive somewhere: the mapping goes with the process
            pass
        self.unlink()


def publish(arr, t_s: float, accel_mps2, stroke_m, count: int | None = None, floor_mps2=None) -> None:
    """A new plant state; count = conversions so far (default: one more than before); floor_mps2: the floor
    accelerometers (default none: 0). A plant of fewer mounts (the prototype: one) leaves the devices' other
    channels at zero."""
    seq = arr[SEQ] + 1.0
    arr[SEQ] = seq                          # odd: writing
    arr[T_S] = t_s
    count = int(arr[COUNT]) + 1 if count is None else int(count)
    arr[COUNT] = float(count)
    pad = [0.0] * (N_MOUNTS - len(accel_mps2))
    acc = [float(a) for a in accel_mps2] + pad
    fl = [float(a) for a in floor_mps2] + [0.0] * (N_MOUNTS - len(floor_mps2)) if floor_mps2 is not None \
        else [0.0] * N_MOUNTS
    arr[ACCEL:ACCEL + N_MOUNTS] = acc
    arr[FLOOR:FLOOR + N_MOUNTS] = fl
    base = FIFO + FIFO_WIDTH * (count % FIFO_SLOTS)
    arr[base:base + FIFO_WIDTH] = [float(count)] + acc + fl
    arr[STROKE:STROKE + N_MOUNTS] = [float(s) for s in stroke_m] + pad
    arr[SEQ] = seq + 1.0                    # even: consistent


def snapshot(arr) -> tuple[int, float, list[float], list[float]]:
    """(counter, t_s, accel_mps2[4], stroke_m[4]), a consistent copy."""
    for _ in range(1000):
        s0 = arr[SEQ]
        block = arr[T_S:STROKE + N_MOUNTS]
        if s0 == arr[SEQ] and int(s0) % 2 == 0:
            return int(block[1]), block[0], block[2:6], block[6:10]
    block = arr[T_S:STROKE + N_MOUNTS]      # writer died mid-update: serve what is there
    return int(block[1]), block[0], block[2:6], block[6:10]


def read_fifo(arr, e0: int, e1: int) -> tuple[int, list[float], list[tuple[int, int, list[float]]]]:
    """(counter, accel_mps2[4] + floor accel_mps2[4], [(entry, its counter, its 8 values)] for FIFO entries e0..e1-1,
    entry e = conversion counter - e), one consistent copy (only the slots asked for)."""
    w = FIFO_WIDTH
    for _ in range(1000):
        s0 = arr[SEQ]
        count = int(arr[COUNT])
        acc = arr[ACCEL:ACCEL + N_MOUNTS] + arr[FLOOR:FLOOR + N_MOUNTS]
        slots = []
        for e in range(e0, min(e1, FIFO_SLOTS)):
            b = FIFO + w * ((count - e) % FIFO_SLOTS)
            slots.append((e, int(arr[b]), arr[b + 1:b + w]))
        if s0 == arr[SEQ] and int(s0) % 2 == 0:
            break
    return count, acc, slots

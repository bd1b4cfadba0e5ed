"""Entry point of an emulated device process: `python -m sim_backend.emulators.device KIND STATE_FILE ...`.

  modbus STATE_FILE V_PER_MPS2 PRIORITY [FLOOR_V_PER_MPS2 FLOOR_CHANNELS [FAULTS [DELAY_STEPS]]]
                                          prints `PORT <n>` once listening on 127.0.0.1:<n>
                                          (FLOOR_CHANNELS: comma-separated AI channels, MOUNTS order;
                                          FAULTS: wiring faults, JSON [sources, factors, offsets, noise] or
                                          null; DELAY_STEPS: conversions the signal lags, fractional)
  serial STATE_FILE PRIORITY [FAULTS]     prints `PATH <pty>` once the pty pair is open (FAULTS: JSON
                                          [sources, factors, offsets_m, noise_m] or null)
  plant STATE_FILE SPEC_FILE PRIORITY     the plant and the valve nodes behind a CAN gateway; prints
                                          `PORT <n> <@name>` once listening on 127.0.0.1:<n> (socketcand) and
                                          on the abstract Unix socket @name (rig_stream, drivers/can_stream.py)
                                          (SPEC_FILE: pickled)
The device serves until its stdin closes (the parent closed the pipe or died) or it is terminated.
"""
from __future__ import annotations

import importlib
import json
import logging
import os
import sys
import threading

from rig.runtime.rt import freeze_heap
from sim_backend.emulators.shared import SharedFile


class _Announce:
    """The pipe-like object the serve() functions report on; poll() becomes true when stdin closes."""

    def __init__(self, word: str):
        self.word = word
        self.closed = threading.Event()
        threading.Thread(target=self._watch, daemon=True).start()

    def _watch(self):
        try:
            while sys.stdin.buffer.read(1):
                pass
        except (OSError, ValueError):
            pass
        self.closed.set()

    def send(self, value) -> None:
        sys.stdout.write(f"{self.word} {value}\n")
        sys.stdout.flush()

    def poll(self, timeout: float = 0.0) -> bool:
        return self.closed.wait(timeout) if timeout else self.closed.is_set()


def main(argv: list[str]) -> int:
    kind, path = argv[0], argv[1]
    state = SharedFile(path)
    if kind in ("modbus", "serial", "plant"):
        # this child's libraries loaded first, then the heap frozen (rig.runtime.rt.freeze_heap): a full
        # collection while serving then walks only what serving made
        importlib.import_module({"modbus": "sim_backend.emulators.modbus_server",
                                 "serial": "sim_backend.emulators.serial_device",
                                 "plant": "sim_backend.emulators.canopen_valve"}[kind])
        freeze_heap()
    if kind == "modbus":
        from sim_backend.emulators import modbus_server          # lazy: this child serves Modbus only
        floor = (float(argv[4]), tuple(int(c) for c in argv[5].split(","))) if len(argv) > 5 else (2.0, (4, 5, 6, 7))
        faults = json.loads(argv[6]) if len(argv) > 6 else None
        delay = float(argv[7]) if len(argv) > 7 else 0.0
        modbus_server.serve(state.arr, _Announce("PORT"), float(argv[2]), int(argv[3]), floor_V_per_mps2=floor[0],
                            floor_channels=floor[1], faults=faults, delay_steps=delay)
    elif kind == "serial":
        from sim_backend.emulators import serial_device          # lazy: this child serves the pty only
        serial_device.serve(state.arr, _Announce("PATH"), 0, int(argv[2]),
                            faults=json.loads(argv[3]) if len(argv) > 3 else None)
    elif kind == "plant":
        from sim_backend.emulators import canopen_valve          # lazy: this child runs canopen and the plant
        canopen_valve.serve(state.arr, _Announce("PORT"), argv[2], int(argv[3]))
    else:
        print(f"unknown device kind {kind!r}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except KeyboardInterrupt:             # Ctrl-C reaches the whole process group: the rig stops us
        sys.stdout.flush()
        os._exit(0)                       # not sys.exit: the stdin watcher's read would make finalizing fatal

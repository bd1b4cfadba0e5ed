"""ADAM-6024-style analog I/O module with eight AI channels: a pymodbus TCP server on 127.0.0.1, run in its own
process.

Register map (drivers/devicemaps/adam6024_modbus.md): holding registers, 0-based address = 4xxxx - 40001.
  0-7   AI ch0-7  (40001-40008)  0..65535 = -10..+10 V; ch0-3 accelerometers of the four mounts, the floor
                                 accelerometers on their channels (floor_channels; others 0 V)
  8     40009  conversion counter (+1 per ADC conversion, wraps at 65536)
  9     40010  module status: bit0 host watchdog tripped (write 0 to clear)
  10-11 AO ch0-1  (40011-40012)  0..65535 = -10..+10 V
  12-13 40013-40014 AO safe values, applied when the host watchdog trips
  20    40021  host watchdog timeout in 0.1 s (0 = off)
  24-599 40025-40600  conversion FIFO, newest first: 64 entries of [counter, AI ch0-7] (one conversion per
                     plant step, i.e. per SYNC; entries not yet filled carry counter = newest + 1)
The accelerometer voltages come from the shared plant state; fault knobs from the shared MODBUS_MODE.
"""
from __future__ import annotations

import asyncio
import os
import random
import time

from pymodbus.constants import ExcCodes

from drivers.protocol.modbus_map import (FIFO_WIDTH, N_AI, N_REGS, REG_AI, REG_AO, REG_AO_SAFE, REG_COUNT,
                                        REG_FIFO, REG_STATUS, REG_WDOG, volts_to_raw)
from rig.runtime.rt import raise_priority
from sim_backend.emulators import shared as sh

class Module:
    """The module's behaviour behind the registers (sensitivity: accelerometer V per m/s^2; the floor
    accelerometers' sensitivity and channels: floor_V_per_mps2, floor_channels)."""

    def __init__(self, arr, sensitivity_V_per_mps2: float, floor_V_per_mps2: float = 2.0,
                 floor_channels=(4, 5, 6, 7)):
        self.arr = arr
        self.k = sensitivity_V_per_mps2
        # per AI channel: (index into the snapshot's 8 values: 4 mount then 4 floor accelerations, V per m/s^2)
        self.wiring = [(ch, sensitivity_V_per_mps2) if ch < sh.N_MOUNTS else (None, 0.0) for ch in range(N_AI)]
        for i, ch in enumerate(floor_channels):
            self.wiring[ch] = (sh.N_MOUNTS + i, floor_V_per_mps2)
        self.last_request = time.monotonic()
        self.frozen: list[int] | None = None

    def watchdog(self, regs: list[int]) -> None:
        """The host watchdog: no request for the configured time -> AO to safe values, status bit set."""
        timeout_s = regs[REG_WDOG] * 0.1
        now = time.monotonic()
        if timeout_s > 0 and now - self.last_request > timeout_s:
            regs[REG_AO:REG_AO + 2] = regs[REG_AO_SAFE:REG_AO_SAFE + 2]
            regs[REG_STATUS] |= 1
        self.last_request = now

    def volts(self, values) -> list[int]:
        """AI ch0-7 (raw) of one conversion: values = 4 mount then 4 floor accelerations."""
        return [volts_to_raw(values[i] * k) if i is not None else 32768 for i, k in self.wiring]

    async def action(self, func_code, start, address, count, regs, set_values):
        mode = int(self.arr[sh.MODBUS_MODE])
        if mode == sh.SILENCE:                    # stop answering while the knob is set
            while int(self.arr[sh.MODBUS_MODE]) == sh.SILENCE:
                await asyncio.sleep(0.005)
            return ExcCodes.GATEWAY_NO_RESPONSE   # the answer is late anyway
        if mode == sh.EXCEPTION:
            return ExcCodes.DEVICE_FAILURE
        self.watchdog(regs)
        if mode == sh.STALE:
            if self.frozen is None:
                self.frozen = list(regs[:REG_STATUS]) + [None] + list(regs[REG_FIFO:N_REGS])
            regs[:REG_STATUS] = self.frozen[:REG_STATUS]
            regs[REG_FIFO:N_REGS] = self.frozen[REG_STATUS + 1:]
            return None
        self.frozen = None
        count_, accel, fifo = sh.snapshot_fifo(self.arr)
        lo, hi = max(address, REG_FIFO), min(address + count, N_REGS)
        w = FIFO_WIDTH
        if lo < hi:                                 # the FIFO entries asked for: entry e = conversion count_ - e
            for e in range((lo - REG_FIFO) // w, (hi - 1 - REG_FIFO) // w + 1):
                base = REG_FIFO + w * e
                c, acc = fifo[(count_ - e) % sh.FIFO_SLOTS]
                if c == count_ - e >= 0:
                    regs[base] = c & 0xFFFF
                    regs[base + 1:base + w] = self.volts(acc)
                else:                               # not converted yet
                    regs[base:base + w] = [(count_ + 1) & 0xFFFF] + [32768] * (w - 1)
        regs[REG_AI:REG_AI + N_AI] = self.volts(accel)
        regs[REG_COUNT] = count_ & 0xFFFF
        return None


def serve(arr, port_conn, sensitivity_V_per_mps2: float, priority: int = 0, host: str = "127.0.0.1",
          floor_V_per_mps2: float = 2.0, floor_channels=(4, 5, 6, 7)) -> None:
    """Process entry: bind an ephemeral port on loopback, report it on port_conn, serve until the parent
    goes away or sends anything on port_conn."""
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    raise_priority(priority)
    parent = os.getppid()
    module = Module(arr, sensitivity_V_per_mps2, floor_V_per_mps2, floor_channels)

    def trace_packet(sending: bool, data: bytes) -> bytes:
        if sending and int(arr[sh.MODBUS_MODE]) == sh.GARBAGE:
            return bytes(random.getrandbits(8) for _ in range(len(data)))
        return data

    async def main():
        device = SimDevice(id=0, simdata=[SimData(0, count=N_REGS, values=0, datatype=DataType.REGISTERS)],
                           action=module.action)
        server = ModbusTcpServer(device, address=(host, 0), trace_packet=trace_packet)
        await server.serve_forever(background=True)
        port = server.transport.sockets[0].getsockname()[1]
        port_conn.send(port)
        while os.getppid() == parent and not port_conn.poll():
            await asyncio.sleep(0.05)
        await server.shutdown()

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass

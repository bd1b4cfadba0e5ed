"""ADAM-6024-style analog I/O module with eight AI channels: a Modbus TCP server on 127.0.0.1, run in its own
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
The accelerometer voltages come from the shared plant state; fault knobs from the shared MODBUS_MODE; wiring faults
and an extra delay of the module's signal from the configuration (Module.miswire, delay_steps).

The protocol is Modbus TCP as the spec has it (MBAP header, function codes 3, 6 and 16, exception responses),
written out here in a few lines: a module is not pymodbus, and pymodbus's asyncio server costs this process
about 150 us a request, too much beside a 2 kHz loop on two cores. The drivers' side is pymodbus's client, and
tests/drivers/test_device_ends.py holds it against pymodbus's own server serving the documented map.
"""
from __future__ import annotations

import os
import random
import select
import socket
import struct
import time

from drivers.protocol.modbus_map import (FIFO_WIDTH, N_AI, N_REGS, REG_AI, REG_AO, REG_AO_SAFE, REG_COUNT,
                                        REG_FIFO, REG_STATUS, REG_WDOG, volts_to_raw)
from rig.runtime.rt import raise_priority
from sim_backend.emulators import shared as sh

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 1, 2, 3, 4
MAX_DELAY_STEPS = sh.FIFO_SLOTS // 2      # a delayed conversion is still in the FIFO beside the newest entries read


class Module:
    """The module's behaviour behind the registers (sensitivity: accelerometer V per m/s^2; the floor
    accelerometers' sensitivity and channels: floor_V_per_mps2, floor_channels)."""

    def __init__(self, arr, sensitivity_V_per_mps2: float, floor_V_per_mps2: float = 2.0,
                 floor_channels=(4, 5, 6, 7), faults=None, delay_steps: float = 0.0):
        self.arr = arr
        self.regs = [0] * N_REGS
        # per AI channel: (index into a conversion's 8 values: 4 mount then 4 floor accelerations, V per m/s^2)
        self.wiring = [(ch, sensitivity_V_per_mps2) if ch < sh.N_MOUNTS else (None, 0.0) for ch in range(N_AI)]
        for i, ch in enumerate(floor_channels):
            self.wiring[ch] = (sh.N_MOUNTS + i, floor_V_per_mps2)
        self.offset_V = [0.0] * N_AI
        self.noise_V = [0.0] * N_AI
        self.rng = random.Random(0)
        self._noise: list[tuple[int, list[float]]] = [(-1, [0.0] * N_AI)] * sh.FIFO_SLOTS   # per conversion slot
        if faults is not None:
            self.miswire(*faults)
        if not 0 <= delay_steps <= MAX_DELAY_STEPS:
            raise ValueError(f"module delay {delay_steps:g} steps (expected 0 to {MAX_DELAY_STEPS})")
        self.delay_steps = float(delay_steps)
        self.last_request = time.monotonic()
        self.frozen: list[int] | None = None
        # a conversion's registers, made once: each request reads the newest few entries again, and rounding
        # every value every time was most of this process's work (drivers/README.md); kept with its counter and
        # values: a plant started again counts from 0 anew
        self._raw: list[tuple[int, list, list[int]]] = [(-1, [], [])] * sh.FIFO_SLOTS

    def watchdog(self) -> None:
        """The host watchdog: no request for the configured time -> AO to safe values, status bit set."""
        regs = self.regs
        timeout_s = regs[REG_WDOG] * 0.1
        now = time.monotonic()
        if timeout_s > 0 and now - self.last_request > timeout_s:
            regs[REG_AO:REG_AO + 2] = regs[REG_AO_SAFE:REG_AO_SAFE + 2]
            regs[REG_STATUS] |= 1
        self.last_request = now

    def miswire(self, source, factor, offset_mps2, noise_mps2=None) -> None:
        """Wiring faults (rig.config HilConfig ai_*): per AI channel the signal it carries (the channel that
        carries it when right: 0-3 the table's, 4-7 the floor's), a factor on it (0: dead), an offset and extra
        white noise (rms), in that channel's own sensitivity. The identity (0..7, 1, 0, 0) is the rig as
        documented."""
        right = list(self.wiring)
        for ch in range(N_AI):
            i, k = right[source[ch]]
            self.wiring[ch] = (i, k * factor[ch]) if i is not None else (None, 0.0)
            self.offset_V[ch] = offset_mps2[ch] * (right[ch][1] or k)
            self.noise_V[ch] = (noise_mps2[ch] if noise_mps2 is not None else 0.0) * (right[ch][1] or k)

    def noise(self, count: int) -> list[float]:
        """Conversion `count`'s extra noise (V) per channel: drawn once, the same however often it is read."""
        slot = count % sh.FIFO_SLOTS
        c, n = self._noise[slot]
        if c != count:
            n = [self.rng.gauss(0.0, s) if s else 0.0 for s in self.noise_V]
            self._noise[slot] = (count, n)
        return n

    def volts(self, values, count: int = 0) -> list[int]:
        """AI ch0-7 (raw) of conversion `count`: values = 4 mount then 4 floor accelerations (undelayed, those
        of conversion `count` itself: made once per conversion)."""
        slot = count % sh.FIFO_SLOTS
        c, made_of, raw = self._raw[slot]
        if c != count or made_of != values:
            raw = self._volts(values, count)
            self._raw[slot] = (count, list(values), raw)
        return raw

    def _volts(self, values, count: int) -> list[int]:
        noise = self.noise(count) if any(self.noise_V) else self.noise_V
        return [volts_to_raw(values[i] * k + o + n) if i is not None else 32768
                for (i, k), o, n in zip(self.wiring, self.offset_V, noise)]

    def delayed(self, e: int, by_entry: dict) -> list[float]:
        """Conversion newest - e's 8 values as the module delays them (delay_steps, fractional: linear between
        the two conversions around it; before the first conversions, the earliest there is)."""
        k = int(self.delay_steps)
        a = self.delay_steps - k
        older = [by_entry[j] for j in (e + k, e + k + 1) if j in by_entry]
        if not older:
            return [0.0] * (2 * sh.N_MOUNTS)
        x0, x1 = older[0], older[-1]
        return [(1 - a) * u + a * v for u, v in zip(x0, x1)]

    def read(self, address: int, count: int) -> list[int]:
        """The registers address..address+count-1 now (the FIFO entries asked for only)."""
        regs = self.regs
        if self.frozen is not None:
            return self.frozen[address:address + count]
        e0 = max(0, (address - REG_FIFO) // FIFO_WIDTH)
        e1 = max(0, (address + count - 1 - REG_FIFO) // FIFO_WIDTH + 1) if address + count > REG_FIFO else 0
        if self.delay_steps:                       # the entries asked for and the older ones they are delayed from
            lag = int(self.delay_steps) + 2
            newest, accel, fifo = sh.read_fifo(self.arr, 0, max(e1, 1) + lag)
            by_entry = {e: acc for e, c, acc in fifo if c == newest - e >= 0}
            accel = self.delayed(0, by_entry)
            fifo = [(e, c, self.delayed(e, by_entry)) for e, c, _ in fifo if e0 <= e < e1]
            volts = self._volts                    # (values between conversions: made anew)
        else:
            newest, accel, fifo = sh.read_fifo(self.arr, e0, e1)
            volts = self.volts
        regs[REG_AI:REG_AI + N_AI] = volts(accel, newest)
        regs[REG_COUNT] = newest & 0xFFFF
        for e, c, acc in fifo:                     # entry e = conversion newest - e
            base = REG_FIFO + FIFO_WIDTH * e
            if c == newest - e >= 0:
                regs[base] = c & 0xFFFF
                regs[base + 1:base + FIFO_WIDTH] = volts(acc, c)
            else:                                  # not converted yet
                regs[base:base + FIFO_WIDTH] = [(newest + 1) & 0xFFFF] + [32768] * (FIFO_WIDTH - 1)
        return regs[address:address + count]

    def request(self, pdu: bytes) -> bytes | None:
        """The response PDU to one request PDU (None: no answer, the silence knob)."""
        mode = int(self.arr[sh.MODBUS_MODE])
        fc = pdu[0] if pdu else 0
        if mode == sh.SILENCE:
            return None
        if mode == sh.EXCEPTION:
            return bytes((fc | 0x80, DEVICE_FAILURE))
        self.watchdog()
        if mode == sh.STALE:
            if self.frozen is None:
                self.frozen = self.read(0, N_REGS)
        else:
            self.frozen = None
        try:
            if fc == 3:
                address, count = struct.unpack_from(">HH", pdu, 1)
                if not 1 <= count <= 125 or address + count > N_REGS:
                    return bytes((fc | 0x80, ILLEGAL_ADDRESS))
                values = self.read(address, count)
                return struct.pack(f">BB{count}H", 3, 2 * count, *values)
            if fc == 6:
                address, value = struct.unpack_from(">HH", pdu, 1)
                if address >= N_REGS:
                    return bytes((fc | 0x80, ILLEGAL_ADDRESS))
                self.regs[address] = value
                return pdu[:5]
            if fc == 16:
                address, count, nbytes = struct.unpack_from(">HHB", pdu, 1)
                if address + count > N_REGS or nbytes != 2 * count:
                    return bytes((fc | 0x80, ILLEGAL_ADDRESS))
                self.regs[address:address + count] = struct.unpack_from(f">{count}H", pdu, 6)
                return pdu[:5]
        except struct.error:
            return bytes((fc | 0x80, ILLEGAL_VALUE))
        return bytes((fc | 0x80, ILLEGAL_FUNCTION))


def answer(module: Module, buf: bytearray, garbage: bool) -> bytes:
    """The responses to the complete requests in buf (taken from it): MBAP header + PDU each."""
    out = []
    while len(buf) >= 7:
        tid, pid, length, unit = struct.unpack_from(">HHHB", buf, 0)
        if len(buf) < 6 + length:
            break
        pdu = bytes(buf[7:6 + length])
        del buf[:6 + length]
        resp = module.request(pdu)
        if resp is None:
            continue
        frame = struct.pack(">HHHB", tid, pid, len(resp) + 1, unit) + resp
        out.append(bytes(random.getrandbits(8) for _ in frame) if garbage else frame)
    return b"".join(out)


def serve(arr, port_conn, sensitivity_V_per_mps2: float, priority: int = 0, host: str = "127.0.0.1",
          floor_V_per_mps2: float = 2.0, floor_channels=(4, 5, 6, 7), faults=None, delay_steps: float = 0.0) -> None:
    """Process entry: bind an ephemeral port on loopback, report it on port_conn, serve until the parent
    goes away or sends anything on port_conn (faults: Module.miswire's arguments; delay_steps: conversions the
    module's signal lags, [hil] extra_delay_s)."""
    module = Module(arr, sensitivity_V_per_mps2, floor_V_per_mps2, floor_channels, faults, delay_steps)
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((host, 0))
    srv.listen(4)
    port_conn.send(srv.getsockname()[1])
    raise_priority(priority)
    parent = os.getppid()
    conns: dict[socket.socket, bytearray] = {}
    try:
        while os.getppid() == parent and not port_conn.poll():
            r, _, _ = select.select([srv, *conns], [], [], 0.05)
            for s in r:
                if s is srv:
                    c, _ = srv.accept()
                    c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    conns[c] = bytearray()
                    continue
                try:
                    data = s.recv(65536)
                except OSError:
                    data = b""
                if not data:
                    s.close()
                    del conns[s]
                    continue
                buf = conns[s]
                buf += data
                out = answer(module, buf, int(arr[sh.MODBUS_MODE]) == sh.GARBAGE)
                if out:
                    try:
                        s.sendall(out)
                    except OSError:
                        pass
    finally:
        for c in conns:
            c.close()
        srv.close()

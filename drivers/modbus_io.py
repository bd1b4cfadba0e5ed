"""Modbus TCP analog input module (ADAM-6024-style registers, eight AI channels) carrying the four mount
accelerometers (AI ch0-3) and, when fitted ([sensors] floor_accel), the four floor accelerometers (ch4-7), on
pymodbus. All channels of one conversion are sampled together, so the floor and the mount values share one
time stamp and one conversion counter.

Request/response never runs inside the control period: a driver-owned thread polls AI ch0-7 + the conversion
counter (one read of 40001-40010) every poll period and keeps the latest sample with its time stamp. The loop
only picks that sample up. A sample is new when the module's conversion counter moved; no new sample for
stale_s (silence, exceptions, garbage, frozen module) is a fault naming the module and the last error.
open() configures the module's host watchdog (40021) and clears its status (40010).
Device map: drivers/devicemaps/adam6024_modbus.md.
"""
from __future__ import annotations

import logging
import threading
import time

from drivers.protocol.modbus_map import (FIFO_DEPTH, FIFO_WIDTH, REG_AI, REG_COUNT, REG_FIFO, REG_STATUS,
                                        REG_WDOG, raw_to_volts, volts_to_raw)  # noqa: F401 (volts_to_raw: API)
from drivers.rt import TriggeredPoller
from rig.errors import DeviceError

N_READ = 10                     # 40001-40010 in one request
# Conversion FIFO (modules converting on SYNC, [drivers] accel_sync_fifo): each poll reads 40001-40010 and the
# newest FIFO_FIRST entries in one request (123 registers; FC 3 allows 125); after a stall it reads further
# entries, FIFO_CHUNK at a time (117 registers), until nothing is missing (or the FIFO ends)
FIFO_FIRST, FIFO_CHUNK = 11, 13
N_READ_FIFO = REG_FIFO + FIFO_FIRST * FIFO_WIDTH
KEEP_CONVERSIONS = 256          # conversions kept by counter: a loop stall up to this long is replayed exactly


class ModbusAnalogIO(TriggeredPoller):
    def __init__(self, *, host: str, port: int, unit: int, channels: list[int], names: list[str],
                 V_per_mps2, timeout_s: float, watchdog_s: float, stale_s: float, poll_s: float,
                 priority: int = 0, keep_latency: int = 1 << 16, fifo: bool = False):
        self.host, self.port, self.unit = host, port, unit
        self.channels = list(channels)
        self.names = list(names)
        # sensitivity per channel (one number: the same for all)
        self.k = tuple(V_per_mps2) if isinstance(V_per_mps2, (list, tuple)) else (float(V_per_mps2),) * len(channels)
        self.timeout_s = timeout_s
        self.watchdog_s = watchdog_s
        self.stale_ns = int(stale_s * 1e9)
        self.poll_ns = int(poll_s * 1e9)
        self.priority = priority
        self.where = f"modbus_tcp {host}:{port} unit {unit}"
        self.client = None
        # the latest sample: (accel_mps2 tuple, sample time ns, raw tuple); replaced whole, so reads are atomic
        self.sample: tuple = ((0.0,) * len(channels), 0, (32768,) * len(channels))
        self.last_error = ""
        self.errors = 0
        self.polls = 0
        self._counter = -1
        # fifo: every conversion by its counter (accel_mps2 tuples), the newest counter; see conversions_since
        self.fifo = fifo
        self.n_read = N_READ_FIFO if fifo else N_READ
        self.conversions: dict[int, tuple] = {}
        self.newest = -1
        self.lost_conversions = 0      # handed over interpolated (not fetched before they left the FIFO)
        self.watchdog_tripped = False
        self.asked_ns = 0              # first request since the last new sample (0 = none outstanding)
        self._stop = threading.Event()
        self._trigger = threading.Event()
        self._thread: threading.Thread | None = None
        self.latency_ns = [0] * keep_latency   # ring of request round trips, for the benchmark
        self.n_latency = 0

    def open(self) -> None:
        from pymodbus.client import ModbusTcpClient
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)   # our own one-line faults say it
        self.client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0,
                                      reconnect_delay=0.0)
        if not self.client.connect():
            self.client = None
            raise DeviceError(f"{self.where}: cannot connect (analog I/O module not answering)")
        try:
            wd = round(self.watchdog_s * 10)
            for addr, val, what in ((REG_WDOG, wd, "host watchdog 40021"), (REG_STATUS, 0, "status 40010")):
                r = self.client.write_register(addr, val, device_id=self.unit)
                if r.isError():
                    raise DeviceError(f"{self.where}: configuring the {what} failed ({r})")
            r = self.client.read_holding_registers(REG_WDOG, count=1, device_id=self.unit)
            if r.isError() or r.registers[0] != wd:
                raise DeviceError(f"{self.where}: host watchdog 40021 reads back {r}, expected {wd}")
            self.watchdog_tripped = False
            self._poll_once()
            if self.sample[1] == 0:
                raise DeviceError(f"{self.where}: no valid first sample ({self.last_error})")
        except DeviceError:
            self.close()
            raise
        except Exception as e:                      # noqa: BLE001 - pymodbus raises its own types
            self.close()
            raise DeviceError(f"{self.where}: set-up failed ({e.__class__.__name__}: {e})") from None
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="modbus-poller", daemon=True)
        self._thread.start()

    def _poll_once(self) -> bool:
        """One request; True when it brought a new sample."""
        t0 = time.monotonic_ns()
        if not self.asked_ns:
            self.asked_ns = t0
        try:
            r = self.client.read_holding_registers(REG_AI, count=self.n_read, device_id=self.unit)
        except Exception as e:                      # noqa: BLE001 - timeouts, garbage, closed socket
            self.errors += 1
            text = str(e)
            self.last_error = (f"no valid response within {self.timeout_s * 1e3:g} ms" if "No response" in text
                               else f"{e.__class__.__name__}: {text}")
            if not self.client.connected:
                self.client.connect()
            return False
        t1 = time.monotonic_ns()
        self.latency_ns[self.n_latency % len(self.latency_ns)] = t1 - t0
        self.n_latency += 1
        self.polls += 1
        if r.isError():
            self.errors += 1
            code = getattr(r, "exception_code", None)
            self.last_error = f"exception response {code}" if code is not None else str(r)
            return False
        regs = r.registers
        if len(regs) == self.n_read and regs[REG_STATUS] & 1:
            self.watchdog_tripped = True            # latched in the module until open() clears it
        if len(regs) != self.n_read:
            self.errors += 1
            self.last_error = f"{len(regs)} registers (expected {self.n_read})"
            return False
        if regs[REG_COUNT] == self._counter:
            return False                            # no new conversion: keep the old time stamp
        self._counter = regs[REG_COUNT]
        self.last_error = ""
        self.asked_ns = 0
        raw = tuple(regs[REG_AI + ch] for ch in self.channels)
        if self.fifo:
            self._take_fifo(regs)
        self.sample = (tuple(raw_to_volts(x) / k for x, k in zip(raw, self.k)), t1, raw)
        return True

    def _take_fifo(self, regs) -> None:
        """Store the FIFO's conversions by counter; after a stall, fetch the older entries too. The newest
        counter is published last, so a reader never sees it before its conversion."""
        conv = self.conversions
        newest = regs[REG_COUNT]
        have = self.newest
        missing = self._store(regs, REG_FIFO, FIFO_FIRST, newest, have)
        entry = FIFO_FIRST
        while missing and entry < FIFO_DEPTH:        # a stall: the conversions further back, in chunks
            n = min(FIFO_CHUNK, FIFO_DEPTH - entry)
            try:
                r = self.client.read_holding_registers(REG_FIFO + FIFO_WIDTH * entry, count=FIFO_WIDTH * n,
                                                       device_id=self.unit)
            except Exception:                           # noqa: BLE001 - the next poll tries again
                break
            if r.isError() or len(r.registers) != FIFO_WIDTH * n:
                break
            missing = self._store(r.registers, 0, n, newest, have)
            entry += n
        if len(conv) > KEEP_CONVERSIONS + FIFO_DEPTH:
            for c in [c for c in conv if ((newest - c) & 0xFFFF) >= KEEP_CONVERSIONS]:
                del conv[c]
        self.newest = newest

    def _store(self, regs, base: int, entries: int, newest: int, have: int) -> bool:
        """Take `entries` FIFO entries from regs[base:]; True if conversions after `have` are still missing."""
        conv, k, ch = self.conversions, self.k, self.channels
        oldest = newest
        for e in range(entries):
            b = base + FIFO_WIDTH * e
            c = regs[b]
            if ((newest - c) & 0xFFFF) >= FIFO_DEPTH:    # an entry not filled yet
                continue
            if c not in conv:
                conv[c] = tuple(raw_to_volts(regs[b + 1 + j]) / kj for j, kj in zip(ch, k))
            if ((newest - c) & 0xFFFF) > ((newest - oldest) & 0xFFFF):
                oldest = c
        return have >= 0 and 1 < ((oldest - have) & 0xFFFF) < 0x8000     # a gap after `have`

    def conversions_since(self, counter: int) -> tuple[int, int, tuple, list]:
        """(n, newest counter, newest accel, older): n = conversions after `counter` up to the newest fetched (counter -1: the
        first read, n = 1), older = the accel tuples of the n - 1 before the newest, oldest first. A conversion
        missing here (a stall longer than the FIFO) is interpolated, so the count - the time base of the
        controllers' integration - stays exact."""
        newest = self.newest
        conv = self.conversions
        if newest < 0 or newest not in conv:
            return 0, counter, self.sample[0], []
        last = conv[newest]
        if counter < 0:
            return 1, newest, last, []
        n = (newest - counter) & 0xFFFF
        if n == 0 or n > KEEP_CONVERSIONS:
            return (0 if n == 0 else 1), newest, last, []
        older = []
        prev = conv.get(counter, last)
        for j in range(n - 1, 0, -1):
            a = conv.get((newest - j) & 0xFFFF)
            if a is None:                           # lost: hold the trend towards the newest
                a = tuple(x + (y - x) / (j + 1) for x, y in zip(prev, last))
                self.lost_conversions += 1
            older.append(a)
            prev = a
        return n, newest, last, older

    def check(self, now_ns: int) -> str | None:
        acc, t_ns, raw = self.sample
        # the module was asked and its newest sample is older than the limit: measured from the sample, as
        # the loop's sensor check measures it, so a silent module is named here first (not as a stale mount)
        if self.asked_ns and now_ns - t_ns > self.stale_ns:
            why = f"; last error: {self.last_error}" if self.last_error else "; values not updating"
            return (f"{self.where}: no new sample for {(now_ns - t_ns) / 1e6:.1f} ms "
                    f"(limit {self.stale_ns / 1e6:g} ms){why}")
        if self.watchdog_tripped:
            return (f"{self.where}: module host watchdog tripped (no request for {self.watchdog_s:g} s): "
                    f"outputs at their safe values")
        for i, x in enumerate(raw):
            if x == 0 or x == 65535:
                return f"{self.where}: AI ch{self.channels[i]} ({self.names[i]}) at the +-10 V rail (over range)"
        return None

    def close(self) -> None:
        self._stop_thread()
        if self.client is not None:
            self.client.close()
            self.client = None

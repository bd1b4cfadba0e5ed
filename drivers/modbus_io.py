"""Modbus TCP analog input module (ADAM-6024-style registers, eight AI channels) carrying the mount
accelerometers (AI ch0-3) and, when fitted ([sensors] floor_accel), the floor accelerometers (ch4-7), on
pymodbus, in an I/O process of its own (drivers/process.py). All channels of one conversion are sampled
together: the floor and the mount values share one conversion (counter, time stamp).

Conversions on SYNC (`fifo`, [drivers] accel_sync_fifo): the module converts on each CAN SYNC into a FIFO of its
last 64 conversions with their counters. The process wakes on each SYNC the valves' I/O sends (a futex in the
exchange block), waits `fetch_delay_s` (the module's conversion time), and every `fetch_every` SYNCs reads the
counter and the newest `fetch_every` + 1 FIFO entries in one request (after a stall the entries further back,
in blocks); a reply without the new conversion is asked again once it is due. Every conversion, in order,
goes into the block's conversion ring by its counter (unwrapped from 16 bits): the loop's kernel steps the
controllers once per conversion. When the design takes a conversion two or more periods after its SYNC
([drivers] accel_delay_periods), a fast reply is held until the loop has written its commands for the period
before the one due to take it (counted from the period whose commands the SYNC carried, the valves' row), so no
period finds two conversions and the next none; by time while the loop is not running (hold_s,
drivers.accel_hold_s). The process goes on meanwhile: the next SYNC's fetch may come before the release. One lost
from the FIFO before it was fetched is interpolated and counted.
Without a FIFO the module's latest value (AI ch0-7 and its counter) is read once per loop period.

Faults (the device's line in the block): no new conversion for stale_s (silence, exceptions, garbage, frozen
module: with the last error), an input at the rail, the host watchdog tripped. open() configures the host
watchdog (40021) and clears the status (40010). Device map: drivers/devicemaps/adam6024_modbus.md.
The conversion from registers to m/s^2 per channel: drivers/conversion.py.
"""
from __future__ import annotations

import logging
import struct
import time
from collections import deque

import numpy as np

from drivers import conversion
from drivers.process import IODevice
from drivers.protocol.modbus_map import (FIFO_DEPTH, FIFO_WIDTH, REG_AI, REG_COUNT, REG_FIFO, REG_STATUS,
                                        REG_WDOG, raw_to_volts)
from rig.errors import DeviceError
from rig.runtime import exchange as ex
from rig.runtime.rt import raise_priority

N_LATEST = 10                   # 40001-40010: AI ch0-7, the counter, the status
FIFO_CHUNK = 13                 # entries per request reaching further back after a stall (117 registers)
DELAY_STEP_NS = 10_000          # the learnt fetch delay: +10 us after a request too early, -2 us after one in time
STATUS_EVERY = 50               # with the FIFO: the status register (host watchdog) every this many polls
MAX_BEHIND = 1024               # conversions taken after a stall at most (beyond the FIFO: interpolated)


def registers_response():
    """pymodbus's read-registers response, decoded with one unpack and named in a short text: pymodbus's own
    unpacks each register apart and formats every response for a debug line even when nothing logs
    (drivers/README.md). Registered with the client, pymodbus's way for a response of one's own."""
    from pymodbus.exceptions import ModbusIOException
    from pymodbus.pdu.register_message import ReadHoldingRegistersResponse

    class RegistersResponse(ReadHoldingRegistersResponse):
        def decode(self, data: bytes) -> None:
            n = int(data[0])
            if n >= len(data):                  # as pymodbus's own
                raise ModbusIOException(f"byte_count {n} > length of packet {len(data)}",
                                        function_code=self.function_code)
            self.registers = list(struct.unpack_from(f">{n // 2}H", data, 1))

        def __str__(self) -> str:
            return f"{type(self).__name__}(dev_id={self.dev_id}, {len(self.registers)} registers)"

    return RegistersResponse


class AnalogIO(IODevice):
    """spec: host, port, unit, channels (conversion rows: AI ch -> m/s^2, mount accelerometers then floor
    ones), names (per channel), timeout_s, watchdog_s, stale_s, period_s (the loop's), fifo, fetch_every,
    fetch_delay_s, hold_s, sync_device (the valves' row: the SYNC's time), priority."""

    def __init__(self, spec: dict, block: ex.Block) -> None:
        super().__init__(spec, block)
        self.host, self.port, self.unit = spec["host"], int(spec["port"]), int(spec["unit"])
        self.chs = conversion.from_dict(spec["channels"])
        self.names = list(spec["names"])
        self.timeout_s = float(spec["timeout_s"])
        self.watchdog_s = float(spec["watchdog_s"])
        self.stale_ns = int(spec["stale_s"] * 1e9)
        self.period_ns = int(round(spec["period_s"] * 1e9))
        self.fifo = bool(spec.get("fifo", True))
        self.every = max(1, int(spec.get("fetch_every", 1)))
        # the request after a SYNC: fetch_delay_s at first, then learnt (a request that comes before the
        # conversion costs a round trip for nothing; one that comes late delays the conversion)
        self.delay_ns = self.min_delay_ns = int(round(spec.get("fetch_delay_s", 0.0) * 1e9))
        # a conversion is handed to the loop no sooner than the design takes it (accel_delay_periods after the
        # period whose commands its SYNC carried): never a period early, so a fast reply cannot leave the next
        # period without one. The loop not running: no sooner than hold_s after its SYNC
        self.hold_ns = int(round(spec.get("hold_s", 0.0) * 1e9))
        self.not_before_ns = 0
        # ... and, the loop running, only once it wrote its commands for the period hold_periods after the one whose
        # commands the SYNC carried: it took its inputs for the period before the one due to take the conversion
        # (a loop woken late, or a SYNC sent late, would otherwise have it taken a period early, and none after)
        self.hold_periods = int(spec.get("hold_periods", 0))
        self.after_T = 0.0
        self._loop_T = int(block.io[ex.H_CMD]) + ex.C_T     # the newest period the loop wrote commands for
        self._held: deque = deque()    # [release ns, arrival ns, [(c16, values)], loop period after, last ns]
        self.sync_row = spec.get("sync_device")
        self.priority = int(spec.get("priority", 0))
        self.where = f"modbus_tcp {self.host}:{self.port} unit {self.unit}"
        self.first, self.n_read = (REG_FIFO, (self.every + 1) * FIFO_WIDTH) if self.fifo else (REG_AI, N_LATEST)
        self._polls = 0
        self.client = None
        self.last_error = ""
        self.errors = 0
        self.count = -1.0              # the newest conversion published (unwrapped counter)
        self._c16 = -1                 # the module's 16-bit counter last seen
        self._c16_pub = -1             # ... and last published
        self._last = None              # the newest conversion's values taken (interpolation of lost ones)
        self.watchdog_tripped = False
        self.sample_ns = 0             # when the newest conversion came
        self.asked_ns = 0              # first request since the last new conversion (0 = none outstanding)
        self.rail = ""
        self._ts = np.zeros(block.n)
        self._syncs = 0
        self._said = ""

    def open(self) -> None:
        from pymodbus.client import ModbusTcpClient
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)   # our own one-line faults say it
        # set-up with patience (a module answering its first requests while the other devices start), the
        # cycle with timeout_s
        self.client = ModbusTcpClient(self.host, port=self.port, timeout=max(self.timeout_s, 1.0), retries=0,
                                      reconnect_delay=0.0)
        self.client.register(registers_response())
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
            self.poll()
            if self.count < 0:
                raise DeviceError(f"{self.where}: no valid first sample ({self.last_error})")
            self.client.comm_params.timeout_connect = self.timeout_s
        except DeviceError:
            self.close()
            raise
        except Exception as e:                      # noqa: BLE001 - pymodbus raises its own types
            self.close()
            raise DeviceError(f"{self.where}: set-up failed ({e.__class__.__name__}: {e})") from None

    # ---- the cycle ----------------------------------------------------------------------------------------
    def run(self, stop) -> None:
        raise_priority(self.priority)
        P = self.period_ns
        block = self.block
        sync_row = block.device_row(self.sync_row) if self.sync_row is not None else None
        due = time.monotonic_ns() + P
        seen = int(block.futex[ex.FUTEX_SYNC])
        fetched = 0                      # the block of SYNCs last fetched for (fetch_every per block)
        while not stop.is_set():
            if self.fifo and self.sync_row is not None:    # each SYNC (or, without one, every other period)
                # `seen` is the count at the last wake, so a SYNC sent while this one's fetch was still going
                # on wakes it at once: re-reading the count here would sleep through it, a period late
                self._wait_sync(seen, 2 * P)
                now = int(block.futex[ex.FUTEX_SYNC])
                step = (now - seen) & 0xFFFFFFFF
                self._syncs += step or 1                         # a timeout (no SYNC) counts as one
                seen = now
                if self._syncs // self.every == fetched:
                    self._idle()
                    continue
                fetched = self._syncs // self.every
                t_sync = int(sync_row[ex.D_SAMPLE])
                # held only for the SYNC just sent (after a hold-up, several SYNCs at once, what came is due): the
                # loop running, until it wrote its commands for the period before the one due to take it, else by time
                t_cmd = sync_row[ex.D_PERIOD]
                hold = self.hold_ns and step == 1
                self.after_T = t_cmd + self.hold_periods * P if hold and t_cmd > 0 else 0.0
                self.not_before_ns = t_sync + self.hold_ns if hold and not self.after_T else 0
                self._sleep(max(t_sync + self.delay_ns, time.monotonic_ns()))
                end = time.monotonic_ns() + P // 2
                first = True
                while not self.poll() and time.monotonic_ns() < end and not stop.is_set():
                    if first:                                  # too early: ask later after the next SYNCs
                        self.delay_ns = min(self.delay_ns + DELAY_STEP_NS, P // 2)
                        first = False
                    self._sleep(time.monotonic_ns() + P // 8)          # not converted yet: once more
                if first:                                      # in at once: try a little earlier next time
                    self.delay_ns = max(self.delay_ns - DELAY_STEP_NS // 5, self.min_delay_ns)
                self._watch_status(fetched)
            else:                                           # the latest value, once per loop period
                self.sleep_until(due)
                due += P
                self.poll()
                self._watch_status(self._polls)
            self._idle()

    def _wait_sync(self, seen: int, timeout_ns: int) -> None:
        """Sleep until a SYNC after `seen` (the futex count) or timeout_ns, handing held conversions on as they
        fall due."""
        block = self.block
        end = time.monotonic_ns() + timeout_ns
        while True:
            now = self._release_due()
            until = min(end, self._held[0][0]) if self._held else end
            if until > now:
                block.wait(ex.FUTEX_SYNC, seen, (until - now) * 1e-9)
            if int(block.futex[ex.FUTEX_SYNC]) != seen or time.monotonic_ns() >= end:
                self._release_due()
                return

    def _sleep(self, t_ns: int) -> None:
        """Sleep until t_ns, handing held conversions on as they fall due."""
        while self._held and self._held[0][0] < t_ns:
            self.sleep_until(self._held[0][0])
            self._release_due()
        self.sleep_until(t_ns)
        self._release_due()

    def _hand(self, t1: int, convs: list) -> None:
        """New conversions [(c16, values, lost)] come in at t1: to the loop now, or held until not_before (behind any
        held before them: they go out in order)."""
        if convs and convs[-1][1] is not None:
            self._last = convs[-1][1]
        self._release_due()
        release = max(self.not_before_ns, self._held[-1][0] if self._held else 0, t1)
        if self._held or release > t1 or (self.after_T and self._loop_before(self.after_T, t1)):
            self._held.append([release, t1, convs, self.after_T, release + self.period_ns])
        else:
            self._publish_all(t1, convs)

    def _release_due(self) -> int:
        """The held conversions whose time has come, to the loop; returns the time now."""
        now = time.monotonic_ns()
        while self._held and self._held[0][0] <= now:
            head = self._held[0]
            if head[3] and now < head[4] and self._loop_before(head[3], now):
                head[0] = now + self.period_ns // 16         # the loop is late: look again shortly
                break
            _, t1, convs, _, _ = self._held.popleft()
            self._publish_all(t1, convs)
        return now

    def _loop_before(self, T: float, now: int) -> bool:
        """Whether the running loop has not yet written commands for a period starting at T or later (not
        running: False, the hold is by time alone)."""
        newest = self.io[self._loop_T]
        return 0 < newest < T and now - newest < 4 * self.period_ns

    def _watch_status(self, k: int) -> None:
        """With the FIFO: the status register every STATUS_EVERY fetches, after the fetch's conversion went out
        (read before it, its round trip held every 50th conversion up by that long)."""
        if self.fifo and k % STATUS_EVERY == 0:
            self._status()

    def _idle(self) -> None:
        self.report(self.check(time.monotonic_ns()))
        self._row[ex.D_SAMPLE] = float(self.sample_ns)
        if not self._fault_text and self.last_error != self._said:     # why it has nothing new, if it has not
            self._said = self.last_error
            self.block.set_text(self.d, self.last_error)
        self.beat()

    def poll(self) -> bool:
        """One request (with the FIFO: its newest entries, the newest first; without: AI ch0-7, the counter and
        the status); True when it brought a new conversion (published, with any older ones it had not
        published). With the FIFO the status (the host watchdog's bit) is read apart (_watch_status)."""
        t0 = time.monotonic_ns()
        if not self.asked_ns:
            self.asked_ns = t0
        self._polls += 1
        try:
            r = self.client.read_holding_registers(self.first, count=self.n_read, device_id=self.unit)
        except Exception as e:                      # noqa: BLE001 - timeouts, garbage, closed socket
            self.errors += 1
            text = str(e)
            self.last_error = (f"no valid response within {self.timeout_s * 1e3:g} ms" if "No response" in text
                               else f"{e.__class__.__name__}: {text}")
            if not self.client.connected:
                self.client.connect()
            return False
        t1 = time.monotonic_ns()
        self.stat((t1 - t0) * 1e-3)
        if r.isError():
            self.errors += 1
            code = getattr(r, "exception_code", None)
            self.last_error = f"exception response {code}" if code is not None else str(r)
            return False
        regs = r.registers
        if len(regs) != self.n_read:
            self.errors += 1
            self.last_error = f"{len(regs)} registers (expected {self.n_read})"
            return False
        if not self.fifo and regs[REG_STATUS] & 1:
            self.watchdog_tripped = True            # latched in the module until open() clears it
        c16 = regs[0] if self.fifo else regs[REG_COUNT]    # entry 0: the newest conversion
        if c16 == self._c16:
            return False                            # no new conversion yet
        back = (self._c16 - c16) & 0xFFFF
        if self._c16 >= 0 and back < 0x8000:        # older than one already taken: never published as new
            self.errors += 1
            self.last_error = f"a reply {back} conversions older than the newest taken: ignored"
            return False
        self.last_error = ""
        self.asked_ns = 0
        self.sample_ns = t1
        if not self.fifo:
            convs = [(c16, self._values([regs[REG_AI + ch] for ch in range(8)]), False)]
        elif self._c16 < 0:
            convs = [(c16, self._values(regs[1:FIFO_WIDTH]), False)]
        else:
            convs = self._take_fifo(regs, c16)
        self._c16 = c16
        self._hand(t1, convs)
        return True

    def _status(self) -> bool:
        """The module's status register (the host watchdog's bit); False when the request failed."""
        try:
            r = self.client.read_holding_registers(REG_STATUS, count=1, device_id=self.unit)
        except Exception as e:                      # noqa: BLE001 - as in poll
            self.last_error = f"{e.__class__.__name__}: {e}"
            return False
        if r.isError():
            return False
        if r.registers[0] & 1:
            self.watchdog_tripped = True            # latched in the module until open() clears it
        return True

    def _take_fifo(self, regs, newest: int) -> list:
        """The conversions [(c16, values, lost)] after the last one taken up to `newest`, from the FIFO entries (newest
        first): those in this reply, then after a stall the ones further back, in blocks; one not in the FIFO any more
        is interpolated (counted in lost_conversions)."""
        want = min((newest - self._c16) & 0xFFFF, MAX_BEHIND)    # new conversions
        got = self._entries(regs, 0, self.every + 1, newest)
        entry = self.every + 1
        while len(got) < min(want, FIFO_DEPTH) and entry < FIFO_DEPTH:     # a stall: further back
            n = min(FIFO_CHUNK, FIFO_DEPTH - entry)
            try:
                r = self.client.read_holding_registers(REG_FIFO + FIFO_WIDTH * entry, count=FIFO_WIDTH * n,
                                                       device_id=self.unit)
            except Exception:                           # noqa: BLE001 - the next poll tries again
                break
            if r.isError() or len(r.registers) != FIFO_WIDTH * n:
                break
            got.update(self._entries(r.registers, 0, n, newest))
            entry += n
        convs = [((newest - j) & 0xFFFF, got.get((newest - j) & 0xFFFF)) for j in range(want - 1, -1, -1)]
        values = [None if raw is None else self._values(raw) for _, raw in convs]
        for j, v in enumerate(values):                  # lost: on the line from the one before to the next known
            if v is None:
                self.counted(0, 1)
                k = next((k for k in range(j + 1, len(values)) if values[k] is not None), None)
                a = values[j - 1] if j else self._last
                b = values[k] if k is not None else a
                f = 1.0 / (k - j + 1) if k is not None else 0.0
                values[j] = a if a is None else [x + f * (y - x) for x, y in zip(a, b)]
        return [(c, v, raw is None) for (c, raw), v in zip(convs, values)]

    @staticmethod
    def _entries(regs, base: int, entries: int, newest: int) -> dict:
        """counter -> the AI ch0-7 registers of the FIFO entries in regs[base:] (those already converted)."""
        out = {}
        for e in range(entries):
            b = base + FIFO_WIDTH * e
            c = regs[b]
            if ((newest - c) & 0xFFFF) < FIFO_DEPTH:
                out[c] = regs[b + 1:b + FIFO_WIDTH]
        return out

    def _values(self, raw) -> list[float]:
        """The channels' values of one conversion (AI ch0-7 registers): the per-channel conversion
        (drivers/conversion.py); a channel at a rail is named for the fault check."""
        self.rail = next((f"AI ch{c.source} ({name})" for c, name in zip(self.chs, self.names)
                          if raw[c.source] in (0, 65535)), "")
        return conversion.apply(self.chs, [raw_to_volts(x) for x in raw])

    def _publish_all(self, t1: int, convs: list) -> None:
        """Conversions [(c16, values, lost)] that came in at t1 into the block, in order."""
        self._ts[:] = t1
        for c16, values, lost in convs:
            self._publish(c16, values, lost)

    def _publish(self, c16: int, values, lost: bool = False) -> None:
        """One conversion into the block (the channels' values), its counter unwrapped from 16 bits; one lost from
        the FIFO (values: its estimate) marked as such first (the kernel then suspends isolation and restarts the
        floor feedforward: rig/runtime/kernel.py _after_loss)."""
        if values is None:                              # (nothing known before it: lost at the very start)
            return
        self.count = c16 if self.count < 0 else self.count + ((c16 - self._c16_pub) & 0xFFFF)
        self._c16_pub = c16
        self.counted(1)
        if lost:
            ex.mark_lost(self.io, float(self.count))
        ex.put_conversion(self.io, float(self.count), self._ts, np.asarray(values, dtype=np.float64))

    def check(self, now_ns: int) -> str | None:
        # asked, and the newest conversion older than the limit: named here first (not as a stale mount)
        if self.asked_ns and now_ns - self.sample_ns > self.stale_ns:
            why = f"; last error: {self.last_error}" if self.last_error else "; values not updating"
            return (f"{self.where}: no new sample for {(now_ns - self.sample_ns) / 1e6:.1f} ms "
                    f"(limit {self.stale_ns / 1e6:g} ms){why}")
        if self.watchdog_tripped:
            return (f"{self.where}: module host watchdog tripped (no request for {self.watchdog_s:g} s): "
                    f"outputs at their safe values")
        if self.rail:
            return f"{self.where}: {self.rail} at the +-10 V rail (over range)"
        return None

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

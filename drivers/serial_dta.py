"""Serial displacement-transducer amplifier (DTA-4, RS-232/485, ASCII), four channels, on pyserial, in an I/O
process of its own (drivers/process.py).

The process asks `RD` at the transducer's own rate (`rate_hz`: what its line allows, below the loop's rate), with
`offset_s` >= 0 on the loop's grid (`request_due`: after the start of a period the loop wrote in the block's
commands), and parses the replies with drivers/protocol/dta.py (garbage and partial frames are skipped or
completed, never raised). Each frame with a new sequence number goes into the block's transducer part, stamped with its
arrival: the loop holds it between frames and checks its age against the transducer's own staleness limit.
Faults (the device's line in the block): a channel reporting UR/OR/NP, an `$E` error reply, or no new sample
(sequence number) for stale_s. The conversion from the frame's micrometres per channel: drivers/conversion.py.
Device map and protocol: drivers/devicemaps/dta4_serial.md.
"""
from __future__ import annotations

import time

import numpy as np

from drivers import conversion
from drivers.process import IODevice
from drivers.protocol import dta as proto
from rig.errors import DeviceError
from rig.runtime import exchange as ex
from rig.runtime.rt import raise_priority


def request_due(t_ns: int, loop_start_ns: int, loop_period_ns: int, offset_ns: int) -> int:
    """The first instant from t_ns on that lies offset_ns after a start of the loop's periods (one of them at
    loop_start_ns); t_ns itself where there is no grid (offset_ns < 0, or the loop not running: loop_start_ns 0)."""
    if offset_ns < 0 or loop_start_ns <= 0:
        return t_ns
    on = loop_start_ns + offset_ns % loop_period_ns
    return on + -(-(t_ns - on) // loop_period_ns) * loop_period_ns


class TransducerIO(IODevice):
    """spec: port, baud, names, channels (conversion rows: DTA-4 channel index -> m), stale_s, rate_hz,
    reply_timeout_s, priority; period_s (the loop's) and offset_s (-1: no grid; else every whole number of
    the loop's periods, offset_s after one starts: request_due)."""

    def __init__(self, spec: dict, block: ex.Block) -> None:
        super().__init__(spec, block)
        self.path = spec["port"]
        self.baud = int(spec["baud"])
        self.names = list(spec["names"])
        self.chs = conversion.from_dict(spec["channels"])
        self.stale_ns = int(spec["stale_s"] * 1e9)
        self.period_ns = int(round(1e9 / float(spec["rate_hz"])))
        self.offset_ns = int(round(float(spec.get("offset_s", -1.0)) * 1e9))
        self.loop_period_ns = int(round(float(spec.get("period_s", 0.0)) * 1e9))
        if self.offset_ns < 0 or self.loop_period_ns <= 0:
            self.offset_ns = -1
        else:                                      # a whole number of the loop's periods, at most rate_hz
            self.period_ns = -(-self.period_ns // self.loop_period_ns) * self.loop_period_ns
        self.reply_timeout_s = float(spec.get("reply_timeout_s", 0.01))
        self.priority = int(spec.get("priority", 0))
        self.where = f"serial DTA-4 {self.path}"
        self.ser = None
        self.parser = proto.FrameParser()
        self.last_error = ""
        self.device_error = ""
        self.status = ("OK",) * len(self.chs)
        self.ident = None
        self._seq16 = -1
        self.seq = -1.0                # the newest sample published (unwrapped sequence number)
        self.sample_ns = 0
        self.asked_ns = 0              # first request since the last new sample (0 = none outstanding)

    def open(self) -> None:
        import serial
        try:
            self.ser = serial.Serial(self.path, self.baud, timeout=self.reply_timeout_s, write_timeout=0.1)
        except (serial.SerialException, OSError, ValueError) as e:
            raise DeviceError(f"{self.where}: cannot open the port ({e})") from None
        try:
            self.ser.reset_input_buffer()
            self.ident = self._request(b"ID\r", kind="I", tries=20)
            if self.ident is None:
                raise DeviceError(f"{self.where}: no identification reply to 'ID' ({self.last_error or 'silent'})")
            for _ in range(20):
                self.poll()
                if self.seq >= 0:
                    break
            if self.seq < 0:
                raise DeviceError(f"{self.where}: no valid data frame ({self.device_error or self.last_error})")
        except BaseException:
            self.close()
            raise

    def _request(self, cmd: bytes, kind: str, tries: int = 1):
        for _ in range(tries):
            self.ser.write(cmd)
            end = time.monotonic() + self.reply_timeout_s * 5
            while time.monotonic() < end:
                for f in self.parser.feed(self.ser.read(self.ser.in_waiting or 1)):
                    if isinstance(f, proto.OtherFrame) and f.kind == kind:
                        return f
        return None

    def run(self, stop) -> None:
        raise_priority(self.priority)
        P, Pl, off = self.period_ns, self.loop_period_ns, self.offset_ns
        start = int(self.io[ex.H_CMD]) + ex.C_T      # the newest period's start the loop wrote (0: not running)
        due = request_due(time.monotonic_ns() + P, int(self.io[start]), Pl, off)
        while not stop.is_set():
            self.sleep_until(due)
            self.poll()
            now = time.monotonic_ns()
            self.report(self.check(now))
            self.beat()
            due += P
            if due < now:                          # the line (or this process) fell behind: on from now
                due = now + P // 2
            due = request_due(due, int(self.io[start]), Pl, off)

    def poll(self) -> bool:
        """One RD request; True when it brought a new sample (published)."""
        ser = self.ser
        seq0 = self.seq
        t0 = time.monotonic_ns()
        if not self.asked_ns:
            self.asked_ns = t0
        try:
            ser.write(b"RD\r")
            deadline = t0 + int(self.reply_timeout_s * 1e9)
            got = False
            bad0 = self.parser.bad_frames
            while not got and time.monotonic_ns() < deadline:
                data = ser.read(ser.in_waiting or 1)
                if not data:
                    continue
                for f in self.parser.feed(data):
                    got = True
                    self._take(f, t0)
            if not got:
                self.last_error = ("garbled frames (checksum or format)" if self.parser.bad_frames > bad0
                                   else f"no reply within {self.reply_timeout_s * 1e3:g} ms")
                self.counted(0, 1)
        except Exception as e:                      # noqa: BLE001 - port gone, I/O error
            self.last_error = f"{e.__class__.__name__}: {e}"
            time.sleep(self.reply_timeout_s)
        return self.seq != seq0

    def _take(self, f, t0: int) -> None:
        t1 = time.monotonic_ns()
        if isinstance(f, proto.DataFrame):
            self.stat((t1 - t0) * 1e-3)
            self.device_error = ""
            self.last_error = ""
            if f.seq != self._seq16:
                self.seq = f.seq if self.seq < 0 else self.seq + ((f.seq - self._seq16) & 0xFFFF)
                self._seq16 = f.seq
                self.asked_ns = 0
                self.sample_ns = t1
                self.status = tuple(f.status[c.source] for c in self.chs)
                values = conversion.apply(self.chs, f.position_m)
                ex.put_sample(self.io, float(self.seq), float(t1), np.asarray(values, dtype=np.float64))
                self.counted(1)
        elif f.kind == "E":
            self.device_error = ",".join(f.fields)

    def check(self, now_ns: int) -> str | None:
        if self.device_error:
            return f"{self.where}: amplifier reports error {self.device_error}"
        for c, name, st in zip(self.chs, self.names, self.status):
            if st != "OK":
                return f"{self.where} ch{c.source + 1} ({name}): {proto.STATUS_TEXT.get(st, st)}"
        asked = self.asked_ns
        if asked and now_ns - asked > self.stale_ns:        # asked, and no new sample for too long
            why = self.last_error or "sequence number not advancing (frozen amplifier)"
            return (f"{self.where}: no new sample for {(now_ns - self.sample_ns) / 1e6:.1f} ms "
                    f"(limit {self.stale_ns / 1e6:g} ms); {why}")
        return None

    def close(self) -> None:
        if self.ser is not None:
            try:
                self.ser.close()
            except Exception:              # noqa: BLE001
                pass
            self.ser = None

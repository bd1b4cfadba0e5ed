"""Serial displacement-transducer amplifier (DTA-4, RS-232/485, ASCII), four channels, on pyserial.

A driver-owned thread sends `RD` every poll period and parses the replies with drivers/protocol/dta.py
(garbage and partial frames are skipped or completed, never raised). The loop picks up the latest sample.
Faults: a channel reporting UR/OR/NP, an `$E` error reply, or no new sample (sequence number) for stale_s.
Device map and protocol: drivers/devicemaps/dta4_serial.md.
"""
from __future__ import annotations

import threading
import time

from drivers.protocol import dta as proto
from drivers.rt import TriggeredPoller
from rig.errors import DeviceError


class DisplacementAmplifier(TriggeredPoller):
    def __init__(self, *, port: str, baud: int, names: list[str], stale_s: float, poll_s: float,
                 reply_timeout_s: float = 0.01, priority: int = 0, keep_latency: int = 1 << 16,
                 channels: list[int] | None = None):
        self.path = port
        self.baud = baud
        self.names = list(names)
        self.channels = list(range(len(names))) if channels is None else list(channels)   # 0-based, per name
        self.stale_ns = int(stale_s * 1e9)
        self.poll_ns = int(poll_s * 1e9)
        self.priority = priority
        self.reply_timeout_s = reply_timeout_s
        self.where = f"serial DTA-4 {port}"
        self.ser = None
        self.parser = proto.FrameParser()
        n = len(names)
        self.sample: tuple = ((0.0,) * n, 0, ("OK",) * n)     # (position_m, sample time ns, status)
        self.last_error = ""
        self.device_error = ""
        self.ident = None
        self._seq = -1
        self.asked_ns = 0              # first request since the last new sample (0 = none outstanding)
        self._stop = threading.Event()
        self._trigger = threading.Event()
        self._thread: threading.Thread | None = None
        self.latency_ns = [0] * keep_latency
        self.n_latency = 0

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
                self._poll_once()
                if self.sample[1]:
                    break
            if not self.sample[1]:
                raise DeviceError(f"{self.where}: no valid data frame ({self.device_error or self.last_error})")
        except BaseException:
            self.close()
            raise
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="dta4-poller", daemon=True)
        self._thread.start()

    def _request(self, cmd: bytes, kind: str, tries: int = 1):
        for _ in range(tries):
            self.ser.write(cmd)
            end = time.monotonic() + self.reply_timeout_s * 5
            while time.monotonic() < end:
                for f in self.parser.feed(self.ser.read(self.ser.in_waiting or 1)):
                    if isinstance(f, proto.OtherFrame) and f.kind == kind:
                        return f
        return None

    def _poll_once(self) -> bool:
        """One RD request; True when it brought a new sample."""
        ser = self.ser
        seq0 = self._seq
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
        except Exception as e:                      # noqa: BLE001 - port gone, I/O error
            self.last_error = f"{e.__class__.__name__}: {e}"
            time.sleep(self.reply_timeout_s)
        return self._seq != seq0

    def _take(self, f, t0: int) -> None:
        t1 = time.monotonic_ns()
        if isinstance(f, proto.DataFrame):
            self.latency_ns[self.n_latency % len(self.latency_ns)] = t1 - t0
            self.n_latency += 1
            self.device_error = ""
            self.last_error = ""
            if f.seq != self._seq:
                self._seq = f.seq
                self.asked_ns = 0
                ch = self.channels
                self.sample = (tuple(f.position_m[c] for c in ch), t1, tuple(f.status[c] for c in ch))
        elif f.kind == "E":
            self.device_error = ",".join(f.fields)

    def check(self, now_ns: int) -> str | None:
        pos, t_ns, status = self.sample
        if self.device_error:
            return f"{self.where}: amplifier reports error {self.device_error}"
        for i, st in enumerate(status):
            if st != "OK":
                return f"{self.where} ch{self.channels[i] + 1} ({self.names[i]}): {proto.STATUS_TEXT.get(st, st)}"
        asked = self.asked_ns
        if asked and now_ns - asked > self.stale_ns:        # asked, and no new sample for too long
            why = self.last_error or "sequence number not advancing (frozen amplifier)"
            return (f"{self.where}: no new sample for {(now_ns - t_ns) / 1e6:.1f} ms "
                    f"(limit {self.stale_ns / 1e6:g} ms); {why}")
        return None

    def close(self) -> None:
        self._stop_thread()
        if self.ser is not None:
            try:
                self.ser.close()
            except Exception:              # noqa: BLE001
                pass
            self.ser = None

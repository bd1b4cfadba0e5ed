"""ASCII protocol of the 4-channel displacement-transducer amplifier (DTA-4), shared by driver and emulator.

Documented in drivers/devicemaps/dta4_serial.md. Pure Python: no pyserial here, so the emulator and the
property tests use the same framing code as the driver.

Host -> device (ASCII, CR terminated):   RD\\r    read all channels      ID\\r    identification
Device -> host (one line per request):   $<body>*<CS>\\r\\n   CS = two hex digits, XOR of the body bytes
  data:   $D,<seq>,<st1>,<um1>,<st2>,<um2>,<st3>,<um3>,<st4>,<um4>*CS
  ident:  $I,<model>,<serial>,<firmware>*CS
  error:  $E,<code>,<text>*CS
seq: 0-65535, +1 per new conversion (wraps). st: OK, UR (under range), OR (over range), NP (no probe).
um: displacement in micrometres, signed, 3 decimals (e.g. -0123.456).
"""
from __future__ import annotations

from dataclasses import dataclass

N_CHANNELS = 4
MAX_FRAME = 120                 # bytes from '$' to '\n'; longer = garbage
STATUS_CODES = ("OK", "UR", "OR", "NP")
STATUS_TEXT = {"OK": "ok", "UR": "under range", "OR": "over range", "NP": "no probe"}
RANGE_UM = 2000.0               # measuring span +-2 mm; beyond it the amplifier reports UR/OR


def checksum(body: bytes) -> str:
    cs = 0
    for b in body:
        cs ^= b
    return f"{cs:02X}"


def frame(body: str) -> bytes:
    b = body.encode("ascii")
    return b"$" + b + b"*" + checksum(b).encode("ascii") + b"\r\n"


def data_frame(seq: int, status: list[str], um: list[float]) -> bytes:
    fields = [f"D,{seq & 0xFFFF}"]
    for st, v in zip(status, um):
        fields.append(f"{st},{v:+09.3f}")
    return frame(",".join(fields))


def channel_status(um: float) -> str:
    """What the amplifier reports for a probe at um micrometres."""
    if um < -RANGE_UM:
        return "UR"
    if um > RANGE_UM:
        return "OR"
    return "OK"


@dataclass(slots=True)
class DataFrame:
    seq: int
    status: tuple[str, ...]
    position_m: tuple[float, ...]


@dataclass(slots=True)
class OtherFrame:
    kind: str                   # "I" identification, "E" error
    fields: tuple[str, ...]


def parse_body(body: bytes):
    """A checked body (between '$' and '*') -> DataFrame | OtherFrame | None (malformed)."""
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        return None
    parts = text.split(",")
    kind = parts[0]
    if kind == "D":
        if len(parts) != 2 + 2 * N_CHANNELS or not parts[1].isdigit() or len(parts[1]) > 5:
            return None
        seq = int(parts[1])
        if seq > 0xFFFF:
            return None
        status, pos = [], []
        for i in range(N_CHANNELS):
            st, val = parts[2 + 2 * i], parts[3 + 2 * i]
            if st not in STATUS_CODES or not _is_number(val):
                return None
            v = float(val)
            if not -1e5 < v < 1e5:
                return None
            status.append(st)
            pos.append(v * 1e-6)
        return DataFrame(seq, tuple(status), tuple(pos))
    if kind in ("I", "E"):
        return OtherFrame(kind, tuple(parts[1:]))
    return None


def _is_number(s: str) -> bool:
    # strict: sign, digits, one point, digits (no exponent, no nan/inf, no spaces)
    if not s or len(s) > 12:
        return False
    if s[0] in "+-":
        s = s[1:]
    head, dot, tail = s.partition(".")
    return head.isdigit() and head.isascii() and (not dot or (tail.isdigit() and tail.isascii()))


class FrameParser:
    """Byte stream -> frames. Never raises: garbage, bad checksums and over-long or partial frames are
    counted and skipped; a partial frame waits in the buffer for the rest of its bytes."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_frames = 0
        self.garbage_bytes = 0

    def feed(self, data: bytes) -> list:
        out = []
        buf = self._buf
        buf += data
        while True:
            start = buf.find(b"$")
            if start < 0:
                self.garbage_bytes += len(buf)
                buf.clear()
                break
            if start:
                self.garbage_bytes += start
                del buf[:start]
            end = buf.find(b"\n", 1)
            nxt = buf.find(b"$", 1)
            if nxt >= 0 and (end < 0 or nxt < end):
                # a new frame starts before this one ended: the first was cut off
                self.bad_frames += 1
                del buf[:nxt]
                continue
            if end < 0:
                if len(buf) > MAX_FRAME:
                    self.bad_frames += 1
                    self.garbage_bytes += len(buf)
                    buf.clear()
                break
            line = bytes(buf[1:end]).rstrip(b"\r")
            del buf[:end + 1]
            parsed = self._check(line)
            if parsed is None:
                self.bad_frames += 1
            else:
                out.append(parsed)
        return out

    @staticmethod
    def _check(line: bytes):
        if len(line) < 4 or line[-3:-2] != b"*":
            return None
        body, cs = line[:-3], line[-2:]
        try:
            if cs.decode("ascii").upper() != checksum(body):
                return None
        except UnicodeDecodeError:
            return None
        return parse_body(body)

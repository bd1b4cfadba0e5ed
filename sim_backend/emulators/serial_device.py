"""The 4-channel displacement-transducer amplifier (DTA-4) on a pty pair, run in its own process.

Speaks drivers/protocol/dta.py (documented in drivers/devicemaps/dta4_serial.md). The child owns the pty:
it opens the pair, puts the slave side in raw mode, reports the slave's path to the parent, and answers on the
master side. Displacements come from the shared plant state; fault knobs from SERIAL_MODE and SERIAL_CH; wiring faults
(rig.config HilConfig dt_*) from `faults`.
"""
from __future__ import annotations

import os
import random
import select
import time
import tty

from drivers.protocol import dta as proto
from rig.runtime.rt import raise_priority
from sim_backend.emulators import shared as sh


class Amplifier:
    def __init__(self, arr, seed: int = 0, faults=None):
        self.arr = arr
        self.rng = random.Random(seed)
        self.seq = 0
        self.last_count = -1
        self.frozen: bytes | None = None
        # per channel: the mount whose stroke it carries, a factor, an offset (m), extra noise (m rms)
        self.source, self.factor = list(range(proto.N_CHANNELS)), [1.0] * proto.N_CHANNELS
        self.offset_m, self.noise_m = [0.0] * proto.N_CHANNELS, [0.0] * proto.N_CHANNELS
        self.noise_now = [0.0] * proto.N_CHANNELS      # this conversion's noise: the same on every reply to it
        if faults is not None:
            self.miswire(*faults)

    def miswire(self, source, factor, offset_m, noise_m=None) -> None:
        """Wiring faults (rig.config HilConfig dt_*): per channel the mount whose stroke it carries (a swap), a
        factor on it (-1 an inverted sign, 1e-3 a channel ranged in mm read as um, 0 dead), an offset and
        extra white noise (rms). The identity (0..3, 1, 0, 0) is the amplifier as documented."""
        self.source = [int(s) for s in source]
        self.factor = [float(f) for f in factor]
        self.offset_m = [float(o) for o in offset_m]
        self.noise_m = [float(n) for n in noise_m] if noise_m is not None else [0.0] * proto.N_CHANNELS

    def wired(self, stroke) -> list[float]:
        """The channels' displacements (m) of one conversion, through the wiring."""
        return [stroke[s] * f + o + n for s, f, o, n in zip(self.source, self.factor, self.offset_m, self.noise_now)]

    def reply(self, cmd: bytes) -> list[bytes]:
        """The bytes to send for one command, as a list of chunks (written with a pause between them)."""
        mode = int(self.arr[sh.SERIAL_MODE])
        if mode == sh.SILENCE:
            return []
        cmd = cmd.strip()
        if cmd == b"ID":
            return [proto.frame("I,DTA-4,SN0001,FW1.2")]
        if cmd != b"RD":
            return [proto.frame("E,01,unknown command")]
        if mode == sh.EXCEPTION:
            return [proto.frame("E,10,adc fault")]
        if mode == sh.STALE and self.frozen is not None:
            return [self.frozen]
        count, _t, _accel, stroke = sh.snapshot(self.arr)
        if count != self.last_count:                 # a new conversion since the last request
            self.seq = (self.seq + 1) & 0xFFFF
            self.last_count = count
            self.noise_now = [self.rng.gauss(0.0, n) if n else 0.0 for n in self.noise_m]
        stroke = self.wired(stroke)
        status, um = [], []
        for ch in range(proto.N_CHANNELS):
            v = stroke[ch] * 1e6
            forced = sh.CH_STATUS.get(int(self.arr[sh.SERIAL_CH + ch]))
            st = forced or proto.channel_status(v)
            if st == "NP":
                v = 0.0
            else:
                v = max(-proto.RANGE_UM, min(proto.RANGE_UM, v))
            status.append(st)
            um.append(v)
        out = proto.data_frame(self.seq, status, um)
        self.frozen = out
        if mode == sh.GARBAGE:
            junk = bytes(self.rng.getrandbits(8) for _ in range(self.rng.randint(1, 40)))
            bad = bytearray(out)
            bad[self.rng.randrange(1, len(bad) - 5)] ^= 0x20   # one flipped bit: checksum must catch it
            return [junk + bytes(bad)]
        if mode == sh.FRAGMENT:
            cut = self.rng.randrange(1, len(out) - 1)
            return [out[:cut], out[cut:]]
        return [out]


def serve(arr, path_conn, seed: int = 0, priority: int = 0, faults=None) -> None:
    """Process entry: open a pty pair, send the slave path on path_conn, answer until the parent goes away
    or sends anything on path_conn (faults: Amplifier.miswire's arguments, None: wired as documented)."""
    raise_priority(priority)
    master, slave = os.openpty()
    tty.setraw(slave)                   # no echo, no line editing before the driver configures it
    path_conn.send(os.ttyname(slave))
    parent = os.getppid()
    amp = Amplifier(arr, seed, faults)
    buf = bytearray()
    try:
        while os.getppid() == parent and not path_conn.poll():
            r, _, _ = select.select([master], [], [], 0.05)
            if not r:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                time.sleep(0.01)
                continue
            buf += data
            while (i := buf.find(b"\r")) >= 0:
                cmd = bytes(buf[:i])
                del buf[:i + 1]
                chunks = amp.reply(cmd)
                for k, chunk in enumerate(chunks):
                    if k:
                        time.sleep(0.0002)
                    os.write(master, chunk)
            if len(buf) > 256:          # no CR in sight: drop it like the real amplifier's line buffer
                buf.clear()
    finally:
        os.close(master)
        os.close(slave)

"""The exchange block: what the loop and a port's devices hand each other, one float64 block with named parts.

The loop's side is compiled into the period (rig/runtime/kernel.py: it takes the conversions and samples and
writes the commands itself); the devices' side runs in their I/O processes (drivers/: one process per
transport, the block in shared memory) or in the simulated port (sim_backend/backend.py, a block of its own).
Every part has one writer, and nobody waits for anybody:

  part      writer                                   reader           rule
  accel     the accelerometer module's I/O           the kernel       conversions by counter, a ring of slots
                                                                       [counter, time per mount, mount accels, floor
                                                                       accels]; the slot first, then NEWEST
  stroke    the transducer amplifier's I/O           the kernel       samples by sequence number, the same rule
                                                                       [seq, time, strokes]; its staleness limit
  cmd       the kernel (the loop's thread)           the valves' I/O  a sequence lock: SEQ odd while writing; the
                                                                       reader copies and checks SEQ again
  devices   each device's I/O, its row              the kernel       fault code (0: none; its line in the text
                                                                       part), heartbeat time, silence limit
  ages      the kernel                               rig hil --bench  per period the age of the samples used
  stats     each device's I/O                        rig hil --bench  a ring of round-trip times per device
  safe      Port.safe_state (any thread)             the valves' I/O  a count: valves null until the kernel's
                                                                       commands carry it (cmd ACK)
  text      each device's I/O (bytes after the floats)  the loop (on a fault)

Counters and times are float64 words (exact below 2**53: 104 days of monotonic ns), each written by one aligned
8-byte store and read by one 8-byte load, through numpy or numba, never struct (a struct pack is byte by
byte). The compiled writers and readers put a fence between the data and the word that publishes it, so neither
the compiler nor the CPU moves a slot's write after its counter's.
"""
from __future__ import annotations

import ctypes
import mmap
import os
import tempfile
from dataclasses import dataclass

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from rig.runtime.libc import LIBC, Timespec

# header words: where each part is and how big
# (the compiled readers take every size from here, never from this module's constants: numba's cache keeps a
# constant compiled into a caller's code after the constant changed)
HEADER = ("n", "nf", "accel", "a_cap", "a_width", "stroke", "s_cap", "s_width", "cmd", "devices", "n_devices",
          "d_width", "ages", "ages_cap", "stats", "stats_cap", "safe", "futex", "size")
(H_N, H_NF, H_ACCEL, H_ACAP, H_AWIDTH, H_STROKE, H_SCAP, H_SWIDTH, H_CMD, H_DEV, H_NDEV, H_DWIDTH, H_AGES,
 H_AGESCAP, H_STATS, H_STATSCAP, H_SAFE, H_FUTEX, H_SIZE) = range(len(HEADER))
# accel: NEWEST (counter of the newest published conversion, -1: none yet), COUNTED (1: every conversion reaches
# the controllers, in order; 0: the latest value only, a new one each period), LOST (counter of the newest
# conversion the module lost and published as an estimate, -1: none), then the slots
A_NEWEST, A_COUNTED, A_LOST, A_SLOTS = 0, 1, 2, 3
SLOT_COUNTER = 0      # a slot: counter (sequence number), its time stamp(s): one per mount (accel), one (stroke)
# stroke: NEWEST (sequence number of the newest sample, -1: none yet), STALE (the transducer's own staleness
# limit, ns: it is held between its frames), then the slots
S_NEWEST, S_STALE, S_SLOTS = 0, 1, 2
# cmd: SEQ (even: consistent), T (the period's deadline, ns), ACK (the safe count the kernel had seen), WAITER
# (the valves' I/O waits for this period's commands: wake it), PERIOD (ns), then one command per mount
C_SEQ, C_T, C_ACK, C_WAITER, C_PERIOD, C_VALUES = 0, 1, 2, 3, 4, 5
# devices: one row each: fault code (0 none), heartbeat, silence limit (0 none), the time of its newest sample or
# event (the valves': the last SYNC), a count of requests to it (the port's: a valve fault reset), its samples
# or SYNCs so far, a count of its misses (the valves': SYNCs sent with the period before's commands; the
# module: conversions interpolated, lost from its FIFO; the amplifier: requests without a new frame), and the loop
# period its newest sample or event belongs to (the valves': the period whose commands the last SYNC carried)
DEVICE_ROW = ("fault", "beat_ns", "silent_ns", "sample_ns", "request", "count", "missed", "period_ns")
D_FAULT, D_BEAT, D_SILENT, D_SAMPLE, D_REQUEST, D_COUNT, D_MISSED, D_PERIOD = range(len(DEVICE_ROW))
TEXT_BYTES = 240                          # one device's fault line (UTF-8, NUL-padded)
FUTEX_WORDS = 4                           # int32 words the processes sleep on (futex(2)): cmd, sync, spare


@dataclass(frozen=True)
class Layout:
    """The parts of a block for n mounts (nf floor accelerometers) and the named devices."""
    n: int
    nf: int = 0
    devices: tuple[str, ...] = ()
    accel_cap: int = 256                  # conversions kept: a loop held up this many periods replays exactly
    stroke_cap: int = 8
    ages_cap: int = 1 << 16
    stats_cap: int = 1 << 16

    def offsets(self) -> dict:
        n, nf, nd = self.n, self.nf, len(self.devices)
        parts = {"header": len(HEADER), "accel": A_SLOTS + self.accel_cap * (1 + 2 * n + nf),
                 "stroke": S_SLOTS + self.stroke_cap * (2 + n), "cmd": C_VALUES + n,
                 "devices": nd * len(DEVICE_ROW), "ages": 1 + 2 * self.ages_cap,
                 "stats": nd * (1 + self.stats_cap), "safe": 1}
        at, off = 0, {}
        for part, size in parts.items():
            off[part] = at
            at += size
        off["floats"] = at
        return off

    def nbytes(self) -> int:
        return 8 * self.offsets()["floats"] + 4 * FUTEX_WORDS + TEXT_BYTES * len(self.devices)

    def header(self) -> list:
        o = self.offsets()
        return [self.n, self.nf, o["accel"], self.accel_cap, 1 + 2 * self.n + self.nf, o["stroke"], self.stroke_cap,
                2 + self.n, o["cmd"], o["devices"], len(self.devices), len(DEVICE_ROW), o["ages"], self.ages_cap,
                o["stats"],
                self.stats_cap, o["safe"], 8 * o["floats"], self.nbytes()]


class Block:
    """One exchange block over a buffer: `io` (the float64 words), the futex words and the text part. The
    loop's process creates it (`create`: in shared memory, or `local`: in this process only); an I/O process
    attaches by path (`attach`)."""

    def __init__(self, buf, layout: Layout | None = None, path: str | None = None, owner: bool = False,
                 devices: tuple[str, ...] = ()):
        self.buf, self.path, self.owner = buf, path, owner
        self.devices = tuple(layout.devices) if layout is not None else tuple(devices)
        head = np.frombuffer(buf, dtype=np.float64, count=len(HEADER))
        if layout is not None:
            head[:] = layout.header()
        self.n, self.nf = int(head[H_N]), int(head[H_NF])
        floats = int(head[H_FUTEX]) // 8
        self.io = np.frombuffer(buf, dtype=np.float64, count=floats)
        self.futex = np.frombuffer(buf, dtype=np.int32, count=FUTEX_WORDS, offset=8 * floats)
        self._text0 = 8 * floats + 4 * FUTEX_WORDS
        self.n_devices = int(head[H_NDEV])
        if layout is not None:
            io = self.io
            io[int(io[H_ACCEL]) + A_NEWEST] = -1.0
            io[int(io[H_ACCEL]) + A_LOST] = -1.0
            io[int(io[H_STROKE]) + S_NEWEST] = -1.0
        self._addr = ctypes.addressof(ctypes.c_char.from_buffer(buf)) if isinstance(buf, mmap.mmap) else None
        _warm()

    @classmethod
    def local(cls, layout: Layout) -> "Block":
        return cls(bytearray(layout.nbytes()), layout)

    @classmethod
    def create(cls, layout: Layout) -> "Block":
        """In shared memory (/dev/shm), to be attached by path; unlink() once every process has it mapped."""
        d = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
        fd, path = tempfile.mkstemp(prefix="rig-io-", dir=d)
        try:
            os.ftruncate(fd, layout.nbytes())
            mm = mmap.mmap(fd, layout.nbytes())
        finally:
            os.close(fd)
        return cls(mm, layout, path, owner=True)

    @classmethod
    def attach(cls, path: str, devices: tuple[str, ...] = ()) -> "Block":
        fd = os.open(path, os.O_RDWR)
        try:
            mm = mmap.mmap(fd, 0)
        finally:
            os.close(fd)
        return cls(mm, None, path, devices=devices)

    def unlink(self) -> None:
        if self.owner and self.path:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
            self.owner = False

    def close(self) -> None:
        self.unlink()
        self.io = self.futex = None
        if isinstance(self.buf, mmap.mmap):
            try:
                self.buf.close()
            except BufferError:         # a view is still held: unmapped with the process
                pass

    # ---- named parts -----------------------------------------------------------------------------------
    def part(self, name: str) -> int:
        return int(self.io[{"accel": H_ACCEL, "stroke": H_STROKE, "cmd": H_CMD, "devices": H_DEV,
                            "ages": H_AGES, "stats": H_STATS, "safe": H_SAFE}[name]])

    def device_name(self, d: int) -> str:
        return self.devices[d] if d < len(self.devices) else f"device {d}"

    def device_row(self, d: int) -> np.ndarray:
        o = self.part("devices") + d * len(DEVICE_ROW)
        return self.io[o:o + len(DEVICE_ROW)]

    def set_text(self, d: int, text: str) -> None:
        """Device d's fault line (written before its fault code, so a reader of the code finds it)."""
        raw = text.encode("utf-8", "replace")[:TEXT_BYTES - 1]
        o = self._text0 + d * TEXT_BYTES
        self.buf[o:o + TEXT_BYTES] = raw + bytes(TEXT_BYTES - len(raw))

    def text(self, d: int) -> str:
        o = self._text0 + d * TEXT_BYTES
        return bytes(self.buf[o:o + TEXT_BYTES]).split(b"\0", 1)[0].decode("utf-8", "replace")

    def fault(self, d: int, code: int, text: str) -> None:
        """Device d reports a fault (code > 0) with its line, or none (code 0)."""
        if code:
            self.set_text(d, text)
        fence_store(self.io, self.part("devices") + d * len(DEVICE_ROW) + D_FAULT, float(code))

    def stats(self, d: int) -> np.ndarray:
        """Device d's round trips (us), oldest first (as many as the ring holds)."""
        io = self.io
        cap = int(io[H_STATSCAP])
        o = self.part("stats") + d * (1 + cap)
        k = int(io[o])
        ring = io[o + 1:o + 1 + cap]
        return ring[:k].copy() if k <= cap else np.roll(ring, -(k % cap)).copy()

    def ages_us(self) -> np.ndarray:
        """(periods, 2): the age of the accelerometer conversion and of the transducer sample each period
        used, in us (the kernel's ring, oldest first)."""
        io = self.io
        cap = int(io[H_AGESCAP])
        o = self.part("ages")
        k = int(io[o])
        ring = io[o + 1:o + 1 + 2 * cap].reshape(cap, 2)
        out = ring[:k] if k <= cap else np.roll(ring, -(k % cap), axis=0)
        return out * 1e-3

    # ---- futex(2): a process sleeps on an int32 word until another bumps it --------------------------------
    def wait(self, word: int, seen: int, timeout_s: float) -> None:
        """Sleep while futex word `word` still reads `seen`, at most timeout_s (shared memory only)."""
        if self._addr is not None and timeout_s > 0:
            _futex_wait(self._addr + self._text0 - 4 * FUTEX_WORDS + 4 * word, seen, timeout_s)

    def wake(self, word: int) -> None:
        """Bump futex word `word` and wake whoever sleeps on it."""
        self.futex[word] += 1
        if self._addr is not None:
            _futex_wake(self._addr + self._text0 - 4 * FUTEX_WORDS + 4 * word)


FUTEX_CMD, FUTEX_SYNC = 0, 1            # the words: commands written (valves' I/O), SYNC sent (module's I/O)

_SYS_FUTEX = 202 if os.uname().machine == "x86_64" else 98     # x86_64, aarch64
_FUTEX_WAIT, _FUTEX_WAKE = 0, 1


def _futex_wait(addr: int, seen: int, timeout_s: float) -> None:
    ts = Timespec(int(timeout_s), int((timeout_s % 1.0) * 1e9))
    LIBC.syscall(_SYS_FUTEX, ctypes.c_void_p(addr), _FUTEX_WAIT, ctypes.c_int(seen), ctypes.byref(ts), None, 0)


def _futex_wake(addr: int) -> None:
    LIBC.syscall(_SYS_FUTEX, ctypes.c_void_p(addr), _FUTEX_WAKE, 0x7FFFFFFF, None, None, 0)


# ---- compiled rules ----------------------------------------------------------------------------------------
@intrinsic
def fence(typingctx):
    """A full memory fence (compiler and CPU): no load or store moves across it."""
    def codegen(context, builder, signature, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()
    return types.void(), codegen


@numba.njit(cache=True)
def fence_store(io, i, value):
    """io[i] = value after everything written before (a word that publishes them)."""
    fence()
    io[i] = value
    fence()


@numba.njit(cache=True)
def put_conversion(io, counter, ts, values):
    """Publish one conversion (the accel part: per mount its time stamp in `ts`, then in `values` the mount
    accelerations and the floor ones): its slot, then NEWEST."""
    a = int(io[H_ACCEL])
    cap, w, n = int(io[H_ACAP]), int(io[H_AWIDTH]), int(io[H_N])
    s = a + A_SLOTS + (int(counter) % cap) * w
    io[s + SLOT_COUNTER] = -1.0              # being written: a reader that lapped the writer sees no counter
    fence()
    io[s + 1:s + 1 + n] = ts
    io[s + 1 + n:s + 1 + n + values.shape[0]] = values
    fence()
    io[s + SLOT_COUNTER] = counter
    fence()
    io[a + A_NEWEST] = counter
    fence()


@numba.njit(cache=True)
def mark_lost(io, counter):
    """The conversion `counter`, about to be published, is an estimate of one the module lost (before its slot
    and NEWEST: a reader that sees it published sees the mark)."""
    io[int(io[H_ACCEL]) + A_LOST] = counter
    fence()


@numba.njit(cache=True)
def put_sample(io, seq, t_ns, values):
    """Publish one transducer sample (the stroke part): its slot, then NEWEST."""
    s0 = int(io[H_STROKE])
    cap, w = int(io[H_SCAP]), int(io[H_SWIDTH])
    s = s0 + S_SLOTS + (int(seq) % cap) * w
    io[s + SLOT_COUNTER] = -1.0
    fence()
    io[s + 1] = t_ns
    io[s + 2:s + 2 + values.shape[0]] = values
    fence()
    io[s + SLOT_COUNTER] = seq
    fence()
    io[s0 + S_NEWEST] = seq
    fence()


@numba.njit(cache=True)
def put_step(io, counter, ts, values, seq, t_ns, strokes):
    """A conversion and a transducer sample at once (a simulated plant's step: put_conversion, put_sample)."""
    put_conversion(io, counter, ts, values)
    put_sample(io, seq, t_ns, strokes)


_STEP_SIG = "void(float64[::1], float64, float64[::1], float64[::1], float64, float64, float64[::1])"
_STEP: list = []


def put_step_entry():
    """put_step's own compiled entry for exactly its types (C-contiguous float64 arrays and floats), without the
    dispatcher's type resolution: a simulated plant calls it at every step."""
    if not _STEP:
        put_step.compile(_STEP_SIG)
        (sig,) = put_step.signatures
        _STEP.append(put_step.overloads[sig].entry_point)
    return _STEP[0]


@numba.njit(cache=True)
def put_commands(io, t_ns, values):
    """The loop's commands for the period at t_ns (the sequence lock; the kernel runs this same rule)."""
    c = int(io[H_CMD])
    seq = io[c + C_SEQ] + 1.0
    io[c + C_SEQ] = seq                      # odd: writing
    fence()
    io[c + C_T] = t_ns
    io[c + C_ACK] = io[int(io[H_SAFE])]
    n = values.shape[0]
    io[c + C_VALUES:c + C_VALUES + n] = values
    fence()
    io[c + C_SEQ] = seq + 1.0                # even: consistent
    fence()


@numba.njit(cache=True)
def take_waiter(io):
    """After the commands were written: whether the valves' I/O sleeps waiting for them (ask_wake), the flag
    cleared; the writer then wakes it (Block.wake(FUTEX_CMD)). The kernel runs this after every period that
    faulted on no rule, as drivers/port.py's write does after its commands."""
    w = int(io[H_CMD]) + C_WAITER
    if io[w] != 0.0:
        io[w] = 0.0
        return True
    return False


@numba.njit(cache=True)
def get_commands(io, out):
    """The newest consistent commands into `out`: (sequence, the period's deadline ns, null: the port's safe
    state came after them). Retries while the writer is in the middle (the loop writes for a microsecond);
    sequence -1 after 1000 tries (then `out` is unchanged)."""
    c = int(io[H_CMD])
    n = out.shape[0]
    for _ in range(1000):
        s0 = io[c + C_SEQ]
        fence()
        if int(s0) % 2 == 1:
            continue
        t = io[c + C_T]
        ack = io[c + C_ACK]
        tmp = io[c + C_VALUES:c + C_VALUES + n].copy()
        fence()
        if io[c + C_SEQ] == s0:
            out[:] = tmp
            return s0, t, io[int(io[H_SAFE])] != ack
    return -1.0, 0.0, True


@numba.njit(cache=True)
def ask_wake(io):
    """The valves' I/O is about to sleep on the command futex: say so (WAITER), then the sequence to compare
    (read after the flag, so a loop that wrote meanwhile is seen either here or by the loop's check)."""
    c = int(io[H_CMD])
    io[c + C_WAITER] = 1.0
    fence()
    return io[c + C_SEQ]


@numba.njit(cache=True)
def beat(io, d, t_ns):
    """Device d's I/O is alive at t_ns (its heartbeat)."""
    io[int(io[H_DEV]) + d * int(io[H_DWIDTH]) + D_BEAT] = t_ns


@numba.njit(cache=True)
def add_stat(io, d, value):
    """One round trip (us) of device d into its ring."""
    cap = int(io[H_STATSCAP])
    o = int(io[H_STATS]) + d * (1 + cap)
    k = int(io[o])
    io[o + 1 + k % cap] = value
    io[o] = k + 1


def safe(block: Block) -> None:
    """The port's safe state: valves to null until the kernel writes commands again (any thread)."""
    io = block.io
    fence_store(io, int(io[H_SAFE]), io[int(io[H_SAFE])] + 1.0)



_WARM: list = []


def _warm() -> None:
    """Compile (or load from numba's cache) the rules Python calls, once per process, when the first block is
    made: at set-up, never in a period (a cold load stalls for tens of ms)."""
    if _WARM:
        return
    _WARM.append(True)
    io = Block.local(Layout(1, 0, devices=("warm",))).io
    one = np.zeros(1)
    put_conversion(io, 0.0, one, one)
    put_sample(io, 0.0, 0.0, one)
    put_commands(io, 0.0, one)
    get_commands(io, one)
    ask_wake(io)
    take_waiter(io)
    beat(io, 0, 0.0)
    add_stat(io, 0, 0.0)
    fence_store(io, 0, io[0])

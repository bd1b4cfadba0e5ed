"""The producer's side of a shared row ring (a recording's, rig/runtime/recorder.py; the console's live ring,
rig/console/live.py): which row a new row goes into, and when the reader may take it.

The ring's state is its header, an int64 array on the shared memory (HEADER): rows published so far (the
reader takes rows below it), rows the reader has taken (a recording's writer advances it; NEVER_FULL for a
ring that overwrites its oldest row instead), rows dropped because the ring was full, and whether a claimed
row waits to be published. A row is claimed (`claim`), written, and published (`publish`): the control
loop's compiled period publishes the row of the period before, then claims and writes its own, so a row is
published one period later, so a period that faults after the compiled call (a port write that fails) is
corrected in place (fault flag, null commands) before any reader can see it.

These are plain functions over the header array: the period kernel compiles these same functions into its
one call (rig/runtime/kernel.py), and the Python producers (Recorder.push, the console's copies) run them as they
are. One rule, one place.

On a shared map the ring is HEADER_BYTES of header, then the rows. Both sides reach the header's words
only through `header` (an aligned int64 view: one 8-byte load or store per word). Never through
struct.pack_into/unpack_from: their standard-size formats move one byte at a time, so the other process
can read a word half written (the recorder's ring once saw a tail thousands of rows behind and dropped
rows in simulated time that way).
"""
from __future__ import annotations

import numpy as np

HEAD, TAIL, DROPPED, PENDING = 0, 1, 2, 3      # the header's int64 words
HEADER = ("head", "tail", "dropped", "pending")
NEVER_FULL = -1         # TAIL of a ring that never waits for its reader: it overwrites the oldest row
HEADER_BYTES = 64       # the header's room on a shared map: HEADER's words, then words of the ring's own
HEADER_WORDS = HEADER_BYTES // 8


def header(buf) -> np.ndarray:
    """The header's int64 words on a shared map (HEADER first; a ring may keep its own after them)."""
    return np.frombuffer(buf, dtype=np.int64, count=HEADER_WORDS)


def rows(buf, cap: int, ncols: int) -> np.ndarray:
    """The ring's (cap, ncols) float64 rows on a shared map, after the header."""
    return np.frombuffer(buf, dtype=np.float64, count=cap * ncols, offset=HEADER_BYTES).reshape(cap, ncols)


def map_bytes(cap: int, ncols: int) -> int:
    """The size of a shared map holding the header and cap rows of ncols float64."""
    return HEADER_BYTES + 8 * cap * ncols


def publish(hdr) -> None:
    """The claimed row (if any) to the reader: the head advances after the row was written."""
    if hdr[PENDING]:
        hdr[PENDING] = 0
        hdr[HEAD] += 1


def claim(hdr, cap) -> int:
    """The index of the next row to write (pending until published; publish the one claimed before first),
    or -1 when the ring is full: the row is dropped and counted, never waited for."""
    h = hdr[HEAD]
    t = hdr[TAIL]
    if t != NEVER_FULL and h - t >= cap:
        hdr[DROPPED] += 1
        return -1
    hdr[PENDING] = 1
    return h % cap


def pending_row(hdr, cap) -> int:
    """The index of the claimed row not yet published, or -1."""
    return int(hdr[HEAD] % cap) if hdr[PENDING] else -1


def room(hdr, cap) -> int:
    """Rows that can be claimed now without dropping (a claimed row not yet published counts as taken)."""
    if hdr[TAIL] == NEVER_FULL:
        return cap
    return int(cap - (hdr[HEAD] + hdr[PENDING] - hdr[TAIL]))


# ---- the reader's side -------------------------------------------------------------------------------
def published(hdr) -> int:
    """Rows published so far: the reader may take every row below this."""
    return int(hdr[HEAD])


def taken(hdr) -> int:
    """Rows the reader has taken so far (its rows are free for the producer again)."""
    return int(hdr[TAIL])


def release(hdr, upto: int) -> None:
    """The reader has taken every row below `upto`: their slots are free again."""
    hdr[TAIL] = upto

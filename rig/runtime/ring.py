"""The producer's side of a shared row ring (a recording's, rig/recorder.py; the console's live ring,
rig/console/live.py): which row a new row goes into, and when the reader may take it.

The ring's state is its header, an int64 array on the shared memory (HEADER): rows published so far (the
reader takes rows below it), rows the reader has taken (a recording's writer advances it; NEVER_FULL for a
ring that overwrites its oldest row instead), rows dropped because the ring was full, and whether a claimed
row waits to be published. A row is claimed (`claim`), written, and published (`publish`): the control
loop's compiled period publishes the row of the period before, then claims and writes its own, so a row is
published one period later, so a period that faults after the compiled call (a port write that fails) is
corrected in place (fault flag, null commands) before any reader can see it.

These are plain functions over the header array: the period kernel compiles these same functions into its
one call (rig/kernel.py), and the Python producers (Recorder.push, the console's copies) run them as they
are. One rule, one place.
"""
from __future__ import annotations

HEAD, TAIL, DROPPED, PENDING = 0, 1, 2, 3      # the header's int64 words
HEADER = ("head", "tail", "dropped", "pending")
NEVER_FULL = -1         # TAIL of a ring that never waits for its reader: it overwrites the oldest row


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

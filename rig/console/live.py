"""The live ring: the loop's recording rows, published in shared memory for the console's web server.

The loop's side is the recorder interface the tap already drives (rig/runtime/tap.py): `ncols`, `ring_rows()`,
`ring_header()`, `push_row()`, `event()`. Bound as the loop's recorder while no recording runs, the
compiled period claims, writes and publishes every row in it (rig/runtime/ring.py), exactly as it does in a
recording's ring; while a recording
runs, the console copies the recording's new rows in here from another thread (`append`). Unlike a
recording's ring it never waits for a reader and never drops: it overwrites the oldest row, and a reader that
fell behind by more than the capacity skips ahead (and counts what it skipped).

The memory is a memfd (an anonymous shared file), so the web server may be another process: it maps the
same file descriptor (passed over the control socket) with `LiveReader`. Layout: a 64-byte header (the
producer's words of rig/runtime/ring.py HEADER: head, rows published so far, int64 @0; tail NEVER_FULL; dropped;
pending; then ncols @32 and capacity in rows @40), then capacity x ncols float64 rows. Publication order:
the row first, then the head (x86 does not reorder stores).
"""
from __future__ import annotations

import mmap
import os
import struct

import numpy as np

from rig.runtime import ring as rr

_HDR = 64
_Q = struct.Struct("<q")
_SHAPE = struct.Struct("<qq")           # ncols, capacity
_SHAPE_AT = 8 * len(rr.HEADER)


class LiveRing:
    """The writer's side (the loop's process): a recorder the tap can bind, and `append` for copied rows."""

    def __init__(self, ncols: int, capacity_rows: int) -> None:
        if ncols < 1 or capacity_rows < 2:
            raise ValueError(f"live ring: ncols {ncols}, capacity {capacity_rows} rows")
        self.ncols = int(ncols)
        self.capacity = int(capacity_rows)
        size = _HDR + 8 * self.ncols * self.capacity
        self.fd = os.memfd_create("rig-console-live", os.MFD_CLOEXEC)
        os.ftruncate(self.fd, size)
        self._mm = mmap.mmap(self.fd, size)
        self._hdr = np.frombuffer(self._mm, dtype=np.int64, count=len(rr.HEADER))
        self._hdr[rr.TAIL] = rr.NEVER_FULL
        _SHAPE.pack_into(self._mm, _SHAPE_AT, self.ncols, self.capacity)
        self._rows = np.frombuffer(self._mm, dtype=np.float64, count=self.capacity * self.ncols,
                                   offset=_HDR).reshape(self.capacity, self.ncols)

    # ---- the tap's recorder interface (the loop's thread) ----------------------------------------------
    def ring_rows(self) -> np.ndarray:
        return self._rows

    def ring_header(self) -> np.ndarray:
        return self._hdr

    def push_row(self, row) -> bool:
        self._rows[rr.claim(self._hdr, self.capacity), :] = row
        rr.publish(self._hdr)
        return True

    def event(self, t_s: float, text: str) -> None:
        """The loop's events are not kept here: the console shows the loop's log records and the flag columns."""

    # ---- rows copied from a recording's ring (the console's thread, while the loop records elsewhere) ----
    def append(self, rows: np.ndarray) -> None:
        total = n = len(rows)
        if n == 0:
            return
        start = self.head                  # (the loop published its last row here when it was unbound)
        if n > self.capacity:            # only the newest fit; the older ones count as overwritten
            rows, n, start = rows[-self.capacity:], self.capacity, start + n - self.capacity
        i = start % self.capacity
        k = min(n, self.capacity - i)
        self._rows[i:i + k] = rows[:k]
        self._rows[:n - k] = rows[k:]
        self._hdr[rr.HEAD] += total

    @property
    def head(self) -> int:
        return int(self._hdr[rr.HEAD])

    def close(self) -> None:
        self._rows = self._hdr = None
        try:
            self._mm.close()
        except BufferError:          # a view is still held (a late reader): unmapped with it
            pass
        os.close(self.fd)


class LiveReader:
    """The reader's side (the web server): new rows since the last call, oldest first."""

    def __init__(self, fd: int) -> None:
        size = os.fstat(fd).st_size
        self._mm = mmap.mmap(fd, size, prot=mmap.PROT_READ)
        self.ncols, self.capacity = _SHAPE.unpack_from(self._mm, _SHAPE_AT)
        if _HDR + 8 * self.ncols * self.capacity != size:
            raise ValueError(f"live ring: {size} bytes do not hold {self.capacity} rows of {self.ncols}")
        self._rows = np.frombuffer(self._mm, dtype=np.float64, count=self.capacity * self.ncols,
                                   offset=_HDR).reshape(self.capacity, self.ncols)
        self.seen = _Q.unpack_from(self._mm, 0)[0]     # start at the present
        self.skipped_rows = 0

    def head(self) -> int:
        return _Q.unpack_from(self._mm, 0)[0]

    def read(self, margin_rows: int = 0) -> np.ndarray:
        """Rows published since the last read (a copy). Rows the writer may be overwriting while they are
        copied (further back than capacity - margin_rows) are skipped and counted in skipped_rows."""
        head = self.head()
        cap = self.capacity
        oldest = head - (cap - max(margin_rows, cap // 8))
        start = max(self.seen, oldest)
        self.skipped_rows += start - self.seen
        n = head - start
        if n <= 0:
            self.seen = max(self.seen, head)
            return np.empty((0, self.ncols))
        i = start % cap
        if i + n <= cap:
            out = self._rows[i:i + n].copy()
        else:
            out = np.concatenate([self._rows[i:], self._rows[:n - (cap - i)]])
        # the writer went on while we copied: drop the rows it may have overwritten meanwhile
        lost = self.head() - (start + cap)
        if lost > 0:
            out = out[lost:]
            self.skipped_rows += lost
        self.seen = head
        return out

    def close(self) -> None:
        self._rows = None
        try:
            self._mm.close()
        except BufferError:
            pass

"""The live ring: the loop's recording rows, published in shared memory for the console's web server.

The loop's side is the recorder interface the tap already drives (rig/runtime/tap.py): `ncols`, `ring_rows()`,
`ring_header()`, `push_row()`, `event()`. Bound as the loop's recorder while no recording runs, the
compiled period claims, writes and publishes every row in it (rig/runtime/ring.py), exactly as it does in a
recording's ring; while a recording
runs, the console copies the recording's new rows in here from another thread (`append`). Unlike a
recording's ring it never waits for a reader and never drops: it overwrites the oldest row, and a reader that
fell behind by more than the capacity skips ahead (and counts what it skipped).

The memory is a memfd (an anonymous shared file), so the web server may be another process: it maps the
same file descriptor (passed over the control socket) with `LiveReader`. Layout: rig/runtime/ring.py's header (its
HEADER words: head, rows published so far; tail NEVER_FULL; dropped; pending; then this ring's own two words,
ncols and capacity in rows), then capacity x ncols float64 rows. Publication order: the row first, then the
head (x86 does not reorder stores).
"""
from __future__ import annotations

import mmap
import os

import numpy as np

from rig.runtime import ring as rr

_NCOLS, _CAPACITY = len(rr.HEADER), len(rr.HEADER) + 1      # this ring's own header words


class LiveRing:
    """The writer's side (the loop's process): a recorder the tap can bind, and `append` for copied rows."""

    def __init__(self, ncols: int, capacity_rows: int) -> None:
        if ncols < 1 or capacity_rows < 2:
            raise ValueError(f"live ring: ncols {ncols}, capacity {capacity_rows} rows")
        self.ncols = int(ncols)
        self.capacity = int(capacity_rows)
        size = rr.map_bytes(self.capacity, self.ncols)
        self.fd = os.memfd_create("rig-console-live", os.MFD_CLOEXEC)
        os.ftruncate(self.fd, size)
        self._mm = mmap.mmap(self.fd, size)
        self._hdr = rr.header(self._mm)
        self._hdr[rr.TAIL] = rr.NEVER_FULL
        self._hdr[_NCOLS], self._hdr[_CAPACITY] = self.ncols, self.capacity
        self._rows = rr.rows(self._mm, self.capacity, self.ncols)

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
        self._hdr = rr.header(self._mm)
        self.ncols, self.capacity = int(self._hdr[_NCOLS]), int(self._hdr[_CAPACITY])
        if rr.map_bytes(self.capacity, self.ncols) != size:
            raise ValueError(f"live ring: {size} bytes do not hold {self.capacity} rows of {self.ncols}")
        self._rows = rr.rows(self._mm, self.capacity, self.ncols)
        self.seen = self.head()          # start at the present
        self.skipped_rows = 0

    def head(self) -> int:
        return rr.published(self._hdr)

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
        self._rows = self._hdr = None
        try:
            self._mm.close()
        except BufferError:
            pass

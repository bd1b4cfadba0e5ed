"""The recording tap: the kernel's row of each period into the recorder, without blocking the loop.

With a recorder that offers its ring (rig.runtime.recorder.Recorder of the loop's layout, the console's live ring)
the compiled period does the recording itself: it publishes the row of the period before and writes its
own into the next row of the shared ring (rig/runtime/ring.py), so nothing of it runs in Python per period. A
period that faults after the compiled call (a port write that fails) has its row corrected here, in place,
before the next period publishes it; the row of the run's last period is published when the run ends or the
recorder changes. Any other recorder (an adapter keeping a few columns) gets push_row(row) after the period.
"""
from __future__ import annotations

from operator import itemgetter

from rig.runtime import ring as rr
from rig.runtime.kernel import ring_ok


class RecordingTap:
    def __init__(self, kernel) -> None:
        self.kernel = kernel
        self.row = kernel.row
        self.recorder = None
        self.ring, self.hdr = kernel.no_ring, kernel.no_hdr     # what the kernel writes (no rows: nothing)
        self.pushes = False             # the recorder takes push_row after the period (no ring of its own)
        self.waits = False              # simulated time: wait for the writer rather than drop
        self.dropped_seen = 0           # the recorder's dropped rows already reported (new_drops)

    def bind(self, recorder) -> None:
        """Record into `recorder` from the next period on (None: nothing recorded). The row the old one got
        last is published first. The recorder is set last: another thread that sees it changed may close the
        old one."""
        self.publish()
        ring = hdr = None
        if recorder is not None and getattr(recorder, "ncols", None) == len(self.row) and \
                hasattr(recorder, "ring_rows") and hasattr(recorder, "ring_header"):
            ring, hdr = recorder.ring_rows(), recorder.ring_header()
            if not ring_ok(ring, hdr):
                ring = hdr = None
        if ring is None:
            ring, hdr = self.kernel.no_ring, self.kernel.no_hdr
        self.kernel.bind_ring(ring, hdr)
        self.ring, self.hdr = ring, hdr
        self.pushes = recorder is not None and ring is self.kernel.no_ring
        self.waits = bool(getattr(recorder, "wait_when_full", False)) and not self.pushes
        self.dropped_seen = int(getattr(recorder, "dropped_rows", 0))
        self.recorder = recorder

    def publish(self) -> None:
        """The row claimed last to the reader (the run ended, or the recorder changes)."""
        if self.ring.shape[0]:
            rr.publish(self.hdr)

    def wait_room(self) -> None:
        """Simulated time: the writer makes room for the period's row before the compiled call (not waited for
        on the real clock: a full ring drops the row)."""
        if self.waits:
            self.recorder.wait_room()

    def close(self, written: bool) -> None:
        """The period's row changed after the compiled call (a fault), or goes to a recorder without a ring:
        correct it in the row the kernel claimed (written: the compiled call ran), or claim one now, or push it."""
        rec = self.recorder
        if rec is None:
            return
        if self.pushes:
            rec.push_row(self.row)
            return
        ring, hdr = self.ring, self.hdr
        if written:
            r = rr.pending_row(hdr, ring.shape[0])
        else:
            rr.publish(hdr)
            r = rr.claim(hdr, ring.shape[0])
        if r >= 0:
            ring[r, :] = self.row

    def event(self, t_s: float, text: str) -> None:
        if self.recorder is not None:
            self.recorder.event(t_s, text)

    def new_drops(self) -> int:
        """Rows the recorder dropped (its ring full: the real clock never waits) since the last call."""
        n = int(getattr(self.recorder, "dropped_rows", 0)) - self.dropped_seen
        self.dropped_seen += n
        return n


class Columns:
    """A recording of a few columns of the loop's row under channel names of their own, e.g. an
    identification run keeps time, the command, the position and the acceleration of one mount:
        Columns([(Channel("position_m", "m"), "stroke_m", mount), ...])
    picks: (channel, the loop channel it comes from, the column within that channel)."""

    def __init__(self, picks) -> None:
        self.picks = list(picks)
        self.channels = [c for c, _, _ in self.picks]

    def adapter(self, recorder, layout) -> "_ColumnsRecorder":
        return _ColumnsRecorder(recorder, [layout[src] + i for _, src, i in self.picks])


class _ColumnsRecorder:
    """The loop's recorder interface (push_row, event) over a Recorder of the picked columns."""

    def __init__(self, recorder, cols) -> None:
        self.rec = recorder
        pick = itemgetter(*cols)
        self._pick = pick if len(cols) > 1 else (lambda row: (pick(row),))

    def push_row(self, row) -> bool:
        return self.rec.push(*self._pick(row))

    def event(self, t_s: float, text: str) -> None:
        self.rec.event(t_s, text)

    def writer_died(self) -> str | None:
        return self.rec.writer_died()

    @property
    def dropped_rows(self) -> int:
        return self.rec.dropped_rows

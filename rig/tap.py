"""The recording tap: the kernel's row of each period into the recorder, without blocking the loop.

With a rig.recorder.Recorder of the loop's layout the kernel copies the row straight into the recorder's
shared ring (a slot from Recorder.next_row; committed here after the port write, so a period that faults
after the kernel is recorded with its fault). Any other recorder (an adapter keeping a few columns) gets
push_row(row) after the period. The rare flag columns are written into the row only when they change (begin: flags and slot in one call).
"""
from __future__ import annotations

from operator import itemgetter

from rig.kernel import ring_ok
from rig.lifecycle import State


class RecordingTap:
    def __init__(self, kernel) -> None:
        self.kernel = kernel
        self.row = kernel.row
        lay = kernel.layout
        self._i_state, self._i_iso, self._i_fault = lay["lifecycle_state"], lay["isolation_on"], lay["fault"]
        self._i_over, self._i_skip = lay["overruns"], lay["skipped_periods"]
        self.recorder = None
        self._ring = None
        self._flags = None
        self._slot = -1

    def bind(self, recorder) -> None:
        """Record into `recorder` from the next period on (None: nothing recorded). The recorder is set last:
        another thread that sees it changed may close the old one."""
        ring = None
        if recorder is not None and getattr(recorder, "ncols", None) == len(self.row) and \
                hasattr(recorder, "ring_rows") and hasattr(recorder, "next_row"):
            ring = recorder.ring_rows()
            ring = ring if ring_ok(ring) else None
        self._ring = ring
        self._flags = None
        self.recorder = recorder

    def flags(self, state: State, isolation: bool, overruns: int, skipped: int) -> None:
        """The rare flags into the row, only when they changed (the row keeps them between periods)."""
        f = (state, isolation, overruns, skipped)
        if f != self._flags:
            self._flags = f
            row = self.row
            row[self._i_state] = float(state)
            row[self._i_iso] = 1.0 if isolation else 0.0
            row[self._i_fault] = 1.0 if state is State.FAULT else 0.0
            row[self._i_over] = float(overruns)
            row[self._i_skip] = float(skipped)

    def begin(self, state: State, isolation: bool, overruns: int, skipped: int):
        """A recorded period begins: its flags (flags(), when they changed), then (ring, slot) for the kernel:
        the recorder's ring and its next free row, else (no ring, -1). One call: the loop's hot path."""
        if (state, isolation, overruns, skipped) != self._flags:
            self.flags(state, isolation, overruns, skipped)
        if self._ring is None:
            self._slot = -1
            return self.kernel.no_ring, -1
        self._slot = s = self.recorder.next_row()         # -1: the ring is full, the row dropped and counted
        return self._ring, s

    def close(self, copied: bool) -> None:
        """The period's row is final: commit it (copying it first if the kernel did not), or push it."""
        rec = self.recorder
        if rec is None:
            return
        if self._ring is None:
            rec.push_row(self.row)
        elif self._slot >= 0:
            if not copied:
                self._ring[self._slot, :] = self.row
            rec.commit()

    def event(self, t_s: float, text: str) -> None:
        if self.recorder is not None:
            self.recorder.event(t_s, text)


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

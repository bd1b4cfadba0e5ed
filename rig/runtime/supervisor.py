"""The do-no-harm supervisor: isolation that makes the table worse is said at once and switched off.

At the loop's 10 Hz watch it takes the accelerometer conversions published since its last look from the port's
exchange block (rig/runtime/exchange.py: the ring of conversions, the table's and the floor's accelerations),
filters them to the band ([supervisor] band_low_hz-band_high_hz, a Butterworth band-pass kept running across
looks; by default integrated twice: the table's displacement, the quantity `rig hil` states its isolation in,
since feedback that takes 7 dB off the displacement may add 3-4 dB to the acceleration above the crossover) and
sums their squares per look. Each look is marked with what the rig did over it: isolating (ACTIVE,
isolation on), passive (isolation off or the valves at null), or settling (within settle_s of a switch: not
used). Over the newest window_s of isolating looks it compares the table's rms with its reference:

  reference (the first that exists)                   compared
  the newest window_s of passive looks, with floor     table/floor rms ratio, isolating vs passive
  accelerometers                                      (a change of the floor's vibration is not harm)
  the same without floor accelerometers               table rms, isolating vs passive
  floor accelerometers, nothing passive measured      table/floor rms ratio against 1 (0 dB)
  neither                                             nothing: said once, in one line

Per mount and for the whole table (the mounts' mean square). Worse by more than margin_db, in the whole table or
any mount, for hold_s (consecutive looks): `harm` holds one line saying so; the loop logs it, records it as an
event and holds isolation off (rig/runtime/gate.py `hold_isolation_off`, bumpless).
"""
from __future__ import annotations

import math
from collections import deque

import numba
import numpy as np
from scipy import signal

from rig.runtime.exchange import A_NEWEST, A_SLOTS, H_ACAP, H_ACCEL, H_AWIDTH, SLOT_COUNTER

LOOK_S = 0.1                      # the loop's watch: a look at least every tenth of a second
PASSIVE, ISOLATING, SETTLING = 0, 1, 2


QUANTITIES = ("acceleration", "velocity", "displacement")     # what is compared: acceleration integrated 0-2 times


def band_filter(band_hz, rate_hz: float, integrations: int):
    """The band-pass (2nd-order Butterworth) on acceleration, integrated `integrations` times in the band
    (1/(s + w_low) each: an integrator above the band's low edge, no drift below it), discretised by the
    bilinear transform (scipy.signal); second-order sections."""
    lo, hi = band_hz
    z, p, k = signal.butter(2, [2 * math.pi * lo, 2 * math.pi * hi], btype="bandpass", analog=True, output="zpk")
    p = np.append(p, [-2 * math.pi * lo] * integrations)
    zd, pd, kd = signal.bilinear_zpk(z, p, k, rate_hz)
    return signal.zpk2sos(zd, pd, kd)


@numba.njit(cache=True)
def filter_squares(sos, zi, x, out):
    """x (samples x channels) through the second-order sections `sos` (scipy's layout, transposed direct form II,
    as scipy.signal.sosfilt) from the state zi (sections x 2 x channels, updated in place); out[c] = the sum of
    the squares of channel c's output. Compiled: the look runs in the loop's slack, a few us instead of the
    hundreds scipy's checks cost a call."""
    ns, nc = sos.shape[0], x.shape[1]
    out[:] = 0.0
    for k in range(x.shape[0]):
        for c in range(nc):
            v = x[k, c]
            for i in range(ns):
                y = sos[i, 0] * v + zi[i, 0, c]
                zi[i, 0, c] = sos[i, 1] * v - sos[i, 4] * y + zi[i, 1, c]
                zi[i, 1, c] = sos[i, 2] * v - sos[i, 5] * y
                v = y
            out[c] += v * v


@numba.njit(cache=True)
def worse_db(on, ref, n, floor, out):
    """out[m] (mounts, then the whole table at n): 10 log10 of the isolating window's mean square over the
    reference's, in dB; with floor accelerometers (floor) each the table/floor ratio (channels n.. the floor under
    each mount); ref empty: against the floor itself (a ratio of 1)."""
    tiny = 1e-300
    for k in range(n + 1):
        if k < n:
            a = on[k] / max(on[n + k], tiny) if floor else on[k]
            b = (ref[k] / max(ref[n + k], tiny) if floor else ref[k]) if ref.shape[0] else 1.0
        else:
            a = on[:n].sum() / max(on[n:2 * n].sum(), tiny) if floor else on[:n].sum()
            b = ((ref[:n].sum() / max(ref[n:2 * n].sum(), tiny)) if floor else ref[:n].sum()) if ref.shape[0] else 1.0
        out[k] = 10.0 * math.log10(max(a, tiny) / max(b, tiny))


def warm() -> None:
    """Compile (or load from numba's cache) the filter and the comparison before any device runs: never in a
    running loop (the first comparison, uncompiled, held a 2 kHz loop's next wake-up by about a millisecond)."""
    filter_squares(np.zeros((1, 6)), np.zeros((1, 2, 1)), np.zeros((1, 1)), np.zeros(1))
    worse_db(np.ones(8), np.ones(8), 4, True, np.zeros(5))
    worse_db(np.ones(4), np.ones(0), 4, False, np.zeros(5))


class HarmSupervisor:
    """One per loop. look(io, isolating, t_s) at the loop's watch (every `look_periods(cap)` periods at most:
    the ring holds `cap` conversions); `harm` (a line) once it tripped."""

    def __init__(self, sup, n: int, nf: int, rate_hz: float, names: tuple[str, ...]) -> None:
        self.cfg, self.n, self.nf, self.names = sup, int(n), int(nf), tuple(names)
        self.rate_hz = float(rate_hz)
        hi = min(sup.band_high_hz, 0.45 * self.rate_hz)
        lo = min(sup.band_low_hz, 0.5 * hi)
        self.band_hz = (lo, hi)
        self.sos = band_filter(self.band_hz, self.rate_hz, QUANTITIES.index(sup.quantity))
        width = self.n + (self.n if self.nf >= self.n else 0)     # the table's, then the floor's under each mount
        self.width = width
        self.zi = np.zeros((self.sos.shape[0], 2, width))
        warm()
        self.last = -1                # the newest conversion taken
        self.looks = {PASSIVE: deque(), ISOLATING: deque()}   # per kind the newest looks: (sums of squares, count)
        self._sum_sq = {k: np.zeros(width) for k in self.looks}  # ... and their totals
        self._sum_n = {k: 0 for k in self.looks}
        self._worse = np.zeros(self.n + 1)     # the newest comparison, dB: per mount, then the whole table
        self.window_n = max(1, int(round(sup.window_s * self.rate_hz)))    # conversions in a window
        self.switched_s = -math.inf   # the loop time of the last switch
        self.was = None
        self.over_s: float | None = None      # since when the comparison is over the margin
        self.look_s = LOOK_S
        self.harm: str | None = None
        self.worst_db: float | None = None    # the newest comparison: whole table, dB against the reference
        self.max_mount_db = -math.inf          # the worst mount's worst comparison of the run
        self.reference = "none"
        self.skipped = 0              # conversions lost to the ring (the watch held up longer than the ring)
        self.said_no_reference = False

    def look_periods(self, io) -> int:
        """Periods between looks: a tenth of a second, or fewer at high rates (at most a quarter of the block's
        ring of conversions between looks: on the real clock a look may come a watch late)."""
        k = max(1, min(int(round(LOOK_S * self.rate_hz)), int(io[H_ACAP]) // 4))
        self.look_s = k / self.rate_hz
        return k

    # ---- the conversions since the last look ---------------------------------------------------------
    def _take(self, io) -> np.ndarray:
        a = int(io[H_ACCEL])
        cap, w = int(io[H_ACAP]), int(io[H_AWIDTH])
        newest = int(io[a + A_NEWEST])
        if newest < 0 or newest <= self.last:
            return np.empty((0, self.width))
        first = max(self.last + 1, newest - cap + 2)       # the slot after the newest may be being written
        if self.last >= 0 and first > self.last + 1:
            self.skipped += first - self.last - 1
        slots = io[a + A_SLOTS:a + A_SLOTS + cap * w].reshape(cap, w)
        want = np.arange(first, newest + 1)
        rows = slots[want % cap]
        ok = rows[:, SLOT_COUNTER] == want                  # a slot rewritten meanwhile: left out
        self.last = newest
        vals = rows[ok, 1 + self.n:]
        return vals[:, :self.width] if self.nf >= self.n else vals[:, :self.n]

    # ---- one look ------------------------------------------------------------------------------------
    def look(self, io, isolating: bool | None, t_s: float) -> str | None:
        """Take the new conversions, mark them (isolating None: neither, e.g. a stand tracking a reference),
        compare. Returns the harm line the moment it trips. It runs in the loop's slack (half a period at 2 kHz),
        so its cost does not grow with the window: running sums per kind, the comparison compiled."""
        x = self._take(io)
        sq = np.zeros(self.width)
        if x.shape[0]:
            filter_squares(self.sos, self.zi, np.ascontiguousarray(x), sq)
        if isolating != self.was:
            self.was, self.switched_s = isolating, t_s
            self.over_s = None
            if isolating:
                self._clear(ISOLATING)                   # a new isolated stretch: judged on its own
        settled = t_s - self.switched_s >= self.cfg.settle_s + self.look_s
        kind = SETTLING if not settled or isolating is None else ISOLATING if isolating else PASSIVE
        if kind != SETTLING:
            self._add(kind, sq, x.shape[0])
        if self.harm is not None or kind != ISOLATING:
            return None
        return self._compare(t_s)

    def _clear(self, kind: int) -> None:
        self.looks[kind].clear()
        self._sum_sq[kind][:] = 0.0
        self._sum_n[kind] = 0

    def _add(self, kind: int, sq: np.ndarray, count: int) -> None:
        """One look into its kind's window; the oldest looks leave once the rest still fill window_s."""
        looks, tot = self.looks[kind], self._sum_sq[kind]
        looks.append((sq, count))
        tot += sq
        self._sum_n[kind] += count
        while len(looks) > 1 and self._sum_n[kind] - looks[0][1] >= self.window_n:
            old, c = looks.popleft()
            tot -= old
            self._sum_n[kind] -= c

    def _window(self, kind: int):
        """The newest window_s of looks of this kind: per channel mean square, or None when not that much."""
        count = self._sum_n[kind]
        if count < self.window_n:
            return None
        return np.maximum(self._sum_sq[kind], 0.0) / count     # (a running sum: never below 0 by rounding)

    def _compare(self, t_s: float) -> str | None:
        on = self._window(ISOLATING)
        if on is None:
            return None
        n, floor = self.n, self.nf >= self.n
        off = self._window(PASSIVE)
        if off is not None:
            self.reference = "isolation off (table/floor)" if floor else "isolation off"
        elif floor:
            self.reference = "the floor accelerometers"
        else:
            self.reference = "none"
            return None
        worse = self._worse
        worse_db(on, off if off is not None else on[:0], n, floor, worse)    # dB per mount, then the table
        self.worst_db = float(worse[n])
        m = int(np.argmax(worse[:n]))
        self.max_mount_db = max(self.max_mount_db, float(worse[m]))
        if max(worse[n], worse[m]) <= self.cfg.margin_db:
            self.over_s = None
            return None
        if self.over_s is None:
            self.over_s = t_s
        if t_s - self.over_s < self.cfg.hold_s:
            return None
        lo, hi = self.band_hz
        self.harm = (f"do-no-harm: isolation made the table worse than {self.reference}: {self.names[m]} "
                     f"{worse[m]:+.1f} dB, the whole table {worse[n]:+.1f} dB ({lo:g}-{hi:g} Hz {self.cfg.quantity} "
                     f"rms over {self.cfg.window_s:g} s; margin {self.cfg.margin_db:g} dB for {self.cfg.hold_s:g} s) "
                     f"at t = {t_s:.2f} s: isolation switched off and held off")
        return self.harm

    @property
    def worst_mount_db(self) -> dict:
        """The newest comparison per mount, dB against the reference ({} before the first)."""
        if self.worst_db is None:
            return {}
        return {self.names[m]: round(float(self._worse[m]), 2) for m in range(self.n)}

    def no_reference_line(self) -> str | None:
        """Once, when isolating without any reference: the supervisor cannot judge (no floor accelerometers,
        nothing measured with isolation off yet)."""
        if self.said_no_reference or self.reference != "none" or self.nf >= self.n:
            return None
        if self._window(ISOLATING) is None or self._window(PASSIVE) is not None:
            return None
        self.said_no_reference = True
        return (f"do-no-harm: no reference to judge isolation by (no floor accelerometers, and isolation has not "
                f"been off for {self.cfg.window_s:g} s in this run): switch isolation off for that long to give "
                f"it one")

    def summary(self) -> dict:
        """For the run's JSON and the recording's attributes."""
        return {"tripped": self.harm is not None, "harm": self.harm or "", "reference": self.reference,
                "table_vs_reference_db": None if self.worst_db is None else round(self.worst_db, 2),
                "per_mount_db": self.worst_mount_db,
                "worst_mount_db_of_run": None if self.max_mount_db == -math.inf else round(self.max_mount_db, 2),
                "quantity": self.cfg.quantity, "margin_db": self.cfg.margin_db,
                "band_hz": [round(b, 3) for b in self.band_hz], "window_s": self.cfg.window_s,
                "conversions_skipped": self.skipped}

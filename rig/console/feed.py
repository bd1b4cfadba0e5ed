"""From the loop's rows to what the page draws (the web server's side; numpy and scipy only).

- Traces: per mount acceleration, stroke and valve command, kept for the last TRACE_S seconds as a min/max
  envelope in buckets of 1 / BUCKETS_PER_S seconds (two points a bucket, in the order they occurred), so a
  spike or a command at the clamp stays visible however the rate compares with the screen's pixels.
- Lifecycle state, isolation, fault, counters: the newest row's flag columns. (An isolation switch is an
  event through the loop's own log record, `isolation on`, logged where the gate applies it: the page's
  event log has each event once, on one clock.)
- Loop timing: p50/p99/max of the rows' wake latency and compute time over the last TIMING_S seconds.
- Table motion spectrum: the table's heave acceleration (the mean of the mounts' accelerometers) sorted by
  what the isolation was doing (on: ACTIVE with isolation on; off: INACTIVE, or ACTIVE with isolation off),
  the first SETTLE_S after each switch left out, kept at about SPECTRUM_FS_HZ (block means); the amplitude
  spectral density of each (Welch) every SPECTRUM_EVERY_S, from the last SPECTRUM_S seconds of each.
- VC curves: one-third-octave rms velocity against the vibration criteria (controllers/vibration_criteria.py)
  from the same spectra, and the class each meets.
A chirp identification's run (layout kind "chirp") has traces and flags, but no spectra: it plays a chirp,
not isolation.
"""
from __future__ import annotations

import math
import time

import numpy as np
import scipy.signal

from controllers import vibration_criteria as criteria

TRACE_S = 10.0
BUCKETS_PER_S = 100
TIMING_S = 10.0
SPECTRUM_S = 20.0
SPECTRUM_EVERY_S = 2.0
SEGMENT_S = 4.0              # Welch segment: 0.25 Hz resolution
SETTLE_S = 1.0
F_MIN_HZ, F_MAX_HZ = 0.5, 200.0
SPECTRUM_FS_HZ = 1000.0      # the heave is kept at about this rate (block means): five times the top of the plot
STATE_NAMES = ("UNCONFIGURED", "INACTIVE", "ACTIVE", "FAULT")
_INACTIVE, _ACTIVE = 1, 2


class Feed:
    """The state of one attached run, built from its rows. layout: {"channels": [{"name", "width", ...}],
    "rate_hz", "mounts": [...], "limits": {...}} as the loop's side sends it."""

    def __init__(self, layout: dict) -> None:
        self.layout = layout
        self.rate_hz = float(layout["rate_hz"])
        self.mounts = list(layout["mounts"])
        n = self.n = len(self.mounts)
        off, col = {}, 0
        for ch in layout["channels"]:
            off[ch["name"]] = (col, ch["width"])
            col += ch["width"]
        self.ncols = col
        self.col = {k: v[0] for k, v in off.items()}
        a, x, u = self.col["accel_mps2"], self.col["stroke_m"], self.col["valve_cmd_V"]
        self.trace_cols = np.r_[a:a + n, x:x + n, u:u + n]        # accel per mount, stroke, command
        self.trace_names = ([f"accel_mps2.{m}" for m in self.mounts] + [f"stroke_m.{m}" for m in self.mounts]
                            + [f"valve_cmd_V.{m}" for m in self.mounts])
        self.bucket = max(1, int(round(self.rate_hz / BUCKETS_PER_S)))
        pts = (2 if self.bucket > 1 else 1) * int(math.ceil(TRACE_S * self.rate_hz / self.bucket))
        self._tr_t = _Ring(pts, 1)
        self._tr_v = _Ring(pts, len(self.trace_cols))
        self._pending = np.empty((0, self.ncols))
        self._new_t: list[np.ndarray] = []
        self._new_v: list[np.ndarray] = []
        nt = int(TIMING_S * self.rate_hz)
        self._wake = _Ring(nt, 1)
        self._comp = _Ring(nt, 1)
        self.spec_q = max(1, int(self.rate_hz // SPECTRUM_FS_HZ))     # block length of the block means
        self.spec_fs = self.rate_hz / self.spec_q
        ns = int(SPECTRUM_S * self.spec_fs)
        self._spec = {"off": _Ring(ns, 1), "on": _Ring(ns, 1)}
        self._carry = np.empty(0)          # heave samples of the current class short of a whole block
        self._cls = None                   # the class of the last row ("on", "off", None)
        self._settle_left = 0
        self._spec_due = time.monotonic() + SPECTRUM_EVERY_S
        self._timing_due = 0.0
        self.now: dict = {}
        self.timing: dict | None = None
        self.spectrum: dict | None = None
        self.vc: dict | None = None
        self.rows_seen = 0
        self.spectra = layout.get("kind", "run") != "chirp"
        self.changed = set()               # parts recomputed since the last delta

    # ---- rows in ------------------------------------------------------------------------------------------
    def add(self, rows: np.ndarray) -> None:
        """Take the rows read from the live ring (any number, oldest first)."""
        if len(rows) == 0:
            return
        self.rows_seen += len(rows)
        self._flags(rows)
        self._timing_rows(rows)
        if self.spectra:
            self._spectrum_rows(rows)
        rows = np.concatenate([self._pending, rows]) if len(self._pending) else rows
        nb = len(rows) // self.bucket
        if nb:
            t, v = self._envelope(rows[:nb * self.bucket], nb)
            self._tr_t.put(t[:, None])
            self._tr_v.put(v)
            self._new_t.append(t)
            self._new_v.append(v)
        self._pending = rows[nb * self.bucket:].copy()

    def _envelope(self, rows: np.ndarray, nb: int) -> tuple[np.ndarray, np.ndarray]:
        b = self.bucket
        t = rows[:, self.col["time_s"]].reshape(nb, b)
        x = rows[:, self.trace_cols].reshape(nb, b, -1)
        if b == 1:
            return t[:, 0], x[:, 0, :]
        i_lo, i_hi = x.argmin(axis=1), x.argmax(axis=1)
        lo = np.take_along_axis(x, i_lo[:, None, :], axis=1)[:, 0, :]
        hi = np.take_along_axis(x, i_hi[:, None, :], axis=1)[:, 0, :]
        lo_first = i_lo <= i_hi
        first, second = np.where(lo_first, lo, hi), np.where(lo_first, hi, lo)
        tt = np.stack([t[:, 0], t[:, b // 2]], axis=1).reshape(-1)
        vv = np.stack([first, second], axis=1).reshape(2 * nb, -1)
        return tt, vv

    def _flags(self, rows: np.ndarray) -> None:
        c = self.col
        last = rows[-1]
        st = int(last[c["lifecycle_state"]])
        self.now = {"t_s": float(last[c["time_s"]]), "state": STATE_NAMES[st] if 0 <= st < 4 else str(st),
                    "isolation": bool(last[c["isolation_on"]] > 0.5), "fault": bool(last[c["fault"]] > 0.5),
                    "overruns": int(last[c["overruns"]]), "skipped_periods": int(last[c["skipped_periods"]]),
                    "cmd_limited": bool(last[c["cmd_limited"]] > 0.5)}

    def _timing_rows(self, rows: np.ndarray) -> None:
        self._wake.put(rows[:, [self.col["wake_latency_us"]]])
        self._comp.put(rows[:, [self.col["compute_prev_us"]]])
        now = time.monotonic()
        if now >= self._timing_due:
            self._timing_due = now + 0.5
            w, c = self._wake.values()[:, 0], self._comp.values()[:, 0]
            self.timing = {"window_s": len(w) / self.rate_hz, "wake_latency_us": _pct(w), "compute_us": _pct(c)}
            self.changed.add("timing")

    def _spectrum_rows(self, rows: np.ndarray) -> None:
        c = self.col
        st = rows[:, c["lifecycle_state"]].astype(int)
        iso = rows[:, c["isolation_on"]] > 0.5
        cls = np.where(st == _ACTIVE, np.where(iso, 1, 0), np.where(st == _INACTIVE, 0, -1))
        heave = rows[:, c["accel_mps2"]:c["accel_mps2"] + self.n].mean(axis=1)
        # contiguous runs of one class; the first SETTLE_S after a change of class are left out
        edges = np.flatnonzero(np.diff(cls)) + 1
        for a, b in zip(np.r_[0, edges], np.r_[edges, len(cls)]):
            k = int(cls[a])
            name = ("off", "on")[k] if k >= 0 else None
            if name != self._cls:
                self._cls = name
                self._settle_left = int(SETTLE_S * self.rate_hz)
                self._carry = np.empty(0)
            skip = min(self._settle_left, b - a)
            self._settle_left -= skip
            if name is not None and b - a > skip:
                x = np.concatenate([self._carry, heave[a + skip:b]])
                q = self.spec_q
                k = len(x) // q
                self._carry = x[k * q:]
                if k:       # block means: an average over 1 ms, -0.6 dB at 200 Hz with 5 kHz rows
                    self._spec[name].put(x[:k * q].reshape(k, q).mean(axis=1)[:, None])
        now = time.monotonic()
        if now >= self._spec_due:
            self._spec_due = now + SPECTRUM_EVERY_S
            self._spectra()

    def _spectra(self) -> None:
        fs = self.spec_fs
        nper = int(SEGMENT_S * fs)
        out, psd = {}, {}
        for name, ring in self._spec.items():
            x = ring.values()[:, 0]
            if len(x) < nper:
                out[name] = {"seconds": len(x) / fs, "asd": None}
                continue
            f, S = scipy.signal.welch(x, fs=fs, window="hann", nperseg=nper, detrend="linear")
            sel = (f >= F_MIN_HZ) & (f <= min(F_MAX_HZ, fs / 2.5))
            psd[name] = (f[sel], S[sel])
            out[name] = {"seconds": len(x) / fs, "asd": np.sqrt(S[sel]).tolist()}
        freqs = next(iter(psd.values()))[0].tolist() if psd else []
        rms = {k: float(np.sqrt(np.trapezoid(S, fk))) for k, (fk, S) in psd.items()}
        self.spectrum = {"f_hz": freqs, "classes": out, "rms_mps2": rms, "segment_s": SEGMENT_S,
                         "window_s": SPECTRUM_S}
        self.changed.add("spectrum")
        if psd:
            self.vc = vc_panel(psd)
            self.changed.add("vc")

    # ---- out to the page --------------------------------------------------------------------------------
    def take_delta(self) -> dict:
        """What changed since the last call (trace points, flags, figures recomputed)."""
        msg = {"now": self.now, "rows_seen": self.rows_seen}
        if self._new_t:
            t = np.concatenate(self._new_t)
            v = np.concatenate(self._new_v)
            msg["traces"] = {"t": t.tolist(), "v": v.T.tolist()}
            self._new_t, self._new_v = [], []
        for part in self.changed:
            msg[part] = getattr(self, part)
        self.changed = set()
        return msg

    def full(self) -> dict:
        """Everything a page that has just connected needs: the layout and the whole history."""
        return {"layout": {k: v for k, v in self.layout.items() if k != "channels"},
                "trace_names": self.trace_names, "bucket_rows": self.bucket,
                "traces": {"t": self._tr_t.values()[:, 0].tolist(), "v": self._tr_v.values().T.tolist()},
                "now": self.now, "timing": self.timing, "spectrum": self.spectrum, "vc": self.vc,
                "rows_seen": self.rows_seen}


def vc_panel(psd: dict) -> dict:
    """The VC panel from the acceleration PSDs {class: (f_hz, S_a)}: band rms velocity (um/s) per
    one-third octave band, the class each meets, and the criterion lines over the bands."""
    out = {"available": True, "velocity_um_s": {}, "vc_class": {}}
    bands = None
    for name, (f, S) in psd.items():
        S_v = np.where(f > 0, S / np.maximum((2 * np.pi * f) ** 2, 1e-300), 0.0)    # a = j w v
        bands, rms = criteria.band_velocity_rms_from_psd(f, S_v, kind="velocity", f_lo_hz=1.0, f_hi_hz=100.0)
        out["velocity_um_s"][name] = (rms * 1e6).tolist()
        out["vc_class"][name] = criteria.vc_class(rms * 1e6, bands)
    out["band_hz"] = [float(b) for b in bands]
    out["criteria"] = {name: criteria.criterion_um_s(name, bands).tolist() for name, _, _ in criteria.CRITERIA}
    return out


def _pct(a: np.ndarray) -> dict:
    if len(a) == 0:
        return {"p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(a, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(a.max())}


class _Ring:
    """A fixed-size history of rows (the last `cap` put), for the server's own bookkeeping."""

    def __init__(self, cap: int, width: int) -> None:
        self.cap = max(1, cap)
        self.a = np.zeros((self.cap, width))
        self.n = 0                 # rows put so far

    def put(self, rows: np.ndarray) -> None:
        k = len(rows)
        if k >= self.cap:
            self.a[:] = rows[-self.cap:]
            self.n += k
            self.a = np.roll(self.a, self.n % self.cap, axis=0)
            return
        i = self.n % self.cap
        j = min(k, self.cap - i)
        self.a[i:i + j] = rows[:j]
        self.a[:k - j] = rows[j:]
        self.n += k

    def values(self) -> np.ndarray:
        """The rows kept, oldest first (a copy)."""
        if self.n < self.cap:
            return self.a[:self.n].copy()
        i = self.n % self.cap
        return np.concatenate([self.a[i:], self.a[:i]])

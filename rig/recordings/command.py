"""What the recorded valve command is, read from the command itself (never from how it was meant to be made).

`analyse(cmd, fs)` returns a `Command`:
  kind      sweep (linear or logarithmic, one or several levels), multisine (periodic, a line spectrum), steps
            (piecewise constant), noise (broadband, neither), sine (one frequency), flat
  band_hz   sweeps: the range of the instantaneous frequency; multisines: the excited lines; else where the
            command's power is (within 30 dB of the peak of its smoothed spectrum)
  segments  [(i0, i1, level)]: the same signal repeated, at one level or several (a multi-level chirp); level is
            the scale of each repetition relative to the largest
  phase     instantaneous phase of a sweep (for harmonics locked to it), else None
  period    samples per period of a periodic command, with its excited lines (multisine), else None
The evidence the diagnosis gives follows from this: harmonics of the instantaneous phase for sweeps, the empty
lines for a multisine, gain by level for a repeated command at several levels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import hilbert, welch

KINDS = ("sweep", "multisine", "steps", "noise", "sine", "flat")


@dataclass
class Segment:
    i0: int
    i1: int
    level: float                 # scale relative to the largest repetition (1.0 for the largest)
    peak_V: float


@dataclass
class Command:
    kind: str
    fs_hz: float
    n: int
    band_hz: tuple[float, float]
    peak_V: float
    rms_V: float
    wide_band_hz: tuple[float, float] = (0.0, 0.0)   # within 60 dB of the peak: where a response is still seen
    segments: list[Segment] = field(default_factory=list)
    repeat_samples: int = 0                 # lag of the repetition (0: not repeated)
    phase: np.ndarray | None = None         # sweeps: instantaneous phase, rad
    sweep_law: str = ""                     # linear | logarithmic
    period: int = 0                         # multisine: samples per period
    excited_lines: np.ndarray | None = None   # multisine: indices k of the excited lines (frequency k fs / period)
    start_V: float = 0.0
    notes: list[str] = field(default_factory=list)
    unit: str = "V"                         # the command's unit (a plant file's command may be N or A)

    @property
    def multilevel(self) -> bool:
        lv = [s.level for s in self.segments]
        return len(lv) >= 2 and max(lv) / max(min(lv), 1e-12) > 1.3

    @property
    def starts_mid_run(self) -> bool:
        """A command far from null at the first sample: the plant was moving before the recording began (or the
        command jumps at t = 0; either way a model started from rest is wrong for the first instants)."""
        return abs(self.start_V) > 0.02 * max(self.peak_V, 1e-12)

    def describe(self) -> str:
        lo, hi = self.band_hz
        what = {"sweep": f"{self.sweep_law or 'frequency'} sweep", "multisine": "periodic multisine",
                "steps": "steps", "noise": "broadband random command", "sine": "single sine", "flat": "constant"}
        s = f"{what.get(self.kind, self.kind)}, {lo:.3g}-{hi:.3g} Hz, peak {self.peak_V:.3g} {self.unit}"
        if self.kind == "multisine" and self.period:
            s += (f", period {self.period / self.fs_hz:.4g} s ({self.n // self.period} periods), "
                  f"{len(self.excited_lines)} excited lines")
        if self.multilevel:
            s += ", levels " + ", ".join(f"{s_.peak_V:.3g}" for s_ in self.segments) + f" {self.unit}"
        elif len(self.segments) > 1:
            s += f", repeated {len(self.segments)} times"
        return s


def _band(cmd: np.ndarray, fs: float, rel_db: float = 30.0) -> tuple[float, float]:
    n = len(cmd)
    nper = int(min(n, max(256, 2 ** int(math.log2(max(256, 8 * fs))))))
    f, P = welch(cmd - cmd.mean(), fs=fs, nperseg=nper)
    f, P = f[1:], P[1:]
    if not np.any(P > 0):
        return 0.0, 0.0
    k = max(3, (len(P) // 200) | 1)
    from scipy.ndimage import median_filter
    Ps = median_filter(P, size=k, mode="nearest")
    on = np.flatnonzero(Ps > np.max(Ps) * 10 ** (-rel_db / 10))
    if on.size == 0:
        return float(f[0]), float(f[-1])
    return float(f[on[0]]), float(min(f[on[-1]], 0.45 * fs))


def _repetition(cmd: np.ndarray, fs: float) -> int:
    """Lag (samples) at which the command repeats itself (a period, or the next level of a multi-level run)."""
    n = len(cmd)
    x = cmd - cmd.mean()
    m = 1 << int(math.ceil(math.log2(2 * n)))
    X = np.fft.rfft(x, m)
    ac = np.fft.irfft(np.abs(X) ** 2, m)[:n]
    if ac[0] <= 0:
        return 0
    # normalise by the overlap so that a scaled copy over part of the record still stands out
    lags = np.arange(n)
    ov = np.maximum(n - lags, 1)
    acn = ac / ac[0] * n / ov
    below = np.flatnonzero(acn[: n // 2] < 0.3)
    lo = int(max(0.2 * fs, below[0] if below.size else n))     # past the command's own correlation time
    hi = int(0.8 * n)
    if hi <= lo:
        return 0
    seg = acn[lo:hi]
    top = float(np.max(seg))
    k = int(np.argmax(seg >= top - 0.02 * abs(top)))      # the first of equal peaks: a period, not a multiple
    w = max(1, int(0.01 * fs))
    k = k + int(np.argmax(seg[k:k + w]))                    # the top of that peak
    peak = float(seg[k])
    base = float(np.median(np.abs(seg)))
    if peak > 0.25 and peak > 8 * max(base, 1e-3):
        return lo + k
    return 0


def _offset(cmd: np.ndarray, lag: int, fs: float) -> int:
    """Where the repetitions start (a recording may begin mid-way through one). cmd(t + lag) = r cmd(t) with r
    constant within a repetition, so a boundary is where the windowed ratio r jumps; failing that (too little
    overlap), where a sweep restarts (its instantaneous frequency falls back); 0 when neither shows (a periodic
    command at one level)."""
    n = len(cmd)
    w = max(1, int(max(0.5 * fs, lag / 50)))         # a slow recording: at least a sample
    starts = np.arange(0, max(0, n - lag - w), w)
    if len(starts) >= 3:
        a = np.array([np.dot(cmd[i:i + w], cmd[i:i + w]) for i in starts])
        b = np.array([np.dot(cmd[i + lag:i + lag + w], cmd[i:i + w]) for i in starts])
        r = np.where(a > 1e-6 * np.max(a), b / np.maximum(a, 1e-300), np.nan)
        fin = np.flatnonzero(np.isfinite(r))
        if len(fin) >= 3:
            jumps = np.abs(np.diff(r[fin])) / np.maximum(np.abs(r[fin][:-1]), 1e-12)
            j = int(np.argmax(jumps))
            if jumps[j] >= 0.1:
                return int(starts[fin[j + 1]] % lag)
    from scipy.ndimage import median_filter
    z = hilbert(cmd - cmd.mean())
    env = np.abs(z)
    on = env > 0.2 * np.max(env)
    if on.sum() < 10:
        return 0
    idx = np.flatnonzero(on)
    fi = np.gradient(np.unwrap(np.angle(z))) * fs / (2 * math.pi)
    fi = median_filter(fi[idx], size=max(3, int(0.2 * fs) | 1), mode="nearest")     # over the samples that are on
    sp = max(1, int(0.25 * fs))                           # the analytic signal smears a reset over ~0.1 s
    if len(fi) <= 2 * sp + 2:
        return 0
    drop = fi[:-sp] - fi[sp:]
    rng_ = np.percentile(fi, 95) - np.percentile(fi, 5)
    edge = int(0.5 * fs)                                  # it is unreliable at the ends
    drop[:edge] = 0.0
    drop[max(0, len(drop) - edge):] = 0.0
    big = np.flatnonzero(drop > 0.5 * rng_)
    if not big.size:
        return 0
    first = big[big < big[0] + 2 * sp]                    # the first reset: where its drop is largest
    j = int(first[np.argmax(drop[first])]) + sp // 2
    return int(idx[min(j, len(idx) - 1)] % lag)


def _segments(cmd: np.ndarray, lag: int, fs: float) -> list[Segment]:
    n = len(cmd)
    if lag <= 0:
        return [Segment(0, n, 1.0, float(np.max(np.abs(cmd))))]
    o = _offset(cmd, lag, fs)
    if o < 0.05 * lag or o > 0.95 * lag:
        o = 0
    cuts = sorted(set([0] + list(range(o, n, lag))))
    cuts = [c for c in cuts if c < n - 0.05 * lag] + [n]
    bounds = list(zip(cuts[:-1], cuts[1:]))
    full = [(a, b) for a, b in bounds if b - a >= 0.95 * lag]
    r0 = full[0][0] if full else bounds[0][0]
    ref = cmd[r0: r0 + lag]
    segs = []
    for a, b in bounds:
        part = cmd[a:b]
        k0 = lag - len(part) if (a == 0 and o > 0) else 0            # a partial first one ends like a full one
        m = max(0, min(len(part), len(ref) - k0))
        r = ref[k0:k0 + m]
        scale = float(np.dot(part[:m], r) / max(np.dot(r, r), 1e-300)) if m else 0.0
        segs.append(Segment(a, b, abs(scale), float(np.max(np.abs(cmd[a:b])))))
    top = max(s.level for s in segs) or 1.0
    for s in segs:
        s.level /= top
    return segs


def _sweep_phase(cmd: np.ndarray, fs: float, segments: list[Segment]) -> tuple[np.ndarray, np.ndarray, bool, str]:
    """Instantaneous phase/frequency per segment (analytic signal) and whether it reads as one sweep."""
    phase = np.zeros(len(cmd))
    finst = np.full(len(cmd), np.nan)          # nan where the command is off (pauses between levels)
    ok, laws = [], []
    for s in segments:
        x = cmd[s.i0:s.i1]
        if len(x) < 64 or np.ptp(x) <= 0:
            continue
        z = hilbert(x - x.mean())
        ph = np.unwrap(np.angle(z))
        phase[s.i0:s.i1] = ph
        fi = np.gradient(ph) * fs / (2 * math.pi)
        env = np.abs(z)
        finst[s.i0:s.i1] = np.where(env > 0.3 * np.max(env), fi, np.nan)
        m = len(x) // 20
        core = slice(m, len(x) - m) if len(x) > 40 else slice(None)
        on = env[core] > 0.3 * np.max(env)
        if on.mean() < 0.8:
            ok.append(False)
            continue
        from scipy.ndimage import median_filter
        fs_med = median_filter(fi[core], size=max(3, int(0.5 * fs) | 1), mode="nearest")[on]
        tt = np.arange(len(x))[core][on]
        if len(tt) < 10 or np.ptp(fs_med) <= 0:
            ok.append(False)
            continue
        rank = np.corrcoef(np.argsort(np.argsort(fs_med)), tt)[0, 1]
        rel_env = float(np.std(env[core][on]) / np.mean(env[core][on]))
        ok.append(abs(rank) > 0.97 and rel_env < 0.25 and np.ptp(fs_med) > 0.2 * np.max(fs_med))
        lin = np.corrcoef(fs_med, tt)[0, 1]
        lg = np.corrcoef(np.log(np.maximum(fs_med, 1e-3)), tt)[0, 1]
        laws.append("linear" if abs(lin) >= abs(lg) else "logarithmic")
    sweep = bool(ok) and sum(ok) >= max(1, len(ok) - 1)
    law = max(set(laws), key=laws.count) if laws else ""
    return phase, finst, sweep, law


def _multisine(cmd: np.ndarray, period: int) -> np.ndarray | None:
    """Excited lines of a periodic command when its spectrum over whole periods is a line spectrum (the null
    command before and after the run, a rig's settle time and tail, is left aside)."""
    act = np.flatnonzero(np.abs(cmd) > 1e-9 * np.max(np.abs(cmd)))
    cmd = cmd[act[0]: act[-1] + 1] if act.size else cmd
    P = len(cmd) // period
    if P < 2 or period < 16:            # one period cannot show that it repeats
        return None
    x = cmd[: P * period].reshape(P, period)
    X = np.fft.rfft(x.mean(axis=0))
    pw = np.abs(X) ** 2
    pw[0] = 0.0
    if pw.sum() <= 0:
        return None
    on = np.flatnonzero(pw > 1e-4 * pw.max())
    if len(on) < 3:
        return None
    spread = float(np.mean(np.std(x, axis=0) ** 2) / max(np.mean(x ** 2), 1e-300))
    if spread > 1e-3:                  # the periods differ: not one repeated period
        return None
    return on


def analyse(cmd_V: np.ndarray, fs: float, unit: str = "V") -> Command:
    """The command's kind, band and levels; `unit` (V, N, A: the recording's command_unit) for the text."""
    out = _classify(cmd_V, fs)
    out.unit = unit
    return out


def _classify(cmd_V: np.ndarray, fs: float) -> Command:
    cmd = np.asarray(cmd_V, float)
    n = len(cmd)
    peak = float(np.max(np.abs(cmd))) if n else 0.0
    rms = float(np.sqrt(np.mean((cmd - cmd.mean()) ** 2))) if n else 0.0
    if n < 16 or np.ptp(cmd) <= 0:
        return Command("flat", fs, n, (0.0, 0.0), peak, rms, (0.0, 0.0), [Segment(0, n, 1.0, peak)],
                       start_V=float(cmd[0]) if n else 0.0)
    band = _band(cmd, fs)
    lag = _repetition(cmd, fs)
    segs = _segments(cmd, lag, fs)
    out = Command("noise", fs, n, band, peak, rms, _band(cmd, fs, 60.0), segs, repeat_samples=lag,
                  start_V=float(cmd[0]))
    flat_steps = float(np.mean(np.diff(cmd) == 0.0))
    if flat_steps > 0.9:
        out.kind = "steps"
        return out
    if lag:
        lines = _multisine(cmd, lag)
        if lines is not None and len(lines) >= 3:
            out.kind, out.period, out.excited_lines = "multisine", lag, lines
            out.band_hz = (float(lines[0] * fs / lag), float(lines[-1] * fs / lag))
            out.segments = [Segment(0, n, 1.0, peak)]
            return out
    phase, finst, sweep, law = _sweep_phase(cmd, fs, segs)
    if sweep:
        out.kind, out.phase, out.sweep_law = "sweep", phase, law
        from scipy.ndimage import median_filter
        on = np.isfinite(finst)
        fi = median_filter(np.where(on, finst, 0.0), size=max(3, int(0.5 * fs) | 1), mode="nearest")
        m = n // 200
        core = np.zeros(n, bool)
        core[m:n - m] = True
        lo, hi = np.percentile(np.clip(fi[core & on], 0.0, fs / 2), [0.5, 99.5])
        out.band_hz = (max(float(lo), 3.0 * fs / n), min(float(hi), 0.45 * fs))
        return out
    # one sine: nearly all power in one Welch bin; segments of at least a quarter of the record, so that a slow
    # narrow-band command (a closed loop's at a low sample rate) is not three 0.25 Hz bins, i.e. a "sine"
    f, P = welch(cmd - cmd.mean(), fs=fs, nperseg=int(min(n, max(4 * fs, n // 4))))
    if P.sum() > 0 and np.sort(P)[-3:].sum() > 0.95 * P.sum():
        out.kind = "sine"
        out.phase = phase
    return out


def harmonic_window_ok(cmd: Command) -> bool:
    """Harmonics locked to the instantaneous phase mean something only for a sweep."""
    return cmd.kind == "sweep" and cmd.phase is not None

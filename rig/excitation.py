"""Valve-command signals for identification and diagnosis runs (controllers/playback.py plays one back).

Each generator returns an `Excitation`: the command samples (V, held by the DAC between samples) and a short
description of what they are. What the diagnosis concludes never depends on that description: it reads the
recorded command itself (rig.recordings.command). The signals:

- linear_chirp       the paper's identification input, f0 -> f1 linearly in time
- log_sweep          f0 -> f1 exponentially in time (equal time per decade)
- multilevel_chirp   the same linear chirp at several amplitudes back to back: saturation loses gain at the top
                     level, the spool deadband at the bottom one, a linear effect is the same at every level
- odd_multisine      an odd random-phase multisine (random-odd design: one odd line in each group of three left
                     out): in a linear system the even and the unexcited odd lines stay empty, so energy there is
                     nonlinear distortion, even or odd (Pintelon & Schoukens, System Identification, ch. 4)
- band_noise         Gaussian noise band-limited to f0..f1, clipped at the amplitude
- steps              random levels held for random times
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rig.errors import RigError


@dataclass
class Excitation:
    cmd_V: np.ndarray
    fs_hz: float
    kind: str                          # linear_chirp, log_sweep, multilevel_chirp, odd_multisine, band_noise, steps
    info: dict = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return len(self.cmd_V) / self.fs_hz

    @property
    def t_s(self) -> np.ndarray:
        return np.arange(len(self.cmd_V)) / self.fs_hz

    @property
    def peak_V(self) -> float:
        return float(np.max(np.abs(self.cmd_V))) if len(self.cmd_V) else 0.0

    @property
    def slew_V_per_s(self) -> float:
        """The largest step between samples, per second (what the safety slew limit sees)."""
        return float(np.max(np.abs(np.diff(self.cmd_V)))) * self.fs_hz if len(self.cmd_V) > 1 else 0.0

    def attrs(self) -> dict:
        """Flat attributes for a recording file (HDF5 attrs take scalars and flat lists)."""
        out = {"excitation": self.kind}
        for k, v in self.info.items():
            if isinstance(v, (int, float, str)) or (isinstance(v, list) and len(v) <= 16):
                out[k] = v
        return out


def _n(fs: float, duration_s: float) -> int:
    return int(round(duration_s * fs))


def _fade_out(x: np.ndarray, fs: float, fade_s: float = 0.05) -> np.ndarray:
    """A half-cosine taper over the last fade_s: a segment that stops mid-cycle ends at zero, within the slew."""
    k = min(len(x), max(1, int(fade_s * fs)))
    x = x.copy()
    x[-k:] *= 0.5 * (1 + np.cos(np.linspace(0.0, math.pi, k)))
    return x


def linear_chirp(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0,
                 amplitude_V: float = 2.0) -> Excitation:
    """A sin(2 pi (f0 t + (f1 - f0) t^2 / (2 T))): the paper's chirp."""
    t = np.arange(_n(fs, duration_s)) / fs
    phase = 2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) / duration_s * t ** 2)
    return Excitation(amplitude_V * np.sin(phase), fs, "linear_chirp",
                      {"f0_hz": f0_hz, "f1_hz": f1_hz, "amplitude_V": amplitude_V})


def log_sweep(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0,
              amplitude_V: float = 2.0) -> Excitation:
    """A sin(2 pi f0 T / ln(f1/f0) (exp(t ln(f1/f0) / T) - 1)): the instantaneous frequency grows exponentially."""
    t = np.arange(_n(fs, duration_s)) / fs
    k = math.log(f1_hz / f0_hz) / duration_s
    phase = 2 * np.pi * f0_hz * np.expm1(k * t) / k
    return Excitation(_fade_out(amplitude_V * np.sin(phase), fs), fs, "log_sweep",
                      {"f0_hz": f0_hz, "f1_hz": f1_hz, "amplitude_V": amplitude_V})


def multilevel_chirp(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0,
                     levels_V=(0.5, 1.5, 3.0), pause_s: float = 0.5) -> Excitation:
    """The same linear chirp (duration_s each) at every level, back to back with pause_s at null between."""
    levels = [float(a) for a in levels_V]
    base = linear_chirp(fs, duration_s, f0_hz, f1_hz, 1.0).cmd_V
    base = _fade_out(base, fs)
    gap = np.zeros(_n(fs, pause_s))
    parts, starts = [], []
    for i, a in enumerate(levels):
        starts.append(sum(len(p) for p in parts))
        parts.append(a * base)
        if i < len(levels) - 1:
            parts.append(gap)
    return Excitation(np.concatenate(parts), fs, "multilevel_chirp",
                      {"f0_hz": f0_hz, "f1_hz": f1_hz, "levels_V": levels, "segment_s": duration_s,
                       "pause_s": pause_s, "segment_starts_s": [s / fs for s in starts]})


def odd_multisine(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0,
                  amplitude_V: float = 2.0, period_s: float = 10.0, seed: int = 0) -> Excitation:
    """Odd random-phase multisine with period period_s (frequency resolution 1/period_s), repeated over
    duration_s (rounded to whole periods, at least one): lines at odd multiples of 1/period_s in f0..f1, one of
    each three consecutive odd lines left out at random, flat amplitudes, random phases, scaled to the peak."""
    rng = np.random.default_rng(seed)
    n_per = _n(fs, period_s)
    df = fs / n_per
    k_lo, k_hi = max(1, int(math.ceil(f0_hz / df))), int(math.floor(f1_hz / df))
    odd = [k for k in range(k_lo, k_hi + 1) if k % 2 == 1]
    excited = []
    for g in range(0, len(odd), 3):
        grp = odd[g:g + 3]
        if len(grp) == 3:
            skip = grp[int(rng.integers(3))]
            excited += [k for k in grp if k != skip]
        else:
            excited += grp
    if not excited:
        raise ValueError(f"odd multisine: no odd line of {df:g} Hz between {f0_hz:g} and {f1_hz:g} Hz")
    X = np.zeros(n_per // 2 + 1, complex)
    X[excited] = np.exp(2j * np.pi * rng.random(len(excited)))
    one = np.fft.irfft(X, n_per)
    one *= amplitude_V / np.max(np.abs(one))
    periods = max(1, int(round(duration_s / period_s)))
    cmd = np.tile(one, periods)
    return Excitation(cmd, fs, "odd_multisine",
                      {"f0_hz": f0_hz, "f1_hz": f1_hz, "amplitude_V": amplitude_V, "period_s": n_per / fs,
                       "periods": periods, "excited_lines": excited, "line_spacing_hz": df})


def band_noise(fs: float, duration_s: float, f0_hz: float = 0.1, f1_hz: float = 100.0, amplitude_V: float = 2.0,
               seed: int = 0) -> Excitation:
    """Gaussian noise band-limited to f0..f1 (brick-wall in the frequency domain), rms amplitude/3, clipped to
    +-amplitude (the clip touches about 0.3 % of the samples)."""
    rng = np.random.default_rng(seed)
    n = _n(fs, duration_s)
    X = np.fft.rfft(rng.standard_normal(n))
    f = np.fft.rfftfreq(n, 1.0 / fs)
    X[(f < f0_hz) | (f > f1_hz)] = 0.0
    x = np.fft.irfft(X, n)
    x *= (amplitude_V / 3.0) / max(float(np.std(x)), 1e-300)
    return Excitation(np.clip(x, -amplitude_V, amplitude_V), fs, "band_noise",
                      {"f0_hz": f0_hz, "f1_hz": f1_hz, "amplitude_V": amplitude_V})


def steps(fs: float, duration_s: float, amplitude_V: float = 2.0, hold_s: tuple[float, float] = (0.3, 2.0),
          seed: int = 0) -> Excitation:
    """Random levels uniform in +-amplitude, each held for a random time in hold_s."""
    rng = np.random.default_rng(seed)
    n = _n(fs, duration_s)
    cmd = np.empty(n)
    i = 0
    while i < n:
        k = max(1, int(rng.uniform(*hold_s) * fs))
        cmd[i:i + k] = rng.uniform(-amplitude_V, amplitude_V)
        i += k
    return Excitation(cmd, fs, "steps", {"amplitude_V": amplitude_V, "hold_s": list(hold_s)})


KINDS = ("linear_chirp", "log_sweep", "multilevel_chirp", "odd_multisine", "band_noise", "steps")


def for_chirp_run(fs: float, duration_s: float, f0_hz: float, f1_hz: float, amplitude_V: float, *,
                  levels_V=None, multisine: bool = False, period_s: float = 10.0, seed: int = 0) -> Excitation | None:
    """The signal `rig chirp --levels / --multisine` plays back, or None for the plain chirp (which the loop
    computes itself). Bad settings raise RigError naming the option."""
    if not levels_V and not multisine:
        return None
    if levels_V and multisine:
        raise RigError("--levels/--multisine: choose one")
    if not 0 <= f0_hz < f1_hz < fs / 2:
        raise RigError(f"--f0/--f1: expected 0 <= f0 < f1 < rate/2 = {fs / 2:g} Hz, got {f0_hz:g}, {f1_hz:g}")
    if duration_s <= 0:
        raise RigError(f"--duration: expected > 0 s, got {duration_s:g}")
    if levels_V:
        return multilevel_chirp(fs, duration_s, f0_hz, f1_hz, levels_V)
    if not 0 < period_s <= duration_s:
        raise RigError(f"--period: expected 0 < S <= --duration ({duration_s:g} s), got {period_s:g}")
    if f1_hz - max(f0_hz, 1.0 / period_s) < 3.0 / period_s:
        raise RigError(f"--period: {period_s:g} s gives lines {1 / period_s:g} Hz apart, too few between "
                       f"{f0_hz:g} and {f1_hz:g} Hz")
    return odd_multisine(fs, duration_s, f0_hz, f1_hz, amplitude_V, period_s, seed=seed)


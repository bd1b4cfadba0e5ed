"""What real sensors add to a simulated recording: the habits of a test rig's transducers (not physics).

`SensorHabits.apply(position_m, accel_mps2, fs)` turns the plant's true piston position and acceleration (from
simulate_stand with its noise off) into what the converters record:

- noise: white, low-pass coloured (one pole at noise_corner_hz), or white plus a 1/f part below
  noise_corner_hz; optionally through a second-order anti-alias filter at adc_filter_hz before sampling (on the
  noise: a filter in the signal path would add its group delay to the position, which a recording of command and
  position alone cannot tell from a transport delay);
- the transducer's zero: offset plus drift, linear, exponential (thermal settling toward a new zero) or a slow
  smooth random wander (white noise through two lags);
- line pickup at the mains frequency and its harmonics on either channel (not a force: the other sensor does
  not see it);
- quantisation of each converter (step in m or m/s^2), then clipping at the converter's range;
- an accelerometer offset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Line:
    frequency_hz: float
    amplitude: float            # m on position, m/s^2 on acceleration
    phase_rad: float = 0.0


@dataclass(frozen=True)
class SensorHabits:
    position_noise_m: float = 2e-8          # rms of the whole noise (after colouring and filtering)
    accel_noise_mps2: float = 2e-4
    noise_colour: str = "white"             # white | lowpass | pink
    noise_corner_hz: float = 0.0
    adc_filter_hz: float = 0.0              # 0 = none
    offset_m: float = 0.0
    drift_m_per_s: float = 0.0
    drift_shape: str = "linear"             # linear | exponential | wander
    drift_tau_s: float = 60.0               # exponential: time constant; wander: the lags' time constant
    wander_m: float = 0.0                   # rms of the random wander (drift_shape "wander")
    position_lines: tuple[Line, ...] = ()
    accel_lines: tuple[Line, ...] = ()
    quant_step_m: float = 0.0
    accel_quant_step_mps2: float = 0.0
    clip_m: float = 0.0                     # converter range +-clip_m (0 = none)
    accel_offset_mps2: float = 0.0
    seed: int = 0

    def _noise(self, rng: np.random.Generator, n: int, fs: float, rms: float) -> np.ndarray:
        if rms <= 0:
            return np.zeros(n)
        w = rng.standard_normal(n)
        if self.noise_colour != "white" and self.noise_corner_hz > 0:
            W = np.fft.rfft(w)
            f = np.fft.rfftfreq(n, 1.0 / fs)
            if self.noise_colour == "lowpass":
                W /= np.sqrt(1.0 + (f / self.noise_corner_hz) ** 2)
            elif self.noise_colour == "pink":
                W *= np.sqrt(1.0 + self.noise_corner_hz / np.maximum(f, 0.05))
            w = np.fft.irfft(W, n)
        if self.adc_filter_hz > 0:
            from scipy.signal import butter, sosfilt
            sos = butter(2, min(self.adc_filter_hz, 0.45 * fs), fs=fs, output="sos")
            w = sosfilt(sos, w)
        return w * (rms / max(float(np.std(w)), 1e-300))

    def zero_m(self, n: int, fs: float, rng: np.random.Generator | None = None) -> np.ndarray:
        """The transducer's zero over the recording: offset plus drift of the chosen shape."""
        t = np.arange(n) / fs
        z = self.offset_m + np.zeros(n)
        if self.drift_shape == "exponential":
            z += self.drift_m_per_s * self.drift_tau_s * -np.expm1(-t / self.drift_tau_s)
        else:
            z += self.drift_m_per_s * t
        if self.drift_shape == "wander" and self.wander_m > 0:
            # thermal wander: white noise through two first-order lags of time constant tau (smooth, not a
            # random walk: the zero of a transducer follows its temperature)
            rng = rng or np.random.default_rng(self.seed + 1)
            a = math.exp(-1.0 / (fs * self.drift_tau_s))
            from scipy.signal import lfilter
            w = lfilter([1.0], [1.0, -a], lfilter([1.0], [1.0, -a], rng.standard_normal(n)))
            w -= w[0]
            z += self.wander_m * w / max(float(np.std(w)), 1e-300)
        return z

    def apply(self, position_m: np.ndarray, accel_mps2: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng(self.seed)
        n = len(position_m)
        t = np.arange(n) / fs
        x = np.asarray(position_m, float) + self.zero_m(n, fs, rng)
        a = np.asarray(accel_mps2, float) + self.accel_offset_mps2
        for ln in self.position_lines:
            x = x + ln.amplitude * np.sin(2 * np.pi * ln.frequency_hz * t + ln.phase_rad)
        for ln in self.accel_lines:
            a = a + ln.amplitude * np.sin(2 * np.pi * ln.frequency_hz * t + ln.phase_rad)
        x = x + self._noise(rng, n, fs, self.position_noise_m)
        a = a + self._noise(rng, n, fs, self.accel_noise_mps2)
        if self.quant_step_m > 0:
            x = self.quant_step_m * np.round(x / self.quant_step_m)
        if self.accel_quant_step_mps2 > 0:
            a = self.accel_quant_step_mps2 * np.round(a / self.accel_quant_step_mps2)
        if self.clip_m > 0:
            x = np.clip(x, -self.clip_m, self.clip_m)
        return x, a

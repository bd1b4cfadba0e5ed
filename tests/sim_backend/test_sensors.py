"""The sensor-habit simulator (sim_backend/sensors.py): offset, drift, converter step, pickup lines on either
sensor, accelerometer offset and coloured noise land in the signals as drawn."""
from __future__ import annotations

import numpy as np
import pytest

from sim_backend.sensors import Line, SensorHabits


def test_sensor_habits_simulator():
    n, fs = 20000, 1000.0
    t = np.arange(n) / fs
    h = SensorHabits(position_noise_m=1e-8, offset_m=2e-6, drift_m_per_s=50e-9, quant_step_m=3e-8,
                     position_lines=(Line(50.0, 5e-8, 0.0),), accel_lines=(Line(60.0, 1e-3, 0.0),),
                     accel_offset_mps2=0.05, seed=2)
    x, a = h.apply(np.zeros(n), np.zeros(n), fs)
    k = x / 3e-8
    assert np.allclose(k, np.round(k))                                      # on the converter's grid
    trend = np.polyfit(t, x, 1)
    assert trend[0] == pytest.approx(50e-9, rel=0.05) and trend[1] == pytest.approx(2e-6, rel=0.02)
    X = np.abs(np.fft.rfft(x - np.polyval(trend, t))) * 2 / n
    assert X[int(50 * n / fs)] == pytest.approx(5e-8, rel=0.15)
    A = np.abs(np.fft.rfft(a - a.mean())) * 2 / n
    assert A[int(60 * n / fs)] == pytest.approx(1e-3, rel=0.1) and a.mean() == pytest.approx(0.05, abs=1e-4)
    lp = SensorHabits(position_noise_m=1e-8, noise_colour="lowpass", noise_corner_hz=20.0, seed=1)
    w, _ = lp.apply(np.zeros(n), np.zeros(n), fs)
    W = np.abs(np.fft.rfft(w)) ** 2
    f = np.fft.rfftfreq(n, 1 / fs)
    assert np.std(w) == pytest.approx(1e-8, rel=1e-6)
    assert W[f < 10].mean() > 20 * W[f > 200].mean()                       # coloured

"""A small stand-in plant for protocol-level tests of the emulated devices (no machine model).

Per mount: stroke follows the valve command through the actuator's low-frequency lag (DC gain 2.68 um/V,
corner K_C K_L / A_p^2 = 46.7 rad/s, PHYSICS_NOTES); the mount rides on a sinusoidal floor, and the
accelerometer reads the second difference of floor + stroke. Deterministic, so tests can check values.
"""
from __future__ import annotations

import math


class StandInPlant:
    n_mounts = 4

    def __init__(self, dt: float, *, floor_amp_m: float = 10e-6, floor_hz: float = 5.0,
                 gain_m_per_V: float = 2.68e-6, corner_rad_s: float = 46.7):
        self.dt = dt
        self.amp = floor_amp_m
        self.w = 2 * math.pi * floor_hz
        self.gain = gain_m_per_V
        self.alpha = 1.0 - math.exp(-corner_rad_s * dt)
        self.k = 0
        self.t_s = 0.0
        self.stroke_m = [0.0] * 4
        self.accel_mps2 = [0.0] * 4
        self.floor_m = [0.0] * 4
        self.table_m = 0.0
        self._x = [[0.0, 0.0] for _ in range(4)]      # position history for the second difference

    def step(self, valve_cmd_V) -> None:
        self.k += 1
        self.t_s = self.k * self.dt
        fl = self.amp * math.sin(self.w * self.t_s)
        for i in range(4):
            self.stroke_m[i] += (self.gain * float(valve_cmd_V[i]) - self.stroke_m[i]) * self.alpha
            x = fl + self.stroke_m[i]
            x1, x2 = self._x[i]
            self.accel_mps2[i] = (x - 2 * x1 + x2) / (self.dt * self.dt) if self.k > 2 else 0.0
            self._x[i] = [x, x1]
            self.floor_m[i] = fl
        self.table_m = fl + sum(self.stroke_m) / 4

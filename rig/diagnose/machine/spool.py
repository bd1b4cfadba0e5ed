"""A valve's spool deadband in the replay: the command the linear model must see for the spool's flow.

The deadband acts on the spool (Eq. 1's x_v, in mA-equivalent): no flow while |x_v| < width, flow from
|x_v| - width (sim_backend/rig_error.py deadband, the simulator's own term). The valve is linear up to its
spool, so the spool of the recorded command is computed in the time domain (the valve's exact zero-order-hold
recursion), passed through the overlap, and taken back to an effective command in the frequency domain
(dividing by the same recursion's response): the rest of the replay stays linear. At width 0 the effective
command is the recorded one. Between samples the spool past the overlap is known only at them: the model feeds
the chamber from them interpolated linearly (rigmodel.predict), as the simulated rig steps it, not through the
valve's response to the held effective command (whose error at that mount a viscous term took up).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.signal

from rig.diagnose.machine.rigmodel import ACT_KEYS, Base
from sim_backend.rig_error import deadband


def valve_filter(base: Base, th: dict):
    """(b, a) of the valve's exact ZOH recursion at the record's period, per volt -> mA-equivalent spool."""
    a0, v0 = base.cfg.valve, dict(zip(ACT_KEYS, th["act"]))
    w, z = a0.w_nv * v0["w_nv"], a0.zeta * v0["zeta"]
    num, den = [a0.K_v * w * w], [1.0, 2 * z * w, w * w]
    b, a, _ = scipy.signal.cont2discrete((num, den), base.dt, method="zoh")
    return np.ravel(b), np.ravel(a)


class Spools:
    """The recorded commands (time domain) and their DFT bins; effective commands of deadband valves."""

    def __init__(self, u: np.ndarray, bins: np.ndarray, base: Base, U: np.ndarray):
        self.u = np.asarray(u, dtype=float)
        self.bins = bins
        self.base = base
        self.U = U
        self.n = len(u)

    def effective(self, th: dict) -> np.ndarray | None:
        """The commands the linear model sees (K, 4) at theta's deadbands (None: none set)."""
        widths = th["deadband_ma"]
        if not np.any(widths > 0):
            return None
        b, a = valve_filter(self.base, th)
        z = np.exp(2j * math.pi * np.fft.rfftfreq(self.n, self.base.dt)[self.bins] * self.base.dt)
        V = np.polyval(b[::-1], 1 / z) / np.polyval(a[::-1], 1 / z)
        out = self.U.copy()
        for i in np.flatnonzero(widths > 0):
            xv = scipy.signal.lfilter(b, a, self.u[:, i])
            out[:, i] = np.fft.rfft(deadband(xv, float(widths[i])))[self.bins] / V
        return out

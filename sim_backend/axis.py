"""A single electro-mechanical axis as recorded (the physics other rigs' recordings come from), for the proof of
the diagnosis on plant files (rig prove --plant, the EMPS-like worked example in docs/PLANT.md).

    M x'' = g u_d(t - tau) - c x' - k x - F_c sgn(x') + F_0      (carriage; u_d: the command after the drive's
                                                                   saturation and deadband)
Coulomb friction here is the real thing, not the diagnosis's smooth tanh: the carriage sticks while the applied
force stays within +-F_c (Karnopp's stick band), which the diagnosis must still recognise. Integrated with small
fixed sub-steps (semi-implicit Euler, 20 per sample by default); the command is held over each sample and delayed
by tau (the switch inside a sample at the right sub-step).

Closed loop: a position controller at the sample rate on the measured (quantised, noisy) position, as a drive's
P-PI cascade: v_ref = k_p (r - x_m), u = k_v (v_ref - v_m) + k_i int(v_ref - v_m) dt, clipped to +-u_max; the
recorded command is what the controller wrote.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np


@dataclass(frozen=True)
class Axis:
    mass_kg: float
    damping_n_s_per_m: float
    stiffness_n_per_m: float = 0.0
    gain_n_per_unit: float = 1.0
    coulomb_n: float = 0.0
    constant_force_n: float = 0.0
    delay_s: float = 0.0
    saturation: float = 0.0            # command limit (its unit); 0: none
    deadband: float = 0.0              # command half-width without drive output; 0: none
    base: tuple[float, float, float] | None = None    # (frequency_hz, damping_ratio, mass_kg) of a compliant base
    disturbance: tuple[float, float, float] | None = None   # (frequency_hz, force_n, phase_rad) on the carriage


@dataclass(frozen=True)
class Loop:
    """The drive's cascade: k_p [1/s] position, k_v [command per m/s] velocity, k_i [command per m] integral."""
    kp_per_s: float
    kv: float
    ki: float = 0.0
    u_max: float = 10.0


@dataclass(frozen=True)
class Sensor:
    step_m: float = 0.0                # encoder quantisation
    noise_m: float = 0.0               # white noise rms
    offset_m: float = 0.0
    seed: int = 0


@numba.njit(cache=True)
def _integrate(N, fs, n_sub, drive_in, closed, kp, kv, ki, u_max, ref, prm, base, dist, sens_noise, step, offset,
               x_out, u_out):
    M, c, k, g, Fc, F0, tau, sat, dead = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6], prm[7], prm[8]
    has_base = base[2] > 0.0
    wb = 2.0 * math.pi * base[0]
    mb = base[2] if has_base else 1.0
    kb = mb * wb * wb; cb = 2.0 * base[1] * wb * mb
    T = 1.0 / fs; h = T / n_sub
    m = int(math.floor(tau / T + 1e-9)); fr = tau - m * T
    x = 0.0; v = 0.0; xb = 0.0; vb = 0.0
    integ = 0.0; xm_prev = 0.0
    u_hist = np.zeros(N)
    vstick = 1e-7
    for kk in range(N):
        xm = x - xb + offset + sens_noise[kk]
        if step > 0.0:
            xm = step * math.floor(xm / step + 0.5)
        x_out[kk] = xm
        if closed:
            vm = (xm - xm_prev) * fs if kk > 0 else 0.0
            e = kp * (ref[kk] - xm) - vm
            integ += e * T
            u = kv * e + ki * integ
            if u > u_max:
                u = u_max
            elif u < -u_max:
                u = -u_max
        else:
            u = drive_in[kk]
        xm_prev = xm
        u_hist[kk] = u
        u_out[kk] = u
        for j in range(n_sub):
            t_in = j * h
            idx = kk - m if t_in >= fr - 1e-15 else kk - m - 1
            ud = u_hist[idx] if idx >= 0 else 0.0
            if sat > 0.0:
                ud = min(max(ud, -sat), sat)
            if dead > 0.0:
                ud = ud - dead if ud > dead else (ud + dead if ud < -dead else 0.0)
            t = kk * T + t_in
            Fd = dist[1] * math.sin(2.0 * math.pi * dist[0] * t + dist[2]) if dist[0] > 0.0 else 0.0
            vr = v - vb
            Fa = g * ud + F0 + Fd - c * vr - k * (x - xb)
            if abs(vr) < vstick and abs(Fa) <= Fc:
                Ff = -Fa                       # stuck: friction holds the applied force
            else:
                s = vr if abs(vr) >= vstick else Fa
                Ff = -Fc if s > 0 else Fc
            a = (Fa + Ff) / M
            if has_base:
                ab = (-(Fa + Ff) - kb * xb - cb * vb) / mb
                vb += h * ab
                xb += h * vb
            vn = v + h * a
            if Fc > 0.0 and (v - vb + 0.0) * (vn - vb) < 0.0 and abs(Fa) <= Fc:
                vn = vb                        # a reversal inside the stick band stops the carriage
            v = vn
            x += h * v


def simulate_axis(ax: Axis, fs: float, *, command=None, reference=None, loop: Loop | None = None,
                  sensor: Sensor = Sensor(), n_sub: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """(recorded command, measured position [m]) at fs: open loop from `command`, or closed loop following
    `reference` [m] under `loop`."""
    closed = loop is not None
    src = np.ascontiguousarray(reference if closed else command, dtype=float)
    N = len(src)
    prm = np.array([ax.mass_kg, ax.damping_n_s_per_m, ax.stiffness_n_per_m, ax.gain_n_per_unit, ax.coulomb_n,
                    ax.constant_force_n, ax.delay_s, ax.saturation, ax.deadband])
    base = np.array(ax.base if ax.base else (0.0, 0.0, 0.0), float)
    dist = np.array(ax.disturbance if ax.disturbance else (0.0, 0.0, 0.0), float)
    noise = np.random.default_rng(sensor.seed).normal(0.0, sensor.noise_m, N) if sensor.noise_m > 0 else np.zeros(N)
    lp = loop or Loop(0.0, 0.0)
    x_out = np.empty(N); u_out = np.empty(N)
    _integrate(N, float(fs), int(n_sub), src if not closed else np.zeros(N), closed, lp.kp_per_s, lp.kv, lp.ki,
               lp.u_max, src if closed else np.zeros(N), prm, base, dist, noise, sensor.step_m, sensor.offset_m,
               x_out, u_out)
    return u_out, x_out


def trapezoid_program(fs: float, moves: list[tuple[float, float]], accel_mps2: float, dwell_s: float,
                      start_m: float = 0.0) -> np.ndarray:
    """A reference of back-and-forth moves: each (distance m, top speed m/s) with a trapezoidal velocity at
    +-accel_mps2 (triangular when too short), a dwell after each."""
    v_parts = [np.zeros(int(round(dwell_s * fs)))]
    for dist, vmax in moves:
        d = abs(dist); sgn = math.copysign(1.0, dist)
        vp = min(vmax, math.sqrt(d * accel_mps2))
        t_acc = vp / accel_mps2
        t_flat = max(0.0, d / vp - t_acc)
        ta = np.arange(int(round(t_acc * fs))) / fs
        up = accel_mps2 * ta
        flat = np.full(int(round(t_flat * fs)), vp)
        v_parts += [sgn * up, sgn * flat, sgn * up[::-1], np.zeros(int(round(dwell_s * fs)))]
    v = np.concatenate(v_parts)
    return start_m + np.cumsum(v) / fs

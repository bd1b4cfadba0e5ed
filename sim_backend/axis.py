"""A single electro-mechanical axis as recorded (the physics other rigs' recordings come from), for the proof of
the diagnosis on plant files (rig prove --plant, the EMPS-like worked example in docs/PLANT.md).

    M x'' = g u_d(t - tau) - c x' - k x - F_f(x') + F_0        (carriage; u_d: the command after the drive's
                                                                   saturation and deadband)
    F_f(v) = (F_c + F_s exp(-(v / v_S)^2)) sgn(v)                 (Coulomb, with Stribeck's breakaway F_s above
                                                                   it fading over the Stribeck velocity v_S)
Friction here is the real thing, not the diagnosis's smooth tanh: the carriage sticks while the applied force
stays within +-(F_c + F_s) (Karnopp's stick band), which the diagnosis must still recognise. With backlash the
encoder reads the load, driven by the carriage through a gear's play of width b (the load's inertia small: it
stays where it is until the carriage crosses the play). Integrated with small
fixed sub-steps (100 per sample by default: the linear part exact over each, the friction force held); the command is held over each sample and delayed
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
import scipy.linalg

from sim_backend.actuator import dead_zone


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
    stribeck_n: float = 0.0            # breakaway force above coulomb_n, fading over stribeck_m_per_s
    stribeck_m_per_s: float = 1e-2
    backlash_m: float = 0.0            # play between the carriage and the load the encoder reads (total width)


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


@numba.njit(cache=True, nogil=True)     # nogil: a signal reaches the main thread meanwhile
def _integrate(N, fs, n_sub, drive_in, closed, kp, kv, ki, u_max, ref, prm, Ad, Gd, Cx, Cv, dist, sens_noise, step,
               offset, x_out, u_out):
    g, Fc, F0, tau, sat, dead = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5]
    c, k = prm[6], prm[7]
    Fs, vS, half = prm[8], prm[9], 0.5 * prm[10]
    Ftop = Fc + Fs                   # the breakaway force (the stick band)
    load = 0.0; engaged = False
    T = 1.0 / fs; h = T / n_sub
    m = int(math.floor(tau / T + 1e-9)); fr = tau - m * T
    n = Ad.shape[0]
    s = np.zeros(n); sn = np.zeros(n)
    integ = 0.0; xm_prev = 0.0
    u_hist = np.zeros(N)
    vstick = 1e-6
    for kk in range(N):
        xr = 0.0
        for i in range(n):
            xr += Cx[i] * s[i]
        if half > 0.0:                       # the load behind the play (centred at the start)
            if not engaged:
                load = xr; engaged = True
            if xr - load > half:
                load = xr - half
            elif xr - load < -half:
                load = xr + half
            xr = load
        xm = xr + offset + sens_noise[kk]
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
            idx = kk - m if j * h >= fr - 1e-15 else kk - m - 1
            ud = u_hist[idx] if idx >= 0 else 0.0
            if sat > 0.0:
                ud = min(max(ud, -sat), sat)
            ud = dead_zone(ud, dead)
            t = kk * T + j * h
            Fd = dist[1] * math.sin(2.0 * math.pi * dist[0] * t + dist[2]) if dist[0] > 0.0 else 0.0
            vr = 0.0; xr = 0.0
            for i in range(n):
                vr += Cv[i] * s[i]
                xr += Cx[i] * s[i]
            Fext = g * ud + F0 + Fd
            Ff = 0.0
            if Ftop > 0.0:
                Fa = Fext - c * vr - k * xr          # what acts on the carriage besides friction
                if abs(vr) < vstick and abs(Fa) <= Ftop:
                    Ff = -Fa                         # stuck (Karnopp): friction holds the rest
                    for i in range(n):               # and the relative velocity is zero
                        s[i] -= Cv[i] * vr * (1.0 if Cv[i] != 0.0 else 0.0) * (1.0 if i == 1 else 0.0)
                else:
                    sg = vr if abs(vr) >= vstick else Fa
                    lev = Fc + (Fs * math.exp(-(vr / vS) ** 2) if Fs > 0.0 else 0.0)
                    Ff = -lev if sg > 0 else lev
            for i in range(n):
                acc = Gd[i] * (Fext + Ff)
                for q in range(n):
                    acc += Ad[i, q] * s[q]
                sn[i] = acc
            if Ftop > 0.0:
                vn = 0.0
                for i in range(n):
                    vn += Cv[i] * sn[i]
                if vr * vn < 0.0 and abs(Fext - c * 0.0 - k * xr) <= Ftop:
                    for i in range(n):               # a reversal inside the stick band: the carriage stops
                        if i == 1:
                            sn[i] -= vn
            for i in range(n):
                s[i] = sn[i]


def _exact_substep(ax: Axis, h: float):
    """The linear part (mass, damping, stiffness, base) discretised exactly over a sub-step, with the force between
    carriage and frame held: (Ad, Gd, Cx = encoder row, Cv = relative velocity row)."""
    M, c, k = ax.mass_kg, ax.damping_n_s_per_m, ax.stiffness_n_per_m
    if ax.base is None:
        A = np.array([[0.0, 1.0], [-k / M, -c / M]]); G = np.array([0.0, 1.0 / M])
        Cx = np.array([1.0, 0.0]); Cv = np.array([0.0, 1.0])
    else:
        fb, zb, mb = ax.base
        wb = 2 * math.pi * fb
        kb, cb = mb * wb * wb, 2 * zb * wb * mb
        A = np.array([[0.0, 1.0, 0.0, 0.0], [-k / M, -c / M, k / M, c / M], [0.0, 0.0, 0.0, 1.0],
                      [k / mb, c / mb, -(k + kb) / mb, -(c + cb) / mb]])
        G = np.array([0.0, 1.0 / M, 0.0, -1.0 / mb])
        Cx = np.array([1.0, 0.0, -1.0, 0.0]); Cv = np.array([0.0, 1.0, 0.0, -1.0])
    n = len(G)
    E = np.zeros((n + 1, n + 1)); E[:n, :n] = A * h; E[:n, n] = G * h
    X = scipy.linalg.expm(E)
    return X[:n, :n], X[:n, n], Cx, Cv


def simulate_axis(ax: Axis, fs: float, *, command=None, reference=None, loop: Loop | None = None,
                  sensor: Sensor = Sensor(), n_sub: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """(recorded command, measured position [m]) at fs: open loop from `command`, or closed loop following
    `reference` [m] under `loop`."""
    closed = loop is not None
    src = np.ascontiguousarray(reference if closed else command, dtype=float)
    N = len(src)
    prm = np.array([ax.gain_n_per_unit, ax.coulomb_n, ax.constant_force_n, ax.delay_s, ax.saturation, ax.deadband,
                    ax.damping_n_s_per_m, ax.stiffness_n_per_m, ax.stribeck_n, ax.stribeck_m_per_s, ax.backlash_m])
    Ad, Gd, Cx, Cv = _exact_substep(ax, 1.0 / (fs * n_sub))
    dist = np.array(ax.disturbance if ax.disturbance else (0.0, 0.0, 0.0), float)
    noise = np.random.default_rng(sensor.seed).normal(0.0, sensor.noise_m, N) if sensor.noise_m > 0 else np.zeros(N)
    lp = loop or Loop(0.0, 0.0)
    x_out = np.empty(N); u_out = np.empty(N)
    _integrate(N, float(fs), int(n_sub), src if not closed else np.zeros(N), closed, lp.kp_per_s, lp.kv, lp.ki,
               lp.u_max, src if closed else np.zeros(N), prm, Ad, Gd, Cx, Cv, dist, noise, sensor.step_m,
               sensor.offset_m, x_out, u_out)
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


# The EMPS benchmark's published figures (Janot, Gautier, Brunot: the electro-mechanical positioning system data
# set and its reference model): M q'' = g_tau v_ir - F_v q' - F_c sign(q') - OF, recorded at 1 kHz in closed loop.
EMPS = Axis(mass_kg=95.1089, damping_n_s_per_m=203.5034, gain_n_per_unit=35.15, coulomb_n=20.3935,
            constant_force_n=-3.1648)
EMPS_LOOP = Loop(kp_per_s=160.18, kv=243.45, ki=0.0, u_max=10.0)   # P position, P velocity (V s/m), +-10 V drive
EMPS_ENCODER = Sensor(step_m=5e-8)                                    # ASSUMED: a 0.05 um encoder step, no noise
EMPS_MOVES = [(0.15, 0.13), (-0.15, 0.13), (0.1, 0.06), (-0.1, 0.06), (0.05, 0.03), (-0.05, 0.03)] * 2  # ASSUMED
EMPS_ACCEL_MPS2 = 0.83                                                # ASSUMED: the published profile's ~0.83 m/s^2


def emps_like(fs: float = 1000.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(drive voltage v_ir [V], encoder position [m]) of an EMPS-like run: ~23 s of back-and-forth trapezoidal
    moves up to 0.13 m/s over 0.15 m, under the published cascade. What the published figures do not give (the
    moves, the encoder step) is marked ASSUMED above."""
    ref = trapezoid_program(fs, EMPS_MOVES, EMPS_ACCEL_MPS2, 0.3)
    sensor = Sensor(EMPS_ENCODER.step_m, EMPS_ENCODER.noise_m, EMPS_ENCODER.offset_m, seed)
    return simulate_axis(EMPS, fs, reference=ref, loop=EMPS_LOOP, sensor=sensor)

"""Fast candidate models of the actuator on its stand (Law et al. 2015, Eqs. 1-8) for diagnosis fits.

Two simulators, both checked against sim_backend.actuator.simulate_stand (the recordings' physics):
  sim_linear  exact zero-order-hold discretisation of the linear state-space model, with the transport delay
              (fractional, exact), the base mode (extra second-order pair) and the driver-current clip
              (a Hammerstein nonlinearity before the spool, still exact), run in modal coordinates.
  sim_reduced valve exact per sub-step, then the piston with its mass neglected (the hydraulic mode at
              w_h ~ 2 kHz is far above the chirp), integrated with BDF2: handles the spool deadband and the
              Coulomb friction (stiff tanh, solved implicitly per step). The base mode is applied as its exact
              linear post-filter in the frequency domain (the mode does not feed back onto the stroke here).
Measured position is the absolute piston position x_p (the stand moves under the housing).
"""
from __future__ import annotations

import math

import numba
import numpy as np

from rig.plant.zoh import discretise, friction_velocity, run, substeps
from sim_backend.actuator import FRICTION_V_SCALE, dead_zone
from sim_backend.linear import ActuatorParams


def ss_model(p: ActuatorParams, base: tuple[float, float, float] | None = None):
    """Continuous (A, B, C): input driver current [mA], output absolute piston position [m].

    States: x_v, dx_v/dt (Eq. 1), P_L (Eqs. 3, 6), x_p, v_p (Eq. 7) [, x_b, v_b the stand]. base = (f_hz, zeta, m_b_kg).
    """
    M, A, C, Vt, KL, KQ, KC, w, z, b = p.M, p.A_p, p.C, p.V_t, p.K_L, p.K_Q, p.K_C, p.w_nv, p.zeta, p.beta
    n = 5 if base is None else 7
    Am = np.zeros((n, n)); Bm = np.zeros(n); Cm = np.zeros(n)
    Am[0, 1] = 1.0; Am[1, 0] = -w * w; Am[1, 1] = -2 * z * w; Bm[1] = w * w
    k = 4 * b / Vt
    Am[2, 0] = k * KQ; Am[2, 2] = -k * KC; Am[2, 4] = -k * A
    fa = np.zeros(n); fa[2] = A; fa[3] = -KL; fa[4] = -C       # internal force on the piston (Eq. 7)
    Am[3, 4] = 1.0
    if base is not None:
        fb, zb, mb = base
        wb = 2 * math.pi * fb
        Am[2, 6] = k * A                                         # flow follows the relative velocity
        fa[5] = KL; fa[6] = C
        Am[5, 6] = 1.0
        Am[6] = -fa / mb                                         # reaction on the stand
        Am[6, 5] -= wb * wb; Am[6, 6] -= 2 * zb * wb
    Am[4] = fa / M
    Cm[3] = 1.0
    return Am, Bm, Cm


def driver_current(p: ActuatorParams, cmd_V: np.ndarray, sat_ma: float = 0.0) -> np.ndarray:
    i = p.K_v * np.asarray(cmd_V, dtype=float)
    return np.clip(i, -sat_ma, sat_ma) if sat_ma > 0 else i


def sim_linear(p: ActuatorParams, cmd_V: np.ndarray, fs: float, *, delay_s: float = 0.0,
               base: tuple[float, float, float] | None = None, sat_ma: float = 0.0,
               output: str = "position") -> np.ndarray:
    """Exact sampled response at the sample instants (before u_k acts): position [m], or with
    output="accel" the piston's absolute acceleration [m/s^2] (Eq. 7: the force balance over M)."""
    Am, Bm, Cm = ss_model(p, base)
    if output == "accel":
        Cm = Am[4].copy()                   # dv_p/dt = (internal force) / M; the input enters via the spool only
    Ad, G0, G1, m = discretise(Am, Bm, 1.0 / fs, delay_s)
    return run(Ad, G0, G1, Cm, np.ascontiguousarray(driver_current(p, cmd_V, sat_ma)), m, np.empty(len(cmd_V)))


# ---- reduced nonlinear model --------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _run_reduced(i_cmd, m, n_sub, Av, Bnew, Bold, prm, out):
    # prm: A KL C KQ KC k dead fric vs h
    A = prm[0]; KL = prm[1]; C = prm[2]; KQ = prm[3]; KC = prm[4]; k = prm[5]
    dead = prm[6]; fric = prm[7]; vs = prm[8]; h = prm[9]
    N = i_cmd.shape[0]
    x0 = 0.0; x1 = 0.0
    y = 0.0; yp = 0.0; P = 0.0; Pp = 0.0; v = 0.0; v_old = 0.0
    first = True
    for kk in range(N):
        out[kk] = y
        a = i_cmd[kk - m] if kk - m >= 0 else 0.0
        b = i_cmd[kk - m - 1] if kk - m - 1 >= 0 else 0.0
        for j in range(n_sub):
            u0 = Bnew[j, 0] * a + Bold[j, 0] * b
            u1 = Bnew[j, 1] * a + Bold[j, 1] * b
            n0 = Av[0, 0] * x0 + Av[0, 1] * x1 + u0
            n1 = Av[1, 0] * x0 + Av[1, 1] * x1 + u1
            x0 = n0; x1 = n1
            xe = dead_zone(x0, dead)
            Q = KQ * xe
            if first:       # backward Euler start
                g = h; yb = y; Pb = P
            else:           # BDF2
                g = 2.0 * h / 3.0; yb = (4.0 * y - yp) / 3.0; Pb = (4.0 * P - Pp) / 3.0
            den = 1.0 + g * k * KC
            c0 = A * (Pb + g * k * Q) / den - KL * yb
            c1 = A * A * g * k / den + KL * g + C
            if fric > 0.0:
                # start from the velocity extrapolated over the last two steps
                vv = friction_velocity(c0, c1, fric, vs, 2.0 * v - v_old, 1e-10, 1e-6)
                v_old = v
                v = vv
            else:
                v = c0 / c1
            Pn = (Pb + g * k * (Q - A * v)) / den
            yn = yb + g * v
            yp = y; Pp = P; y = yn; P = Pn
            first = False


def _valve_substeps(p: ActuatorParams, fs: float, n_sub: int, delay_s: float):
    """Exact valve (Eq. 1) sub-step matrices with the held, delayed current switching inside a sample."""
    w, z = p.w_nv, p.zeta
    Av_c = np.array([[0.0, 1.0], [-w * w, -2 * z * w]]); Bv_c = np.array([0.0, w * w])
    return substeps(Av_c, Bv_c, 1.0 / fs, n_sub, delay_s)


def base_filter(y: np.ndarray, fs: float, p: ActuatorParams, base: tuple[float, float, float]) -> np.ndarray:
    """x_p = y (m_b s^2 + c_b s + k_b) / ((m_b + M) s^2 + c_b s + k_b): the stand's mode seen in x_p."""
    fb, zb, mb = base
    wb = 2 * math.pi * fb
    n = len(y); nf = 1 << int(math.ceil(math.log2(n + int(2 * fs) + 1)))
    Y = np.fft.rfft(y, nf)
    s = 2j * math.pi * np.fft.rfftfreq(nf, 1.0 / fs)
    num = s * s + 2 * zb * wb * s + wb * wb
    den = (1 + p.M / mb) * s * s + 2 * zb * wb * s + wb * wb
    return np.fft.irfft(Y * num / den, nf)[:n]


def sim_reduced(p: ActuatorParams, cmd_V: np.ndarray, fs: float, *, delay_s: float = 0.0, sat_ma: float = 0.0,
                dead_ma: float = 0.0, fric_n: float = 0.0, base: tuple[float, float, float] | None = None,
                sub_hz: float = 3000.0) -> np.ndarray:
    """Nonlinear reduced model (deadband, friction; also delay, saturation, base), metres at the samples."""
    n_sub = max(1, int(math.ceil(sub_hz / fs)))
    Av, Bnew, Bold, m = _valve_substeps(p, fs, n_sub, delay_s)
    prm = np.array([p.A_p, p.K_L, p.C, p.K_Q, p.K_C, 4 * p.beta / p.V_t, dead_ma, fric_n, FRICTION_V_SCALE,
                    1.0 / (fs * n_sub)])
    out = np.empty(len(cmd_V))
    _run_reduced(driver_current(p, cmd_V, sat_ma), m, n_sub, Av, Bnew, Bold, prm, out)
    if base is not None:
        out = base_filter(out, fs, p, base)
    return out


def force_response(p: ActuatorParams, fs: float, f_hz: float, n: int,
                   base: tuple[float, float, float] | None = None) -> np.ndarray:
    """(n, 2) responses of x_p to a piston force sin(w t) and cos(w t) N from t = 0 (Eq. 8 with F_L, and the
    stand mode when given): the disturbance regressors, start transient included. The force is held at its
    mid-sample value, which leaves only a gain/phase change that the fitted amplitude and phase absorb."""
    Am, _, Cm = ss_model(p, base)
    BF = np.zeros(Am.shape[0]); BF[4] = 1.0 / p.M
    Ad, G0, G1, m = discretise(Am, BF, 1.0 / fs, 0.0)
    w = 2 * math.pi * f_hz * (np.arange(n) + 0.5) / fs
    out = np.empty((2, n))
    run(Ad, G0, G1, Cm, np.sin(w), m, out[0])
    run(Ad, G0, G1, Cm, np.cos(w), m, out[1])
    return out.T

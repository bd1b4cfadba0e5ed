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
from scipy.linalg import matrix_balance

from sim_backend.actuator import FRICTION_V_SCALE
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


@numba.njit(cache=True)
def _expm_taylor(E):
    """exp(E) by scaling and squaring with an 18-term Taylor series (E balanced, small order)."""
    n = E.shape[0]
    nrm = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += abs(E[i, j])
        nrm = max(nrm, s)
    q = 0
    while nrm > 0.25:
        nrm *= 0.5; q += 1
    X = E / (2.0 ** q)
    R = np.eye(n); T = np.eye(n)
    for k in range(1, 19):
        T = T @ X / k
        R = R + T
    for _ in range(q):
        R = R @ R
    return R


def _phi(Am, Bm, tau):
    """Exact ZOH pair (e^{A tau}, int_0^tau e^{A s} ds B) from the augmented matrix exponential (balanced)."""
    n = len(Bm)
    E = np.zeros((n + 1, n + 1)); E[:n, :n] = Am * tau; E[:n, n] = Bm * tau
    Eb, (sc, _) = matrix_balance(E, permute=False, separate=True)
    X = _expm_taylor(Eb)
    X = X * sc[:, np.newaxis] / sc[np.newaxis, :]          # undo the similarity Eb = D^-1 E D
    return X[:n, :n], X[:n, n]


def discretise(Am, Bm, T: float, delay_s: float):
    """x_{k+1} = Ad x_k + G0 u_{k-m} + G1 u_{k-m-1}: ZOH input delayed by delay_s = m T + fr (exact)."""
    m = int(math.floor(delay_s / T + 1e-9)); fr = max(0.0, delay_s - m * T)
    Ad, G = _phi(Am, Bm, T)
    if fr < 1e-12 * T:
        return Ad, G, np.zeros_like(G), m
    A1, G0 = _phi(Am, Bm, T - fr)
    _, Gf = _phi(Am, Bm, fr)
    return Ad, G0, A1 @ Gf, m


@numba.njit(cache=True, nogil=True)
def _run_ss(Ad, G0, G1, Cm, u, m, out):
    n = Ad.shape[0]; N = u.shape[0]
    x = np.zeros(n); xn = np.zeros(n)
    for k in range(N):
        s = 0.0
        for i in range(n):
            s += Cm[i] * x[i]
        out[k] = s
        a = u[k - m] if k - m >= 0 else 0.0
        b = u[k - m - 1] if k - m - 1 >= 0 else 0.0
        for i in range(n):
            acc = G0[i] * a + G1[i] * b
            for j in range(n):
                acc += Ad[i, j] * x[j]
            xn[i] = acc
        for i in range(n):
            x[i] = xn[i]


@numba.njit(cache=True, nogil=True)
def _run_modal(lam, g0, g1, c, u, m, out):
    """_run_ss in modal coordinates: one complex state per real pole or conjugate pair (3 instead of 25 products
    per sample for the 5-state model); the output is the real part."""
    n = lam.shape[0]; N = u.shape[0]
    xr = np.zeros(n); xi = np.zeros(n)
    for k in range(N):
        s = 0.0
        for i in range(n):
            s += c[i].real * xr[i] - c[i].imag * xi[i]
        out[k] = s
        a = u[k - m] if k - m >= 0 else 0.0
        b = u[k - m - 1] if k - m - 1 >= 0 else 0.0
        for i in range(n):
            lr = lam[i].real; li = lam[i].imag
            nr = lr * xr[i] - li * xi[i] + g0[i].real * a + g1[i].real * b
            ni = lr * xi[i] + li * xr[i] + g0[i].imag * a + g1[i].imag * b
            xr[i] = nr; xi[i] = ni


def run(Ad, G0, G1, Cm, u, m, out) -> np.ndarray:
    """Simulate x_{k+1} = Ad x_k + G0 u_{k-m} + G1 u_{k-m-1}, y_k = Cm x_k from rest: in modal coordinates
    (Ad = V diag(lam) V^-1, one of each conjugate pair kept, its output doubled) when V is well conditioned,
    else directly."""
    lam, V = np.linalg.eig(Ad)
    if np.linalg.cond(V) > 1e8:
        _run_ss(Ad, G0, G1, Cm, u, m, out)
        return out
    Vi = np.linalg.inv(V)
    g0, g1, cc = Vi @ G0, Vi @ G1, Cm @ V
    keep, weight, used = [], [], np.zeros(len(lam), bool)
    for i in range(len(lam)):
        if used[i]:
            continue
        used[i] = True
        if abs(lam[i].imag) > 1e-12 * max(abs(lam[i]), 1e-300):
            rest = np.where(used, np.inf, np.abs(lam - np.conj(lam[i])))
            used[int(np.argmin(rest))] = True
            weight.append(2.0)
        else:
            weight.append(1.0)
        keep.append(i)
    k = np.array(keep)
    _run_modal(lam[k].astype(complex), g0[k].astype(complex), g1[k].astype(complex),
               (cc[k] * np.array(weight)).astype(complex), u, m, out)
    return out


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
            if dead > 0.0:
                if x0 > dead:
                    xe = x0 - dead
                elif x0 < -dead:
                    xe = x0 + dead
                else:
                    xe = 0.0
            else:
                xe = x0
            Q = KQ * xe
            if first:       # backward Euler start
                g = h; yb = y; Pb = P
            else:           # BDF2
                g = 2.0 * h / 3.0; yb = (4.0 * y - yp) / 3.0; Pb = (4.0 * P - Pp) / 3.0
            den = 1.0 + g * k * KC
            c0 = A * (Pb + g * k * Q) / den - KL * yb
            c1 = A * A * g * k / den + KL * g + C
            if fric > 0.0:
                lo = (c0 - fric) / c1; hi = (c0 + fric) / c1
                # start from the velocity extrapolated over the last two steps; if that leaves the bracket,
                # from the slip or the stick solution of the smoothed sign
                vv = 2.0 * v - v_old
                if vv <= lo or vv >= hi:
                    if abs(c0) > fric:
                        vv = (c0 - fric * (1.0 if c0 > 0 else -1.0)) / c1
                    else:
                        vv = c0 / (c1 + fric / vs)
                    if vv <= lo or vv >= hi:
                        vv = 0.5 * (lo + hi)
                for it in range(60):
                    th = math.tanh(vv / vs)
                    f = c0 - c1 * vv - fric * th
                    if f > 0.0:
                        lo = vv
                    else:
                        hi = vv
                    df = -c1 - fric * (1.0 - th * th) / vs
                    vn = vv - f / df
                    if vn <= lo or vn >= hi:
                        vn = 0.5 * (lo + hi)
                    if abs(vn - vv) < 1e-10 + 1e-6 * abs(vv):
                        vv = vn
                        break
                    vv = vn
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
    T = 1.0 / fs; h = T / n_sub
    w, z = p.w_nv, p.zeta
    Av_c = np.array([[0.0, 1.0], [-w * w, -2 * z * w]]); Bv_c = np.array([0.0, w * w])
    m = int(math.floor(delay_s / T + 1e-9)); fr = max(0.0, delay_s - m * T)
    Av, Bh = _phi(Av_c, Bv_c, h)
    Bnew = np.zeros((n_sub, 2)); Bold = np.zeros((n_sub, 2))
    for j in range(n_sub):
        t0, t1 = j * h, (j + 1) * h
        if t1 <= fr + 1e-15:
            Bold[j] = Bh
        elif t0 >= fr - 1e-15:
            Bnew[j] = Bh
        else:                           # switch at fr inside this sub-step
            A2, Bn = _phi(Av_c, Bv_c, t1 - fr)
            _, Bo = _phi(Av_c, Bv_c, fr - t0)
            Bnew[j] = Bn; Bold[j] = A2 @ Bo
    return Av, Bnew, Bold, m


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

"""The one exact zero-order-hold discretisation and the simulators built on it (identification and diagnosis of
every plant family use these).

  phi(A, B, tau)        (e^{A tau}, int_0^tau e^{A s} ds B) from one augmented matrix exponential (balanced,
                        numba Taylor series with scaling and squaring: called per model evaluation)
  discretise(A, B, T, delay_s)
                        x_{k+1} = Ad x_k + G0 u_{k-m} + G1 u_{k-m-1}: the ZOH input delayed by delay_s = m T + fr,
                        exact for a fractional delay
  substeps(A, B, T, n_sub, delay_s)
                        the same over n_sub equal sub-steps of a sample, the held (delayed) input switching
                        inside the sample (for models with a nonlinearity that must be solved within a sample)
  run(...)              simulate from rest (modal coordinates when well conditioned)
  run_segments(...)     simulate with a load force channel: a constant force and Coulomb friction
                        -F_c tanh(v / v_s) solved implicitly at the end of each sub-step (stiff for a small v_s:
                        it sticks), a sub-step where the friction changes regime redone in shorter ones, and the
                        state reset at given samples (multiple shooting, docs/PLANT.md)
  friction_velocity     the one implicit friction solve (also the actuator's reduced model's)
  play(...)             the backlash (play) operator: what a load driven through a gear's play of a given width reads
The sample convention everywhere: y_k is read before u_k acts (converter pair at the same instant).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from scipy.linalg import matrix_balance


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


def phi(Am, Bm, tau):
    """Exact ZOH pair (e^{A tau}, int_0^tau e^{A s} ds B) from the augmented matrix exponential (balanced)."""
    n = len(Bm)
    E = np.zeros((n + 1, n + 1)); E[:n, :n] = Am * tau; E[:n, n] = Bm * tau
    if not np.isfinite(E).all():        # a model beyond floating point (its values absurd): not computable, so
        return np.full((n, n), np.nan), np.full(n, np.nan)      # nan, which a fit rejects and its figures refuse
    with np.errstate(invalid="ignore"):    # scipy casts the scale factors to int with the permutation it returns:
        Eb, (sc, _) = matrix_balance(E, permute=False, separate=True)   # one beyond int64 (1e148) warns, harmless
    X = _expm_taylor(Eb)
    X = X * sc[:, np.newaxis] / sc[np.newaxis, :]          # undo the similarity Eb = D^-1 E D
    return X[:n, :n], X[:n, n]


def split_delay(delay_s: float, T: float) -> tuple[int, float]:
    """delay_s = m T + fr with 0 <= fr < T."""
    m = int(math.floor(delay_s / T + 1e-9))
    return m, max(0.0, delay_s - m * T)


def discretise(Am, Bm, T: float, delay_s: float):
    """x_{k+1} = Ad x_k + G0 u_{k-m} + G1 u_{k-m-1}: ZOH input delayed by delay_s = m T + fr (exact)."""
    m, fr = split_delay(delay_s, T)
    Ad, G = phi(Am, Bm, T)
    if fr < 1e-12 * T:
        return Ad, G, np.zeros_like(G), m
    A1, G0 = phi(Am, Bm, T - fr)
    _, Gf = phi(Am, Bm, fr)
    return Ad, G0, A1 @ Gf, m


def substeps(Am, Bm, T: float, n_sub: int, delay_s: float):
    """Sub-step transition Ah (h = T / n_sub) and, per sub-step j, the input vectors of the sample's new and old
    (delayed) input, Bnew[j] and Bold[j]: the held input switches at fr inside the sample (exact)."""
    h = T / n_sub
    m, fr = split_delay(delay_s, T)
    Ah, Bh = phi(Am, Bm, h)
    n = len(Bm)
    Bnew = np.zeros((n_sub, n)); Bold = np.zeros((n_sub, n))
    for j in range(n_sub):
        t0, t1 = j * h, (j + 1) * h
        if t1 <= fr + 1e-15:
            Bold[j] = Bh
        elif t0 >= fr - 1e-15:
            Bnew[j] = Bh
        else:                           # switch at fr inside this sub-step
            A2, Bn = phi(Am, Bm, t1 - fr)
            _, Bo = phi(Am, Bm, fr - t0)
            Bnew[j] = Bn; Bold[j] = A2 @ Bo
    return Ah, Bnew, Bold, m


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
def _run_ss5(Ad, G0, G1, Cm, u, m, out):
    """_run_ss for 5 states (the actuator alone) with the state in registers: the same products summed in the same
    order (the same numbers bit for bit), 2.7x faster."""
    x0 = 0.0; x1 = 0.0; x2 = 0.0; x3 = 0.0; x4 = 0.0
    for k in range(u.shape[0]):
        out[k] = 0.0 + Cm[0] * x0 + Cm[1] * x1 + Cm[2] * x2 + Cm[3] * x3 + Cm[4] * x4
        a = u[k - m] if k - m >= 0 else 0.0
        b = u[k - m - 1] if k - m - 1 >= 0 else 0.0
        n0 = G0[0] * a + G1[0] * b + Ad[0, 0] * x0 + Ad[0, 1] * x1 + Ad[0, 2] * x2 + Ad[0, 3] * x3 + Ad[0, 4] * x4
        n1 = G0[1] * a + G1[1] * b + Ad[1, 0] * x0 + Ad[1, 1] * x1 + Ad[1, 2] * x2 + Ad[1, 3] * x3 + Ad[1, 4] * x4
        n2 = G0[2] * a + G1[2] * b + Ad[2, 0] * x0 + Ad[2, 1] * x1 + Ad[2, 2] * x2 + Ad[2, 3] * x3 + Ad[2, 4] * x4
        n3 = G0[3] * a + G1[3] * b + Ad[3, 0] * x0 + Ad[3, 1] * x1 + Ad[3, 2] * x2 + Ad[3, 3] * x3 + Ad[3, 4] * x4
        n4 = G0[4] * a + G1[4] * b + Ad[4, 0] * x0 + Ad[4, 1] * x1 + Ad[4, 2] * x2 + Ad[4, 3] * x3 + Ad[4, 4] * x4
        x0 = n0; x1 = n1; x2 = n2; x3 = n3; x4 = n4


@numba.njit(cache=True, nogil=True)
def _run_ss7(Ad, G0, G1, Cm, u, m, out):
    """_run_ss5 for 7 states (the actuator on its stand's mode)."""
    x0 = 0.0; x1 = 0.0; x2 = 0.0; x3 = 0.0; x4 = 0.0; x5 = 0.0; x6 = 0.0
    for k in range(u.shape[0]):
        out[k] = 0.0 + Cm[0] * x0 + Cm[1] * x1 + Cm[2] * x2 + Cm[3] * x3 + Cm[4] * x4 + Cm[5] * x5 + Cm[6] * x6
        a = u[k - m] if k - m >= 0 else 0.0
        b = u[k - m - 1] if k - m - 1 >= 0 else 0.0
        n0 = (G0[0] * a + G1[0] * b + Ad[0, 0] * x0 + Ad[0, 1] * x1 + Ad[0, 2] * x2 + Ad[0, 3] * x3 + Ad[0, 4] * x4
              + Ad[0, 5] * x5 + Ad[0, 6] * x6)
        n1 = (G0[1] * a + G1[1] * b + Ad[1, 0] * x0 + Ad[1, 1] * x1 + Ad[1, 2] * x2 + Ad[1, 3] * x3 + Ad[1, 4] * x4
              + Ad[1, 5] * x5 + Ad[1, 6] * x6)
        n2 = (G0[2] * a + G1[2] * b + Ad[2, 0] * x0 + Ad[2, 1] * x1 + Ad[2, 2] * x2 + Ad[2, 3] * x3 + Ad[2, 4] * x4
              + Ad[2, 5] * x5 + Ad[2, 6] * x6)
        n3 = (G0[3] * a + G1[3] * b + Ad[3, 0] * x0 + Ad[3, 1] * x1 + Ad[3, 2] * x2 + Ad[3, 3] * x3 + Ad[3, 4] * x4
              + Ad[3, 5] * x5 + Ad[3, 6] * x6)
        n4 = (G0[4] * a + G1[4] * b + Ad[4, 0] * x0 + Ad[4, 1] * x1 + Ad[4, 2] * x2 + Ad[4, 3] * x3 + Ad[4, 4] * x4
              + Ad[4, 5] * x5 + Ad[4, 6] * x6)
        n5 = (G0[5] * a + G1[5] * b + Ad[5, 0] * x0 + Ad[5, 1] * x1 + Ad[5, 2] * x2 + Ad[5, 3] * x3 + Ad[5, 4] * x4
              + Ad[5, 5] * x5 + Ad[5, 6] * x6)
        n6 = (G0[6] * a + G1[6] * b + Ad[6, 0] * x0 + Ad[6, 1] * x1 + Ad[6, 2] * x2 + Ad[6, 3] * x3 + Ad[6, 4] * x4
              + Ad[6, 5] * x5 + Ad[6, 6] * x6)
        x0 = n0; x1 = n1; x2 = n2; x3 = n3; x4 = n4; x5 = n5; x6 = n6


_RUN_SS = {5: _run_ss5, 7: _run_ss7}


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
        _RUN_SS.get(len(G0), _run_ss)(Ad, G0, G1, Cm, u, m, out)
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


SLIP_OVER_VS = 20.0          # |v| above 20 v_s: sliding (tanh saturated); below: stuck (the stiff tanh holds it)


@numba.njit(cache=True, nogil=True)
def friction_velocity(c0, c1, fric, vs, guess, atol, rtol, sx=0.0, vst=1.0):
    """The velocity v solving c0 - c1 v - F(v) = 0, F(v) = (fric + sx exp(-(v / vst)^2)) tanh(v / vs): a sub-step's
    end velocity with the friction force held at its end value (implicit, stiff for a small vs). sx > 0: Stribeck's
    breakaway above the Coulomb level fric, fading over the Stribeck velocity vst (F no longer monotone: the root
    stays bracketed). Newton from `guess` (else from the slip or the stick solution), bracketed by the roots of the
    saturated friction. The one friction solve of every simulator (rig.diagnose.models for the actuator,
    run_segments here)."""
    top = fric + sx
    if abs(c0) > top:
        # sliding (the one root, of c0's sign) with tanh saturated, 1.0 in double precision above 19.1 v_s: without
        # Stribeck the slip solution is the root; with it, Newton on the smooth saturated equation from there (its
        # slope within 0.2 % of c1). Such a root sits at or next to the bracket's edge, where the bracketed Newton
        # below has its step refused and bisects: ~20 steps a sub-step
        s = 1.0 if c0 > 0 else -1.0
        vv = (c0 - s * fric) / c1
        done = sx <= 0.0
        for it in range(8):
            if done:
                break
            ex = sx * math.exp(-(vv / vst) ** 2)
            dg = -c1 + s * ex * 2.0 * vv / (vst * vst)
            if dg >= 0.0:
                break
            vn = vv - (c0 - c1 * vv - s * (fric + ex)) / dg
            done = abs(vn - vv) < atol + rtol * abs(vv)
            vv = vn
        if done and s * vv > SLIP_OVER_VS * vs:
            return vv
    lo = (c0 - top) / c1; hi = (c0 + top) / c1
    vv = guess
    if vv <= lo or vv >= hi:
        if abs(c0) > top:
            vv = (c0 - fric * (1.0 if c0 > 0 else -1.0)) / c1
        else:
            vv = c0 / (c1 + top / vs)
        if vv <= lo or vv >= hi:
            vv = 0.5 * (lo + hi)
    for it in range(60):
        th = math.tanh(vv / vs)
        ex = sx * math.exp(-(vv / vst) ** 2) if sx > 0.0 else 0.0
        f = c0 - c1 * vv - (fric + ex) * th
        if f > 0.0:
            lo = vv
        else:
            hi = vv
        df = -c1 - (fric + ex) * (1.0 - th * th) / vs + ex * 2.0 * vv / (vst * vst) * th
        vn = vv - f / df if df < 0.0 else 0.5 * (lo + hi)
        if vn <= lo or vn >= hi:
            vn = 0.5 * (lo + hi)
        if abs(vn - vv) < atol + rtol * abs(vv):
            vv = vn
            break
        vv = vn
    return vv


@numba.njit(cache=True, nogil=True)
def _regime(v, vs):
    if v > SLIP_OVER_VS * vs:
        return 1
    if v < -SLIP_OVER_VS * vs:
        return -1
    return 0


@numba.njit(cache=True, nogil=True)
def _substep(Ah, bn, bo, Gf, Cv, x, a, b, f0, fric, vs, sx, vst, xn):
    """One sub-step: the linear part exact, then the friction force held at its end value (implicit); returns
    the end velocity. xn is written."""
    n = Ah.shape[0]
    for i in range(n):
        acc = bn[i] * a + bo[i] * b + Gf[i] * f0
        for q in range(n):
            acc += Ah[i, q] * x[q]
        xn[i] = acc
    z = 0.0
    for i in range(n):
        z += Cv[i] * xn[i]
    if fric <= 0.0 and sx <= 0.0:
        return z
    gv = 0.0
    for i in range(n):
        gv += Cv[i] * Gf[i]
    v0 = 0.0
    for i in range(n):
        v0 += Cv[i] * x[i]
    # friction held over the sub-step at the end velocity v: v + gv F(v) = z
    v = friction_velocity(z, 1.0, gv * fric, vs, v0, 1e-13, 1e-9, gv * sx, vst)
    F = -(fric + (sx * math.exp(-(v / vst) ** 2) if sx > 0.0 else 0.0)) * math.tanh(v / vs)
    for i in range(n):
        xn[i] += Gf[i] * F
    return v


@numba.njit(cache=True, nogil=True)
def _run_segments(Ah, Bnew, Bold, Gf, Cv, Cy, u, m, fric, vs, sx, vst, f0, starts, X0, Ahf, Bnewf, Boldf, Gff,
                  out):
    n = Ah.shape[0]; N = u.shape[0]; n_sub = Bnew.shape[0]
    K = Bnewf.shape[0] // n_sub if (fric > 0.0 or sx > 0.0) else 0
    x = np.zeros(n); xn = np.zeros(n); xm = np.zeros(n); xk = np.zeros(n)
    seg = 0
    nseg = starts.shape[0]
    for k in range(N):
        if seg < nseg and k == starts[seg]:
            for i in range(n):
                x[i] = X0[seg, i]
            seg += 1
        s = 0.0
        for i in range(n):
            s += Cy[i] * x[i]
        out[k] = s
        a = u[k - m] if k - m >= 0 else 0.0
        b = u[k - m - 1] if k - m - 1 >= 0 else 0.0
        for j in range(n_sub):
            v0 = 0.0
            for i in range(n):
                v0 += Cv[i] * x[i]
            v1 = _substep(Ah, Bnew[j], Bold[j], Gf, Cv, x, a, b, f0, fric, vs, sx, vst, xn)
            if K > 1 and _regime(v0, vs) != _regime(v1, vs):
                # the motion reverses, sticks or breaks away inside this sub-step: the friction force changes
                # within it, so the sub-step is redone in K short ones (the event's time to h / K)
                for i in range(n):
                    xm[i] = x[i]
                for q in range(K):
                    _substep(Ahf, Bnewf[j * K + q], Boldf[j * K + q], Gff, Cv, xm, a, b, f0, fric, vs, sx, vst, xk)
                    for i in range(n):
                        xm[i] = xk[i]
                for i in range(n):
                    xn[i] = xm[i]
            for i in range(n):
                x[i] = xn[i]


def run_segments(Ah, Bnew, Bold, Gf, Cv, Cy, u, m, *, friction_n: float = 0.0, smoothing_m_per_s: float = 1e-4,
                 force_n: float = 0.0, stribeck_n: float = 0.0, stribeck_m_per_s: float = 1.0, starts=None,
                 X0=None, fine=None) -> np.ndarray:
    """Output samples of the sub-stepped model (substeps()) with a load-force channel Gf (sub-step integral of
    the force input), the velocity row Cv and the output row Cy; the state set to X0[s] at sample starts[s].
    fine = (Ah, Bnew, Bold, Gf) of K times shorter sub-steps (substeps(..., K n_sub, ...)): a sub-step in which
    friction changes regime (a reversal, sticking, breakaway) is redone on them. stribeck_n: the breakaway force
    above friction_n, fading as exp(-(v / stribeck_m_per_s)^2) (Stribeck)."""
    u = np.ascontiguousarray(u, dtype=float)
    st = np.zeros(0, np.int64) if starts is None else np.ascontiguousarray(starts, dtype=np.int64)
    x0 = np.zeros((len(st), Ah.shape[0])) if X0 is None else np.ascontiguousarray(X0, dtype=float)
    if fine is None:
        fine = (Ah, Bnew, Bold, Gf)
    Ahf, Bnf, Bof, Gff = (np.ascontiguousarray(a, dtype=float) for a in fine)
    out = np.empty(len(u))
    _run_segments(np.ascontiguousarray(Ah), np.ascontiguousarray(Bnew), np.ascontiguousarray(Bold),
                  np.ascontiguousarray(Gf, dtype=float), np.ascontiguousarray(Cv, dtype=float),
                  np.ascontiguousarray(Cy, dtype=float), u, int(m), float(friction_n), float(smoothing_m_per_s),
                  float(stribeck_n), float(stribeck_m_per_s), float(force_n), st, x0, Ahf, Bnf, Bof, Gff, out)
    return out


@numba.njit(cache=True, nogil=True)
def _play(x, half, out):
    yo = x[0] if x.shape[0] else 0.0
    for k in range(x.shape[0]):
        if x[k] - yo > half:
            yo = x[k] - half
        elif x[k] - yo < -half:
            yo = x[k] + half
        out[k] = yo


def play(x, width: float) -> np.ndarray:
    """The backlash operator on a drive's position x: the load stays where it is until the drive has crossed the
    play of `width` (total), then is pushed by its near side (centred at the start). The load is no state of the
    drive's model: where that model's state is set again (a segment's start) the load stays where it was, inside
    the play of the drive's new position."""
    x = np.ascontiguousarray(x, dtype=float)
    out = np.empty(len(x))
    _play(x, 0.5 * float(width), out)
    return out


def free_response(Ad, Cy, length: int) -> np.ndarray:
    """(length, n): row k is Cy Ad^k, the output's response to each unit initial state."""
    n = Ad.shape[0]
    O = np.empty((length, n))
    row = np.asarray(Cy, float).copy()
    for k in range(length):
        O[k] = row
        row = row @ Ad
    return O

"""The replay's residual in the frequency domain: the recording minus the rig model driven by the recorded valve
commands and floor motion (open-loop replay of the closed loop's inputs), after the nuisance terms.

  measured = gain x (Hu U + Hg X_g) + nuisance + noise,   X_g = -(floor accel / floor gain) / w^2

Nuisance terms, fitted by linear least squares inside every evaluation (variable projection), never effects:
  - the end states: one column per mode (rigmodel.Responses.Tb): a record's DFT relates inputs and outputs
    exactly only up to what the states at its two ends add, and every mode's share shows somewhere in the band;
  - with floor accelerometers: the floor's velocity and position at the record's ends (its double integration
    is exact only up to them), Hg / w^2 and Hg / (j w) per mount;
  - a drift on each channel (a sensor's slow zero, or a jump between the record's ends), 1 / (1 - 1/z);
  - without floor accelerometers: the floor itself, four unknowns per bin, projected out bin by bin. What the
    floor can absorb is not seen; what it cannot is the evidence (floor.py says what can be told).
Weights: weights.py, with the model's own error (own_error: the floor held between samples, as the simulated rig
holds it, against the continuous floor the replay takes). Under the right model the whitened residual has unit
variance per bin and channel.
A fit's Jacobian holds the nuisance terms of its base point (Kaufman's approximation of variable projection):
`Replay.linear` projects a perturbed model's residual with the base point's projector, without a new solve.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.linalg

from rig.diagnose.machine.rigmodel import N_OUT, Base, Modal, linear_hold, modal, predict, responses
from rig.diagnose.machine.spectra import Spectra


def floor_hold_error(md: Modal, w: np.ndarray) -> np.ndarray:
    """(K, 8, 4) per metre of the floor as the replay takes it at each mount (-a_g / w^2, a_g its accelerometer's
    samples): what reading the same samples as a floor held linearly between them (displacement, and velocity
    from its central difference, each interpolated over the period; the acceleration its central second
    difference) moves the outputs by beyond the continuous floor's response. A floor known only at its samples
    is either; the replay takes it continuous (a real floor is), and the two differ by this much: the model's
    own error on the floor's path, exact per frequency (the commands' path is a true hold in both)."""
    w = np.asarray(w, dtype=float)
    T = md.T
    z = np.exp(1j * w * T)
    jw = 1j * w
    Pd = linear_hold(md, z)
    Pc = 1.0 / (jw[:, None] - md.lam[None, :])
    v_held = 1j * np.sin(w * T) / T                        # the central difference's velocity per metre
    sinc2 = np.sinc(w * T / (2 * np.pi)) ** 2              # the second difference's acceleration over -w^2
    CVT = md.CV.T
    out = np.empty((len(w), N_OUT, 4), dtype=complex)
    for i in range(4):
        held = (Pd * (md.VBx[:, i][None, :] + v_held[:, None] * md.VBv[:, i][None, :])) @ CVT \
            + md.Dx[None, :, i] + v_held[:, None] * md.Dv[None, :, i]
        smooth = (Pc * (md.VBx[:, i][None, :] + jw[:, None] * md.VBv[:, i][None, :])) @ CVT \
            + md.Dx[None, :, i] + jw[:, None] * md.Dv[None, :, i]
        out[:, :, i] = held / sinc2[:, None] - smooth
    return out


def own_error(base: Base, md: Modal, th: dict, w: np.ndarray, Y: np.ndarray, U: np.ndarray, G: np.ndarray | None,
              sd: np.ndarray) -> np.ndarray:
    """(K, 8) the model's own error at theta per bin and channel, in the channels' units: the floor's path read
    held or continuous (floor_hold_error) times the floor, the floor accelerometers' (without them its estimate
    from what the commands' response leaves, least squares bin by bin, weighted by sd). It follows the floor's
    part per band, not the reading: under isolation the valves' part cancels most of the floor's, and a reading
    is their small difference (a constant share of the reading took the model's error for 1/28 of itself)."""
    g = md.gain_out[None, :, None]
    if G is not None:
        X = -(G / md.gain_floor[None, :]) / (w ** 2)[:, None]
    else:
        H = responses(base, th, w, md=md, valves=False, ends=False).Hg * (g / sd[:, :, None])
        rest = (Y - predict(md, w, U, None) * md.gain_out[None, :]) / sd
        X = np.einsum("kic,kc->ki", np.linalg.pinv(H), rest)
    return np.einsum("kci,ki->kc", floor_hold_error(md, w) * g, X)


@dataclass
class Evaluation:
    """One model evaluated on a set of bins: the whitened residual r (Kset, 8) after every nuisance term, the
    weights' standard deviations sd (r sd: the residual in the channels' units), the nuisance coefficients,
    per bin and channel the share of the noise the floor's projection leaves (1 with floor accelerometers), and
    the projector (to project other residuals on the same bins as this one was)."""
    r: np.ndarray
    sd: np.ndarray
    coef: np.ndarray
    keep: np.ndarray
    mask: np.ndarray
    Q: np.ndarray | None        # (Kset, 8, 4) the floor's whitened responses bin by bin (None: floor measured)
    Nw: np.ndarray              # (Kset * 8, m) whitened nuisance columns after the floor's projection
    NwH: np.ndarray             # its conjugate transpose (contiguous: projections reuse it)
    chol: tuple                 # Cholesky factor of their normal equations (scaled)
    scale: np.ndarray
    terms: np.ndarray           # (Kset, 8) the nuisance terms fitted, whitened, after the floor's projection

    @property
    def rss(self) -> float:
        return float(np.sum(np.abs(self.r) ** 2))

    def project(self, e: np.ndarray) -> np.ndarray:
        """A whitened residual (Kset, 8) with this evaluation's nuisance terms taken out."""
        if self.Q is not None:
            e = np.ascontiguousarray(e[:, :, None])
            _floor_project(self.Q, e, False)
            e = e[:, :, 0]
        b = e.reshape(-1)
        c = self.scale * scipy.linalg.cho_solve(self.chol, (self.NwH @ b) * self.scale)
        return (b - self.Nw @ c).reshape(e.shape)


class _Bins:
    """What does not depend on theta, per set of bins."""

    def __init__(self, sp: Spectra, mask: np.ndarray, s2: np.ndarray):
        self.mask = mask
        self.w = sp.w[mask]
        self.Y = sp.Y[mask]
        self.G = sp.G[mask] if sp.G is not None else None
        self.U = sp.U[mask]
        self.sd = np.sqrt(s2[mask])
        z = np.exp(1j * self.w / sp.fs_hz)
        col = 1.0 / (1.0 - 1.0 / z)
        self.drift = np.zeros((len(self.w), 8, 8), dtype=complex)
        for c in range(8):
            self.drift[:, c, c] = col / self.sd[:, c]


class Replay:
    """The data, the configured model and the weights: evaluates theta on the fit, held-out or all bins."""

    def __init__(self, sp: Spectra, base: Base, s2: np.ndarray):
        self.sp = sp
        self.base = base
        self.floor = sp.G is not None
        self.s2 = s2
        self._bins: dict = {}

    def with_noise(self, s2: np.ndarray) -> "Replay":
        return Replay(self.sp, self.base, s2)

    def bins(self, mask: np.ndarray | None) -> _Bins:
        m = np.ones(len(self.sp.f_hz), bool) if mask is None else mask
        key = m.tobytes()
        if key not in self._bins:
            self._bins[key] = _Bins(self.sp, m, self.s2)
        return self._bins[key]

    def _error(self, b: _Bins, md, U) -> np.ndarray:
        """The whitened error before the nuisance terms: (Y - gain (Hu U + Hg X)) / sd."""
        U = b.U if U is None else U[b.mask]
        X = -(b.G / md.gain_floor[None, :]) / (b.w ** 2)[:, None] if self.floor else None
        pred = predict(md, b.w, U, X) * md.gain_out[None, :]
        return (b.Y - pred) / b.sd

    def evaluate(self, th: dict, mask: np.ndarray | None = None, *, U: np.ndarray | None = None) -> Evaluation:
        """The residual of theta on the bins of mask (default: all). U: other valve commands (the effective
        command of a deadband valve) at every bin."""
        b = self.bins(mask)
        md = modal(self.base, th)
        R = responses(self.base, th, b.w, md=md, valves=False)
        K, n = len(b.w), len(md.lam)
        m = n + (8 if self.floor else 0) + 8
        g = md.gain_out[None, :, None] / b.sd[:, :, None]
        N = np.empty((K, 8, m), dtype=complex)
        N[:, :, :n] = R.Tb * g
        if self.floor:
            N[:, :, n:n + 4] = R.Hg * (g / (b.w ** 2)[:, None, None])
            N[:, :, n + 4:n + 8] = R.Hg * (g / (1j * b.w)[:, None, None])
        N[:, :, m - 8:] = b.drift
        e = self._error(b, md, U)
        Q = None
        keep = np.ones(e.shape)
        if not self.floor:
            Q = np.ascontiguousarray(R.Hg * g)                 # (K, 8, 4) the floor's span, bin by bin
            both = np.concatenate([e[:, :, None], N], axis=2)
            keep = _floor_project(Q, both)                     # in place
            e, N = both[:, :, 0], both[:, :, 1:]
        Nw = N.reshape(-1, m)
        NwH = np.ascontiguousarray(Nw.conj().T)
        M = NwH @ Nw
        d = np.real(np.diag(M)).copy()
        d[d <= 0] = 1.0
        scale = 1.0 / np.sqrt(d)
        chol = scipy.linalg.cho_factor(M * scale[:, None] * scale[None, :] + 1e-10 * np.eye(m))
        eb = e.reshape(-1)
        coef = scale * scipy.linalg.cho_solve(chol, (NwH @ eb) * scale)
        r = (eb - Nw @ coef).reshape(e.shape)
        return Evaluation(r, b.sd, coef, keep, b.mask, Q, Nw, NwH, chol, scale, (Nw @ coef).reshape(e.shape))

    def faithful(self, th: dict, at: Evaluation, *, U: np.ndarray | None = None) -> np.ndarray:
        """(Kset, 8) the model's own error at theta (own_error) on at's bins after at's nuisance terms, in the
        channels' units: what the two readings of the floor differ by (the replay takes the continuous one)."""
        b = self.bins(at.mask)
        U = b.U if U is None else U[b.mask]
        e = own_error(self.base, modal(self.base, th), th, b.w, b.Y, U, b.G, b.sd) / b.sd
        return np.abs(at.project(e)) * b.sd

    def linear(self, th: dict, at: Evaluation, *, U: np.ndarray | None = None) -> np.ndarray:
        """theta's whitened residual on at's bins with at's nuisance terms (Kaufman): for Jacobians and screens.
        With floor accelerometers projected off at's nuisance span; without them projected off theta's own
        floor span, less at's fitted nuisance terms (the floor's responses move with theta far more than the
        end terms do)."""
        b = self.bins(at.mask)
        md = modal(self.base, th)
        e = self._error(b, md, U)
        if at.Q is None:
            return at.project(e)
        R = responses(self.base, th, b.w, md=md, valves=False, ends=False)
        H = np.ascontiguousarray(R.Hg * (md.gain_out[None, :, None] / b.sd[:, :, None]))
        e = np.ascontiguousarray(e[:, :, None])
        _floor_project(H, e, False)
        return e[:, :, 0] - at.terms


@numba.njit(cache=True)
def _floor_project(H, E, keep_too=True):
    """Per bin k: E[k] -= H[k] (H[k]^H H[k])^-1 H[k]^H E[k] (each column of E[k] off the floor's span, in place);
    returns the diagonal of I - H (H^H H)^-1 H^H per bin and channel (the share of a channel's noise left;
    keep_too False: not computed, ones). The 4 x 4 Gram matrix by Cholesky, bin by bin."""
    K, no, nf = H.shape
    m = E.shape[2]
    keep = np.ones((K, no))
    L = np.zeros((nf, nf), dtype=np.complex128)
    first = -no if keep_too else 0
    v = np.empty(nf, dtype=np.complex128)
    for k in range(K):
        for i in range(nf):                                   # Cholesky of G = H^H H
            for j in range(i + 1):
                acc = 0.0j
                for c in range(no):
                    acc += np.conj(H[k, c, i]) * H[k, c, j]
                for q in range(j):
                    acc -= L[i, q] * np.conj(L[j, q])
                if i == j:
                    L[i, i] = np.sqrt(max(acc.real, 1e-300))
                else:
                    L[i, j] = acc / L[j, j].real
        for col in range(first, m):                           # the channels' unit vectors (keep), then E's columns
            for i in range(nf):
                acc = 0.0j
                if col < 0:
                    acc = np.conj(H[k, col + no, i])
                else:
                    for c in range(no):
                        acc += np.conj(H[k, c, i]) * E[k, c, col]
                for q in range(i):
                    acc -= L[i, q] * v[q]
                v[i] = acc / L[i, i].real
            if col < 0:                                       # h_c G^-1 h_c^H = |L^-1 h_c^H|^2
                s = 0.0
                for i in range(nf):
                    s += v[i].real ** 2 + v[i].imag ** 2
                keep[k, col + no] = 1.0 - s
                continue
            for i in range(nf - 1, -1, -1):                   # back-substitution: G x = H^H e
                acc = v[i]
                for q in range(i + 1, nf):
                    acc -= np.conj(L[q, i]) * v[q]
                v[i] = acc / L[i, i].real
            for c in range(no):
                acc = 0.0j
                for i in range(nf):
                    acc += H[k, c, i] * v[i]
                E[k, c, col] -= acc
    return keep

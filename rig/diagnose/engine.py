"""Diagnosis engine (issues 7 and 12): refit the linear model first, locate the mismatch, choose missing physics
from the catalogue, fit the augmented model and prove each effect on a held-out segment; the sensors' own terms
ride along in every model as nuisance parameters and are reported apart from the physics.

Protocol
  * The recorded command is read first (rig.diagnose.command): sweep, multisine, steps, noise, one level or
    several. The evidence follows from it, never from an assumed linear chirp.
  * Samples left out of every fit: flat tops at a converter's range (clipped), and, when the recording does not
    start at rest, the plant's start transient.
  * Fit/holdout split: interleaved blocks (even blocks fit, odd blocks held out), so both cover the whole run.
  * Every model (nominal, refit, augmented) = physics + sensor terms. The sensor terms (offset, drift, slow
    wander, pickup lines; rig.diagnose.sensor) are linear in their coefficients and are projected out on the fit
    blocks inside each evaluation (variable projection), so they never compete with the physics as effects.
  * Lines in the refit residual are sorted by the two sensors: in position but not in acceleration at the
    (2 pi f)^2-predicted amplitude = pickup (a sensor term); in both = a force (the periodic_disturbance
    candidate).
  * Refit: the identified parameters K_L, K_C, K_Q, w_nv, zeta within physical bounds (0.7-1.4 x nominal; C is
    not identifiable from position below w_h and stays nominal). A parameter change is not missing physics.
  * Candidates: each catalogue effect fitted jointly with the linear parameters (exact fast models, models.py).
    An effect counts only when it passes BOTH: BIC on the fit blocks (noise variance from the data) and a
    likelihood-ratio test on the held-out blocks with the parameters frozen from the fit blocks.
  * Forward selection: best single effect, then the best second effect on top of it, max two; a round is
    skipped once the held-out residual is at the noise. Each chosen model is polished (all parameters).
  * Pair step (plant files' axes only): when the selection leaves the recording above the noise, pairs of
    one-parameter effects fitted jointly from their first-round fits, under the same tests (_pairs).
  * Screening for speed: the disturbance only with a force line; slow nonlinear models (deadband, friction) are
    refined only when their best grid start rivals the best candidate so far (and, without a sign of
    nonlinearity in the command's own terms -- harmonics of a sweep, empty lines of a multisine -- improves the
    current fit). A fast effect added to a slow model is fitted on a superposition proxy.
  * Confounded groups: other passing candidates whose held-out likelihood is statistically indistinguishable
    from the chosen one's (log-likelihood ratio below ln n) are reported as a group.
  * Verdict: "explained" only when the augmented residual is at the noise. Otherwise the summary says plainly
    that the model does not describe the recording, and what the evidence suggests.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.signal import welch

from rig import closedloop
from rig.diagnose import catalogue, command as command_mod
from rig.diagnose import evidence as evidence_mod, locate, noise as noise_mod, sensor as sensor_mod
from rig.diagnose.lm import lm_fit
from rig.diagnose.plants import at_bounds, model_for
from rig.plant.model import Plant
from rig.errors import RecordingError
from rig.recording import check_plausible
from sim_backend.linear import ActuatorParams

LIN_BOUNDS = (0.7, 1.4)            # x nominal: physically bounded refit (recordings move them +-15 %)
N_BLOCKS = 51                      # interleaved blocks (2 s blocks of a 100 s chirp); odd: the first and the last
                                   # are fit blocks, so the slow sensor terms never extrapolate into a held-out end
MAX_EFFECTS = 2
HARMONIC_SCREEN = 4.0              # nonlinear distortion / noise that makes nonlinear candidates worth fitting
LINE_RATIO = 40.0                  # spectral line / local median for a line candidate
EXPLAINED = 1.01                   # held-out residual rms / noise below which no further effect is sought
EXPLAINED_SLOW = 1.02              # the same once a reduced (deadband/friction) model is in
MIN_GAIN = 0.003                   # an effect must cut the held-out residual variance by at least 0.3 %
SLOW_RTOL = 1e-4                   # a slow (reduced) model's fit stops when an iteration gains < 0.01 % of the rss
MIN_CLAIM_S = 5.0                  # shorter recordings get no claim
MIN_SNR = 3.0                      # motion rms / noise below which the recording is too poorly excited
VERDICT_AT_NOISE = 1.15            # augmented residual / noise: "explains the recording"
VERDICT_NOT_DESCRIBED = 3.0        # above: the model does not describe the recording, nothing is named
START_TRANSIENT_S = 1.0            # left out when the recording starts mid-run (the plant forgets in ~0.1 s, a
                                   # lightly damped stand mode in ~1 s)


@dataclass
class Verdict:
    status: str                    # explained | partly | not_described | no_claim
    text: str
    suggestions: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"status": self.status, "text": self.text, "suggestions": list(self.suggestions)}


@dataclass
class Diagnosis:
    effects: list[dict] = field(default_factory=list)        # [{"name","parameters","evidence","score"}]
    group: list[list[str]] = field(default_factory=list)     # confounded groups
    mismatch: dict = field(default_factory=dict)             # bands_hz, windows_s, regimes, harmonics, uncorrelated
    fit: dict = field(default_factory=dict)                  # nominal/refit/augmented -> {"nrmse", ...}
    params_refit: dict = field(default_factory=dict)
    noise_m: float = 0.0
    summary: str = ""
    series: dict = field(default_factory=dict)               # nominal_m, refit_m, augmented_m, ... (as recorded)
    frf: dict = field(default_factory=dict)                  # freqs_hz, measured, nominal, refit, augmented, coherence
    candidates: list[dict] = field(default_factory=list)     # every candidate tried with its test statistics
    timing_s: float = 0.0
    sensor: sensor_mod.SensorTerms | None = None             # sensor terms of the augmented model
    command: command_mod.Command | None = None               # what the recorded command is
    verdict: Verdict | None = None
    evidence: dict = field(default_factory=dict)             # plot data behind each named effect and sensor term
    used: np.ndarray | None = None                           # samples the fits used (not clipped, past the start)
    noise_floor: noise_mod.NoiseFloor | None = None
    plant: dict = field(default_factory=dict)                # family, input unit, fitted linear keys, shooting

    def names(self) -> list[str]:
        return sorted(e["name"] for e in self.effects)


# ---- fitting machinery ------------------------------------------------------------------------------------

@dataclass
class Fit:
    lin: dict                     # linear parameter values
    fx: dict                      # effects {name: {key: value}} (disturbance: frequency_hz only)
    rss_fit: float
    rss_hold: float
    k: int                        # number of fitted physics parameters
    dist: tuple | None = None     # (freq, coef_sin, coef_cos)
    coef: np.ndarray | None = None   # sensor-basis coefficients
    state: np.ndarray | None = None  # segment-wise initial states' response (multiple shooting), metres


@dataclass
class Shooting:
    """Segment-wise initial states of a plant with a pole at the origin (docs/PLANT.md): each segment is a fit
    block and the held-out block after it; its initial state is estimated on the fit block (a linear nuisance
    parameter, projected out with the sensor terms) and the held-out block is the model's prediction from it."""
    starts: np.ndarray            # first sample of each segment
    ends: np.ndarray
    X0: dict = field(default_factory=dict)     # state dimension -> (segments, n) states from the data

    @property
    def count(self) -> int:
        return len(self.starts)

    def as_dict(self, fs: float) -> dict:
        lens = (self.ends - self.starts) / fs
        return {"segments": int(self.count), "segment_s": [float(np.min(lens)), float(np.max(lens))],
                "method": "multiple shooting: each segment's initial state estimated on its fit block, its "
                          "held-out block predicted from it"}


SHOOT_BLOCK_S = 0.5                # block length of a segmented plant (a segment: a fit and a held-out block)
SHOOT_GN_STEPS = 2                 # Gauss-Newton steps on the segment states of a model with friction


def _n_blocks(plant, n: int, fs: float) -> int:
    if not plant.segmented:
        return N_BLOCKS
    k = int(round(n / fs / SHOOT_BLOCK_S))
    return int(min(201, max(21, k | 1)))            # odd: the first and the last are fit blocks


class Problem:
    def __init__(self, cmd: np.ndarray, y: np.ndarray, fs: float, p0, use: np.ndarray):
        self.cmd = np.asarray(cmd, dtype=float)
        self.y = np.asarray(y, dtype=float)
        self.fs = float(fs)
        self.n = len(self.y)
        self.plant = model_for(p0)
        self.p0 = self.plant.p0                     # ActuatorParams of the eha plant, else None
        self.lin_keys = self.plant.lin_keys
        self.nominal = dict(self.plant.nominal)
        self.t = np.arange(self.n) / self.fs
        self.use = np.asarray(use, bool)
        n_blocks = _n_blocks(self.plant, self.n, self.fs)
        blk = np.arange(self.n) * n_blocks // self.n
        self.mfit = ((blk % 2) == 0) & self.use
        self.mhold = ((blk % 2) == 1) & self.use
        self.scale = self.plant.scale(self.cmd, self.fs)   # what effects' bounds and starts are relative to
        self.noise = 1.0
        self.n_eval = 0
        self.base_band = (5.0, 0.45 * self.fs)     # set to the excited band once known
        self.quick = False
        self.proxy = None
        self.broadband = False                      # noise or steps command (set once the command is read)
        self.loop = None                            # closedloop.LoopEvidence (set once the data are read)
        self.shoot = None
        if self.plant.segmented:
            pair = blk // 2
            starts = np.flatnonzero(np.r_[True, np.diff(pair) != 0])
            ends = np.r_[starts[1:], self.n]
            # the first segment starts at the first sample the fits use: the instants left out are the start-up
            # (in closed loop the loop's own transient, the carriage kicked and stuck), where a start state read
            # from the data is poor, and with friction no linear correction undoes it
            first = int(np.argmax(self.use)) if self.use.any() else 0
            starts[0] = min(max(starts[0], first), ends[0] - 1)
            self.shoot = Shooting(starts, ends)
        self._free = (None, None)
        self.set_basis(sensor_mod.SensorBasis(self.n, self.fs, zero_terms=self.shoot is None))

    # -- sensor terms
    def set_basis(self, basis: sensor_mod.SensorBasis) -> None:
        self.basis = basis
        self._Bf = np.ascontiguousarray(basis.B[self.mfit])
        self._G = self._Bf.T @ self._Bf
        self._cho = cho_factor(self._G) if basis.m else None

    def _coef(self, rf: np.ndarray, Ff: np.ndarray | None = None):
        """Least-squares coefficients of the sensor basis (and of F, the disturbance regressors) on the fit
        blocks: normal equations, the basis Gram matrix factored once per basis."""
        Btr = self._Bf.T @ rf
        if Ff is None:
            return cho_solve(self._cho, Btr), None
        BtF = self._Bf.T @ Ff
        M = np.block([[self._G, BtF], [BtF.T, Ff.T @ Ff]])
        v = np.r_[Btr, Ff.T @ rf]
        try:
            sol = np.linalg.solve(M, v)
        except np.linalg.LinAlgError:
            sol = np.linalg.lstsq(M, v, rcond=None)[0]
        m = self.basis.m
        return sol[:m], sol[m:]

    def _project(self, r: np.ndarray, F: np.ndarray | None = None):
        """The full-length residual with the sensor terms (and F) fitted on the fit blocks removed, the sensor
        coefficients and F's coefficients."""
        c, d = self._coef(r[self.mfit], None if F is None else F[self.mfit])
        out = r - self.basis.B @ c
        if F is not None:
            out = out - F @ d
        return out, c, d

    def free_response(self, lin: dict, fx: dict) -> np.ndarray:
        """The segment-state regressors' shape (response to each unit initial state), cached per model."""
        key = (tuple(sorted(lin.items())), repr(self.plant.matrices_key(fx)))
        if self._free[0] != key:
            L = int(np.max(self.shoot.ends - self.shoot.starts))
            self._free = (key, self.plant.free_response(lin, fx, self.fs, L))
        return self._free[1]

    def _project_shooting(self, r: np.ndarray, F: np.ndarray | None, O: np.ndarray, states: bool = False):
        """_project with the segment-wise initial states: block-sparse normal equations (each segment's state
        touches only its own rows), Jacobi-scaled. Returns (residual, sensor coef, F coef, state response) and,
        with states=True, the (segments, n) initial-state corrections too."""
        w = self.mfit
        E = self.basis.B if F is None else np.column_stack([self.basis.B, F])
        q = E.shape[1]
        nx = O.shape[1]
        sh = self.shoot
        N = q + nx * sh.count
        G = np.zeros((N, N)); b = np.zeros(N)
        Ef = E[w]
        G[:q, :q] = Ef.T @ Ef
        b[:q] = Ef.T @ r[w]
        for s, (a, e) in enumerate(zip(sh.starts, sh.ends)):
            ws = w[a:e]
            Ow = O[:e - a][ws]
            i = q + s * nx
            G[i:i + nx, i:i + nx] = Ow.T @ Ow
            if q:
                X = E[a:e][ws].T @ Ow
                G[:q, i:i + nx] = X
                G[i:i + nx, :q] = X.T
            b[i:i + nx] = Ow.T @ r[a:e][ws]
        d = np.sqrt(np.maximum(np.diag(G), 1e-300))
        Gn = G / np.outer(d, d) + 1e-12 * np.eye(N)
        try:
            sol = np.linalg.solve(Gn, b / d) / d
        except np.linalg.LinAlgError:
            sol = np.linalg.lstsq(Gn, b / d, rcond=None)[0] / d
        state = np.empty(self.n)
        for s, (a, e) in enumerate(zip(sh.starts, sh.ends)):
            state[a:e] = O[:e - a] @ sol[q + s * nx:q + (s + 1) * nx]
        out = r - E @ sol[:q] - state
        m = self.basis.m
        if states:
            return out, sol[:m], (sol[m:q] if F is not None else None), state, sol[q:].reshape(sh.count, nx)
        return out, sol[:m], (sol[m:q] if F is not None else None), state

    def model(self, lin: dict, fx: dict) -> np.ndarray:
        self.n_eval += 1
        sfx = catalogue.simulated(fx)
        if self.proxy is not None:
            # superposition proxy: the exact slow model at its fit plus the change that the fast linear-sim
            # effects (delay, base, clip) and linear parameters make
            y_cur, base_c = self.proxy
            fl = catalogue.fast(sfx)
            return y_cur + self.simulate(lin, fl) - base_c
        return self.simulate(lin, sfx)

    def simulate(self, lin: dict, fx: dict) -> np.ndarray:
        """The plant with the effects fx (no disturbance) from the recorded command; a segmented plant from the
        data's state at each segment start."""
        if self.shoot is None:
            return self.plant.simulate(lin, self.cmd, self.fs, fx)
        nx = self.plant.matrices(lin, fx)[0].shape[0]
        if nx not in self.shoot.X0:
            self.shoot.X0[nx] = self.plant.state_from_data(self.y, self.fs, self.shoot.starts, fx)
        X0 = self.shoot.X0[nx]
        y = self.plant.simulate(lin, self.cmd, self.fs, fx, self.shoot.starts, X0)
        if not catalogue.slow_in(fx):
            return y            # linear in the initial state: the projection's correction is exact
        # friction makes the response nonlinear in the initial state (a wrong start velocity moves the reversals
        # and the sticking): Gauss-Newton steps on the segment states, the correction the projection finds from
        # the data's start applied to the simulation itself; the projection then corrects what is left
        for _ in range(SHOOT_GN_STEPS):
            _, _, _, _, dX = self._project_shooting(self.y - y, None, self.free_response(lin, fx), states=True)
            X0 = X0 + dX
            y = self.plant.simulate(lin, self.cmd, self.fs, fx, self.shoot.starts, X0)
        return y

    def _residual_full(self, lin: dict, fx: dict):
        r = self.y - self.model(lin, fx)
        f_line = catalogue.line_frequency(fx)
        F = self.force_basis(lin, fx) if f_line is not None else None
        state = None
        if self.shoot is not None:
            r, c, d, state = self._project_shooting(r, F, self.free_response(lin, fx))
        else:
            r, c, d = self._project(r, F)
        dist = None
        if F is not None:
            dist = (f_line, float(d[0]), float(d[1]))      # force amplitudes [N] of sin and cos
        return r, dist, c, state

    def residual(self, lin: dict, fx: dict):
        """Full-length residual with the sensor terms (and the disturbance) projected out on the fit blocks,
        the disturbance coefficients and the sensor coefficients."""
        r, dist, c, _ = self._residual_full(lin, fx)
        return r, dist, c

    def residual_fit(self, lin: dict, fx: dict) -> np.ndarray:
        """The residual on the fit blocks only (what the least squares see)."""
        if self.shoot is not None:
            return self._residual_full(lin, fx)[0][self.mfit]
        rf = self.y[self.mfit] - self.model(lin, fx)[self.mfit]
        Ff = self.force_basis(lin, fx)[self.mfit] if catalogue.projected(fx) else None
        c, d = self._coef(rf, Ff)
        rf = rf - self._Bf @ c
        if Ff is not None:
            rf = rf - Ff @ d
        return rf

    def force_basis(self, lin: dict, fx: dict) -> np.ndarray:
        """Position responses to a unit sin/cos load force at the disturbance frequency (linear model with
        the base mode if named; the nonlinear effects are not applied to this small line)."""
        return self.plant.force_response(lin, fx, self.fs, catalogue.line_frequency(fx), self.n)

    def spec_keys(self, name: str) -> tuple[str, ...]:
        return self.plant.effects[name].keys(self.plant.input_unit)

    def n_params(self, fx: dict) -> int:
        """Fitted physics parameters: the linear ones, each effect's keys, the disturbance's frequency + 2."""
        return len(self.lin_keys) + sum(catalogue.get(n).n_free for n in fx)

    def fit(self, lin0: dict, fx0: dict, free_lin=None, free_fx: dict | None = None, max_iter=20,
            rtol: float = 1e-5) -> Fit:
        """Least squares on the fit blocks over free linear keys (log scale where positive) and the free effect
        keys."""
        free_lin = self.lin_keys if free_lin is None else tuple(k for k in free_lin if k in self.lin_keys)
        free_fx = {n: self.spec_keys(n) for n in catalogue.simulated(fx0)} if free_fx is None else free_fx
        eha = self.plant.family == "eha"
        names, lo, hi, x0, scale = [], [], [], [], []
        for k in free_lin:
            names.append(("lin", k)); nom = self.nominal[k]
            blo, bhi = self.plant.bounds_lin[k]
            if eha:
                lo.append(math.log(LIN_BOUNDS[0])); hi.append(math.log(LIN_BOUNDS[1]))
                x0.append(math.log(lin0.get(k, nom) / nom)); scale.append(0.05)
            elif self.plant.log_scale[k]:
                lo.append(math.log(blo / nom)); hi.append(math.log(bhi / nom))
                x0.append(math.log(lin0.get(k, nom) / nom)); scale.append(0.05)
            else:
                lo.append(blo); hi.append(bhi)
                x0.append(lin0.get(k, nom)); scale.append(0.02 * (bhi - blo))
        for n, keys in free_fx.items():
            bnd = self.effect_bounds(n)
            for key, (a, b) in zip(self.spec_keys(n), bnd):
                if key not in keys:
                    continue
                names.append((n, key)); lo.append(a); hi.append(b)
                x0.append(fx0[n][key]); scale.append(0.02 * (b - a))
        x0 = np.clip(np.array(x0), np.array(lo) + 1e-12, np.array(hi) - 1e-12)

        def unpack(x):
            lin = dict(lin0); fx = {n: dict(v) for n, v in fx0.items()}
            for (grp, key), val in zip(names, x):
                if grp == "lin":
                    lin[key] = (self.nominal[key] * math.exp(val) if (eha or self.plant.log_scale[key])
                                else float(val))
                else:
                    fx[grp][key] = float(val)
            return lin, fx

        def fun(x):
            lin, fx = unpack(x)
            return self.residual_fit(lin, fx) / self.noise

        if names:
            x, _ = lm_fit(fun, x0, lo, hi, np.array(scale) * 1e-3, max_iter=max_iter, rtol=rtol)
            lin, fx = unpack(x)
        else:
            lin, fx = dict(lin0), {n: dict(v) for n, v in fx0.items()}
        return self.evaluate(lin, fx, k=self.n_params(fx))

    def effect_bounds(self, name: str) -> list[tuple[float, float]]:
        """The bounds of an effect's fitted keys on this recording (a mode seen as a pair only inside the excited
        band: its frequency within it)."""
        effect = catalogue.get(name)
        bnd = effect.bounds(self.scale)
        return [self.base_band] + list(bnd[1:]) if effect.in_band else bnd

    def evaluate(self, lin: dict, fx: dict, k: int) -> Fit:
        r, dist, c, state = self._residual_full(lin, fx)
        return Fit(lin=lin, fx=fx, rss_fit=float(np.sum(r[self.mfit] ** 2)), rss_hold=float(np.sum(r[self.mhold] ** 2)),
                   k=k, dist=dist, coef=c, state=state)

    def physics(self, f: Fit) -> np.ndarray:
        """The physics part of a fitted model (with the disturbance's response and the segment states), metres."""
        yhat = self.model(f.lin, f.fx)
        if f.dist is not None:
            yhat = yhat + self.force_basis(f.lin, f.fx) @ np.array(f.dist[1:])
        if f.state is not None:
            yhat = yhat + f.state
        return yhat

    def series(self, f: Fit) -> np.ndarray:
        """The measurement as the model has it: physics plus the fitted sensor terms."""
        return self.physics(f) + self.basis.B @ f.coef


# ---- tests -------------------------------------------------------------------------------------------------

def compare(pb: Problem, base: Fit, cand: Fit) -> dict:
    """BIC on the fit blocks and a likelihood ratio on the held-out blocks (parameters frozen)."""
    nf = int(pb.mfit.sum()); nh = int(pb.mhold.sum())
    dk = max(1, cand.k - base.k)
    dbic = nf * math.log(base.rss_fit / cand.rss_fit) - dk * math.log(nf)
    lr_h = nh * math.log(base.rss_hold / cand.rss_hold)
    gain_h = 1.0 - cand.rss_hold / base.rss_hold
    passed = dbic > 0 and lr_h > dk * math.log(nh) and gain_h > MIN_GAIN
    return {"delta_bic_fit": dbic, "lr_holdout": lr_h, "lr_needed": dk * math.log(nh), "holdout_gain": gain_h,
            "dk": dk, "passed": bool(passed)}


# ---- candidate initialisation -------------------------------------------------------------------------------

def _init_candidate(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines,
                    y_clean: np.ndarray) -> tuple[dict, dict] | None:
    """The start of an effect's fit, as its definition's start says (rig/diagnose/starts.py)."""
    return catalogue.get(name).start.initial(pb, name, lins, fx_base, band, lines, y_clean, catalogue.slow_in(fx_base))


def _with_prior(pb: Problem, name: str, init, fx_base: dict, prior: dict | None):
    """The better start of two: the fresh one, or the effect's parameters from the first round (an effect found
    alone is often easier to find again from where it was)."""
    if prior is None or init is None:
        return init
    lin0, fx0 = init
    alt = {n: dict(v) for n, v in fx_base.items()}
    alt[name] = dict(prior)
    r0, _, _ = pb.residual(lin0, fx0)
    r1, _, _ = pb.residual(lin0, alt)
    return (lin0, alt) if np.sum(r1[pb.mfit] ** 2) < np.sum(r0[pb.mfit] ** 2) else init


def _fit_candidate(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean, second=False,
                   skip_above: float | None = None, prior: dict | None = None) -> Fit | None:
    if second and not catalogue.get(name).slow and catalogue.slow_in(fx_base):
        return _fit_by_proxy(pb, name, lins, fx_base, band, lines, y_clean, prior)
    init = _with_prior(pb, name, _init_candidate(pb, name, lins, fx_base, band, lines, y_clean), fx_base, prior)
    if init is None:
        return None
    lin0, fx0 = init
    slow = catalogue.slow_in(fx0)
    if (slow or catalogue.get(name).costly_start) and skip_above is not None:
        # another candidate already reached the noise, or nothing calls for this one: refine only a start
        # that is already competitive
        st = pb.evaluate(lin0, fx0, k=0)
        if st.rss_fit > skip_above:
            return Fit(lin=lin0, fx=fx0, rss_fit=st.rss_fit, rss_hold=st.rss_hold, k=pb.n_params(fx0), coef=st.coef, state=st.state)
    if slow and second:   # on a slow model: the effects with the gain and lag; the polish frees all
        return pb.fit(lin0, fx0, free_lin=pb.plant.slow_second_lin, max_iter=6,
                      rtol=SLOW_RTOL)
    if slow:
        return pb.fit(lin0, fx0, max_iter=6, rtol=SLOW_RTOL)
    return pb.fit(lin0, fx0, max_iter=10)


def _fit_by_proxy(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean,
                  prior: dict | None = None) -> Fit | None:
    """A fast effect added to a slow (deadband/friction) model: fit it on the superposition proxy (one slow
    simulation), then score the result with the exact slow model."""
    lin_c = lins[0]
    y_cur = pb.model(lin_c, fx_base)
    base_c = pb.simulate(lin_c, catalogue.fast(fx_base))
    pb.proxy = (y_cur, base_c)
    try:
        init = _with_prior(pb, name, _init_candidate(pb, name, lins, fx_base, band, lines, y_clean), fx_base, prior)
        if init is None:
            return None
        lin0, fx0 = init
        free_fx = {n: pb.spec_keys(n) for n in catalogue.fast(fx0)}
        f = pb.fit(lin0, fx0, free_fx=free_fx, max_iter=12)
    finally:
        pb.proxy = None
    return pb.evaluate(f.lin, f.fx, k=pb.n_params(f.fx))


def _active(pb: Problem, f: Fit, name: str) -> bool:
    """Does the fitted effect itself carry the gain? The candidate with the effect taken out (everything else as
    fitted) must be worse on the held-out blocks by the same likelihood-ratio margin; a deadband of width 0 that
    passed a test would be the linear parameters' extra iterations, not the effect."""
    if catalogue.get(name).projected:
        return True
    without = {k: v for k, v in f.fx.items() if k != name}
    r, _, _ = pb.residual(f.lin, without)
    nh = int(pb.mhold.sum())
    rss_wo = float(np.sum(r[pb.mhold] ** 2))
    return nh * math.log(max(rss_wo, 1e-300) / max(f.rss_hold, 1e-300)) > len(pb.spec_keys(name)) * math.log(nh)


def _at_edge(pb: Problem, f: Fit, name: str) -> bool:
    """A stand mode pinned at the edge of its physical range (its frequency at the excited band's edge, its
    damping ratio or the base's mass at a bound) is three free parameters spent on what is not a mode: a clean
    closed-loop run's fed-back noise fitted by a 161 Hz mode of damping 0.003 on a base of 100 x the axis's mass.
    Only the stand mode: a one-parameter effect at its bound is inactive or a real extreme."""
    if not catalogue.get(name).edge_test:
        return False
    for key, (lo, hi) in zip(pb.spec_keys(name), pb.effect_bounds(name)):
        v = f.fx[name][key]
        if min(abs(math.log(v / lo)), abs(math.log(hi / v))) < 0.01:
            return True
    return False


def _polish(pb: Problem, f: Fit) -> Fit:
    """All linear and effect parameters together (the disturbance frequency refined after)."""
    slow = catalogue.slow_in(f.fx)
    pol = _refine_disturbance(pb, pb.fit(f.lin, f.fx, max_iter=5 if slow else 15, rtol=SLOW_RTOL if slow else 1e-5))
    return pol if pol.rss_fit < f.rss_fit else f


def _refine_disturbance(pb: Problem, f: Fit) -> Fit:
    line = catalogue.projected(f.fx)
    if line is None:
        return f
    fx = {n: {k: v for k, v in d.items()} for n, d in f.fx.items()}
    r = pb.y - pb.model(f.lin, fx) - pb.basis.B @ f.coef - (f.state if f.state is not None else 0.0)
    fx[line]["frequency_hz"] = locate.refine_line(r * pb.use, pb.fs, fx[line]["frequency_hz"])
    out = pb.evaluate(f.lin, fx, f.k)
    return out if out.rss_fit <= f.rss_fit else f


# ---- sensor terms --------------------------------------------------------------------------------------------

def _choose_wander(pb: Problem, fit: Fit, max_terms: int) -> int:
    """Number of slow-wander cosines by BIC on the fit blocks, the physics held at `fit` (nested bases: one QR
    of the largest gives every smaller one's residual; at most 200 k fit rows, evenly spread, for the choice)."""
    if max_terms < 1:
        return 0
    rows = np.flatnonzero(pb.mfit)
    rows = rows[:: max(1, int(math.ceil(len(rows) / 200_000)))]
    rf = (pb.y - pb.physics(fit))[rows]
    n = pb.n
    cols = [np.ones(len(rows)), 2.0 * rows / max(n - 1, 1) - 1.0]
    cols += [np.cos(math.pi * k * (rows + 0.5) / n) for k in range(2, 2 + max_terms)]
    cols += [pb.basis.B[rows, j] for j in range(2 + pb.basis.wander_terms, pb.basis.m)]     # lines, if any
    order = [0, 1] + list(range(2 + max_terms, len(cols))) + list(range(2, 2 + max_terms))
    Q, _ = np.linalg.qr(np.column_stack([cols[j] for j in order]))
    proj = Q.T @ rf
    total = float(rf @ rf)
    nf = len(rf)
    base_m = len(cols) - max_terms
    best = (np.inf, 0)
    for k in sorted({0, 1, 2, 4, 8, 16, max_terms}):
        if k > max_terms:
            continue
        m = base_m + k
        rss = max(total - float(proj[:m] @ proj[:m]), 1e-300)
        bic = nf * math.log(rss) + m * math.log(nf)
        if bic < best[0]:
            best = (bic, k)
    return best[1]


def _on_grid(f: float, grid_hz: float, T: float) -> int | None:
    """The grid index k when f is within one resolution bin of k grid_hz, else None."""
    if not grid_hz:
        return None
    k = int(round(f / grid_hz))
    return k if k >= 1 and abs(f - k * grid_hz) <= 1.0 / T else None


def _lines(pb: Problem, r: np.ndarray, acc: np.ndarray, acc_model: np.ndarray | None, check, fs: float,
           cmd_info: command_mod.Command, acc_use: np.ndarray):
    """Lines of the position residual sorted by the two sensors into pickup (sensor) and force (physics);
    plus lines the accelerometer alone shows (pickup on that channel).

    A periodic command puts its own response (linear and nonlinear) on its line grid: a line there is the
    command's, unless only the position shows it (pickup) or it stands ten times above its unexcited neighbours
    (a force that happens to fall on the grid)."""
    T = pb.n / fs
    grid = fs / cmd_info.period if cmd_info.kind == "multisine" and cmd_info.period else 0.0
    excited = set(int(k) for k in cmd_info.excited_lines) if grid else set()
    found = locate.spectral_lines(r * pb.use, fs, pb.noise, ratio=LINE_RATIO, top=12)
    a_res = None
    if check is not None and check.usable and acc_model is not None:
        a_res = acc - check.gain.real * acc_model - np.mean(acc)       # gain phase is ~0 for a real sensor
    R = np.abs(np.fft.rfft(r * pb.use)) if grid else None
    pickup, force = [], []
    for l in found:
        f = locate.refine_line(r * pb.use, fs, l["frequency_hz"])
        k = _on_grid(f, grid, T)
        xa, xs = sensor_mod.line_amplitude(r, fs, f, pb.use)
        if a_res is not None:
            aa, asig = sensor_mod.line_amplitude(a_res, fs, f, acc_use)
        else:
            aa, asig = 0j, 0.0
        src, ratio, ev = sensor_mod.classify_line(f, xa, xs, aa, asig, check or sensor_mod.AccelCheck(False))
        if k is not None and k in excited and (not src.startswith("pickup") or not sensor_mod.mains_harmonic(f)):
            continue            # the command's own line: its model error (both sensors see it)
        if k is not None and src == "force":
            near = [j for j in range(max(1, k - int(5 / grid)), k + int(5 / grid) + 1)
                    if j != k and j not in excited]
            idx = [int(round(j * grid * T)) for j in near if int(round(j * grid * T)) < len(R)]
            ref = float(np.median(R[idx])) if idx else 0.0
            if R[int(round(f * T))] < 10 * ref:
                continue                         # one of the distortion lines of the periodic command
        line = sensor_mod.SensorLine(frequency_hz=f, amplitude=abs(xa), phase_rad=float(np.angle(xa)),
                                     channel="position_m", source=src, accel_ratio=ratio, evidence=ev)
        (force if src == "force" else pickup).append(line)
    acc_lines = []
    if a_res is not None:
        an = noise_mod.floor(a_res, fs, acc_use)
        for l in locate.spectral_lines(a_res * acc_use, fs, an.white_rms_m, ratio=LINE_RATIO, top=6):
            f = locate.refine_line(a_res * acc_use, fs, l["frequency_hz"])
            if any(abs(f - x.frequency_hz) < 2.0 / T for x in pickup + force):
                continue
            if _on_grid(f, grid, T) is not None and not sensor_mod.mains_harmonic(f):
                continue
            aa, asig = sensor_mod.line_amplitude(a_res, fs, f, acc_use)
            xa, xs = sensor_mod.line_amplitude(r, fs, f, pb.use)
            x_pred = abs(aa) / ((2 * math.pi * f) ** 2 * abs(check.gain))
            if x_pred > 5 * xs and abs(xa) < 0.2 * x_pred:
                acc_lines.append(sensor_mod.SensorLine(
                    frequency_hz=f, amplitude=abs(aa), phase_rad=float(np.angle(aa)), channel="accel_mps2",
                    source="pickup", accel_ratio=None,
                    evidence=f"line in acceleration ({abs(aa):.3g} m/s^2) but not in position: a force would move "
                             f"the position by {x_pred:.3g} m, it shows {abs(xa):.3g} m (noise {xs:.2g})"))
    return pickup, force, acc_lines


# ---- report helpers ------------------------------------------------------------------------------------------

def _metrics(pb: Problem, yhat: np.ndarray) -> dict:
    r = pb.y - yhat
    u = pb.use

    def nrmse(m):
        yy = pb.y[m]
        return float(np.sqrt(np.sum(r[m] ** 2) / max(np.sum((yy - yy.mean()) ** 2), 1e-300)))
    rr = float(np.sqrt(np.mean(r[u] ** 2)))
    return {"nrmse": nrmse(u), "residual_rms_m": rr, "residual_over_noise": rr / pb.noise,
            "nrmse_fit": nrmse(pb.mfit), "nrmse_holdout": nrmse(pb.mhold),
            "residual_over_noise_fit": float(np.sqrt(np.mean(r[pb.mfit] ** 2)) / pb.noise),
            "residual_over_noise_holdout": float(np.sqrt(np.mean(r[pb.mhold] ** 2)) / pb.noise)}


def _public_params(pb: Problem, name: str, f: Fit) -> dict:
    prm = dict(f.fx.get(name, {}))
    if catalogue.get(name).projected and f.dist is not None:
        fq, a, b = f.dist
        line = pb.force_basis(f.lin, f.fx) @ np.array([a, b])
        tail = line[-max(10, int(pb.fs)):]                      # steady state: the last second
        prm.update(force_n=math.hypot(a, b), phase_rad=math.atan2(b, a),
                   amplitude_m=float(math.sqrt(2.0) * np.sqrt(np.mean(tail ** 2))))
    return {k: float(v) for k, v in prm.items()}


def _evidence(name: str, st: dict, mm: dict, extra: str = "") -> str:
    effect = catalogue.get(name)
    sig = effect.evidence.signature
    h = mm.get("harmonics", {})
    ms = mm.get("multisine_lines", {})
    if effect.nonlinear and h:
        sig += f"; odd harmonics {h.get('odd_over_noise', 0):.0f}x noise, even {h.get('even_over_noise', 0):.0f}x"
    if effect.nonlinear and ms and ms.get("odd_over_noise") is not None:
        sig += (f"; unexcited odd lines of the multisine {ms['odd_over_noise']:.2f}x noise rms ({ms['odd_z']:.0f} "
                f"standard errors above noise alone), even lines {ms.get('even_over_noise') or 0:.2f}x: odd "
                f"distortion" if (ms.get("odd_z") or 0) > 5 else "")
    if extra:
        sig += f"; {extra}"
    return (f"{sig}; fit-block BIC gain {st['delta_bic_fit']:.0f} (needs > 0), held-out log-likelihood "
            f"ratio {st['lr_holdout']:.0f} (needs > {st['lr_needed']:.0f}), held-out residual variance cut by "
            f"{100 * st['holdout_gain']:.1f} % (needs > {100 * MIN_GAIN:.1f} %)")


def _summary_effects(effects: list[dict]) -> str:
    return ", ".join(f"{e['name']} ({', '.join(f'{k}={_fmt(v)}' for k, v in e['parameters'].items())})"
                     for e in effects)


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def _residual_spectra(pb: Problem, models: dict) -> dict:
    """Welch amplitude spectral densities of each residual (m/sqrt(Hz)) and the noise floor."""
    out = {}
    nper = int(min(pb.n, 4 * pb.fs))
    f = np.array([])
    for k, yhat in models.items():
        f, P = welch((pb.y - yhat) * pb.use, fs=pb.fs, nperseg=nper)
        out[k] = np.sqrt(P / max(pb.use.mean(), 1e-6)).tolist()
    out["freqs_hz"] = f.tolist()
    out["noise_asd"] = float(pb.noise / math.sqrt(pb.fs / 2))
    return out


# ---- main entry ------------------------------------------------------------------------------------------------

def _floor(pb: Problem, r: np.ndarray, cmd_info: command_mod.Command) -> noise_mod.NoiseFloor:
    """The noise floor of a residual, the response taken out as the command's kind allows (rig.diagnose.noise)."""
    if cmd_info.kind == "multisine":
        return noise_mod.floor(r, pb.fs, pb.use, period=cmd_info.period)
    if cmd_info.kind in ("noise", "steps") and not _feedback(pb):
        return noise_mod.floor(r * pb.use, pb.fs, pb.use, cmd=pb.cmd)
    return noise_mod.floor(r, pb.fs, pb.use)


def _feedback(pb: Problem) -> bool:
    """The command was computed from the measured position (a plant file's axis under its controller): its
    part coherent with the residual is then the position's noise fed back, not the plant's response, so the noise
    floor is not estimated by removing it. (The eha plant keeps its estimator: its closed-loop recordings get no
    open-loop claim.)"""
    return pb.plant.family != "eha" and pb.loop is not None and pb.loop.closed


def _validate(rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    src = getattr(rec, "source", "recording")
    cmd = np.asarray(rec.valve_cmd_V, dtype=float)
    pos = np.asarray(rec.position_m, dtype=float)
    acc = np.asarray(getattr(rec, "accel_mps2", np.zeros_like(pos)), dtype=float)
    if len(cmd) < 100 or not (np.all(np.isfinite(cmd)) and np.all(np.isfinite(pos)) and np.all(np.isfinite(acc))):
        raise RecordingError(f"{src}: diagnosis needs at least 100 finite samples of valve_cmd_V and position_m")
    check_plausible(rec)
    if np.ptp(cmd) <= 0 or np.ptp(pos) <= 0:
        raise RecordingError(f"{src}: valve_cmd_V or position_m is constant; diagnosis needs an excitation "
                             "(chirp, sweep, multisine, noise or steps) and the position it caused")
    return cmd, pos, acc


def _no_claim_reason(rec, cmd_info: command_mod.Command) -> str:
    if rec.duration_s < MIN_CLAIM_S:
        return (f"the recording is {rec.duration_s:.3g} s long, too short for a claim (at least {MIN_CLAIM_S:g} s "
                f"of excitation are needed)")
    if cmd_info.kind in ("flat", "sine"):
        return (f"the command is a {'constant' if cmd_info.kind == 'flat' else 'single sine'}: too poorly excited "
                f"for a claim (a sweep, multisine, noise or steps are needed)")
    lo, hi = cmd_info.band_hz
    if hi <= 0 or hi < 2.0 * max(lo, 1e-3):
        return f"the command excites only {lo:.3g}-{hi:.3g} Hz: too poorly excited for a claim"
    return ""


def diagnose(rec, p0: ActuatorParams | Plant, *, progress: Callable[[str], None] | None = None,
             seed: int = 0) -> Diagnosis:
    """Diagnose a recording (rig.recording.Recording) against a plant: the nominal ActuatorParams p0 of the eha
    plant, or a Plant of any family (rig.plant, a plant file)."""
    if isinstance(p0, Plant):
        unit = getattr(rec, "command_unit", "V")
        if p0.input_unit != unit:
            raise RecordingError(f"{rec.source}: the command is in {unit} but the plant ({p0.source}) takes "
                                 f"input_unit = {p0.input_unit!r}; check the signal map's command unit or the plant")
        if p0.family == "eha":
            p0 = p0.actuator
    from threadpoolctl import threadpool_limits
    # one BLAS thread: the products here are tall and thin (n x 30), where OpenBLAS's threads only wait for each
    # other (100x slower on a loaded 2-core machine); the two cores go to the simulators instead (lm._POOL)
    with threadpool_limits(1, user_api="blas"):
        return _diagnose(rec, p0, progress=progress, seed=seed)


@dataclass
class _Run:
    """The working state of one diagnosis, handed from stage to stage."""
    rec: object
    p0: ActuatorParams
    say: Callable[[str], None]
    cmd: np.ndarray
    pos: np.ndarray
    acc: np.ndarray
    fs: float
    cmd_info: command_mod.Command
    notes: list[str]
    use: np.ndarray                     # samples every fit uses
    clip: tuple                         # position flat tops: (candidate mask, low level, high level)
    transient_s: float
    pb: Problem
    no_claim: str
    nominal_lin: dict
    band: tuple = (0.0, 0.0)
    nom: Fit | None = None
    refit: Fit | None = None
    current: Fit | None = None          # the model so far; the augmented model at the end
    y_nom: np.ndarray | None = None
    y_ref: np.ndarray | None = None
    y_aug: np.ndarray | None = None
    r_ref: np.ndarray | None = None
    check: sensor_mod.AccelCheck | None = None
    acc_clip: np.ndarray | None = None
    acc_use: np.ndarray | None = None
    acc_model: np.ndarray | None = None
    pickup: list = field(default_factory=list)          # SensorLine on the position
    acc_pickup: list = field(default_factory=list)      # SensorLine on the accelerometer
    lines: list = field(default_factory=list)           # force lines (dicts), disturbance candidates
    q: float = 0.0
    q_acc: float = 0.0
    floor_ref: noise_mod.NoiseFloor | None = None
    floor_aug: noise_mod.NoiseFloor | None = None
    mm: dict = field(default_factory=dict)
    nonlinear_hint: bool | None = None
    chosen: list = field(default_factory=list)
    tried: list = field(default_factory=list)
    groups: list = field(default_factory=list)
    stats_of: dict = field(default_factory=dict)
    round1: dict = field(default_factory=dict)          # name -> Fit: each candidate alone (the first round)
    frf: dict = field(default_factory=dict)
    fit: dict = field(default_factory=dict)


def _diagnose(rec, p0: ActuatorParams, *, progress: Callable[[str], None] | None = None, seed: int = 0) -> Diagnosis:
    t_start = time.perf_counter()
    R = _prepare(rec, p0, progress or (lambda msg: None))
    _refit(R)
    _screen(R)
    _search(R)
    _final_lines(R)
    if _pairs(R):
        _final_lines(R)
    _locate_mismatch(R)
    return _conclude(R, _sensor_terms(R), t_start)


def _prepare(rec, p0: ActuatorParams, say: Callable[[str], None]) -> _Run:
    """Read the command and choose the samples every fit leaves out (clipped, the start transient)."""
    cmd, pos, acc = _validate(rec)
    fs = float(rec.fs_hz)
    notes: list[str] = []
    say("reading the command")
    cmd_info = command_mod.analyse(cmd, fs, unit=getattr(rec, "command_unit", "V"))
    notes.append(f"command: {cmd_info.describe()}")
    plant = model_for(p0)
    if fs < 500.0 and plant.family == "eha":
        notes.append(f"sampled at {fs:g} Hz, below the 500 Hz the valve's dynamics (~{p0.w_nv / 2 / math.pi:.0f} Hz)"
                     " need to be seen")
    if plant.segmented:
        notes.append("the plant has a pole at the origin (it integrates: marginally stable), so simulated open loop "
                     "from the recorded command its position drifts; it is simulated segment-wise instead, each "
                     "segment from its own initial state (multiple shooting)")
    use = np.ones(len(cmd), bool)
    clip_cand, clip_lo, clip_hi = sensor_mod.flat_tops(pos)
    if clip_cand.any():
        use &= ~np.convolve(clip_cand, np.ones(3), "same").astype(bool)
    transient_s = 0.05                          # start-up instants carry no information
    if cmd_info.starts_mid_run and not plant.segmented:     # segments start from their own estimated states
        transient_s = START_TRANSIENT_S
        notes.append(f"the command is {cmd_info.start_V:.3g} {getattr(rec, 'command_unit', 'V')} at the first sample, so the plant was not at rest "
                     f"when the recording began (a mid-run start): the first {transient_s:g} s are left out of the "
                     f"fit (the start transient)")
    use[: int(transient_s * fs)] = False
    if use.sum() < 50:
        raise RecordingError(f"{rec.source}: fewer than 50 usable samples after the start transient and the "
                             "clipped samples")
    pb = Problem(cmd, pos, fs, p0, use)
    pb.broadband = cmd_info.kind in ("noise", "steps")
    if plant.family != "eha":
        pb.loop = closedloop.check(cmd, pos, fs, getattr(rec, "meta", None), stated=getattr(rec, "closed_loop", ""))
    return _Run(rec=rec, p0=p0, say=say, cmd=cmd, pos=pos, acc=acc, fs=fs, cmd_info=cmd_info, notes=notes, use=use,
                clip=(clip_cand, clip_lo, clip_hi), transient_s=transient_s, pb=pb,
                no_claim=_no_claim_reason(rec, cmd_info), nominal_lin=dict(pb.nominal))


def _excited_band(R: _Run) -> tuple[float, float]:
    """The band the command excites; the stand mode is looked for where the command excites the plant: a sweep's
    or multisine's band; for a broadband command (noise, steps) wherever its spectrum is within 60 dB of its peak."""
    cmd_info, pb = R.cmd_info, R.pb
    band = cmd_info.band_hz if cmd_info.band_hz[1] > 0 else (1.0, 0.45 * R.fs)
    b_hi = band[1] if cmd_info.kind in ("sweep", "multisine") else max(band[1], cmd_info.wide_band_hz[1])
    pb.base_band = (max(5.0, 1.1 * band[0]), max(min(0.97 * b_hi, 0.45 * R.fs), 6.0))
    if pb.base_band[1] <= pb.base_band[0]:
        pb.base_band = (5.0, max(6.0, 0.45 * R.fs))
    return band


def _refit(R: _Run) -> None:
    """Nominal model, refit of the linear parameters, and the sensor terms found on the way: slow wander, the
    accelerometer's check, pickup told from force lines by the two sensors, the converter step."""
    pb, cmd_info, fs = R.pb, R.cmd_info, R.fs
    R.say("nominal model")
    nom = pb.evaluate(R.nominal_lin, {}, k=0)
    pb.noise = _floor(pb, pb.y - pb.series(nom), cmd_info).rms_m or 1e-12
    R.say("refit of the linear parameters")
    refit = pb.fit(R.nominal_lin, {}, max_iter=10)
    R.band = band = _excited_band(R)
    R.say("sensor terms")
    # a noise or steps command excites from DC on: no band edge to keep the wander below; the BIC decides
    f_lo = 4.0 * sensor_mod.WANDER_MAX_HZ if pb.broadband else max(band[0], 1.0 / max(R.rec.duration_s, 1e-3))
    wander_max = min(sensor_mod.max_wander_terms(R.rec.duration_s, f_lo),
                     N_BLOCKS // 4)     # a cosine spans at least four blocks: it interpolates over a held-out one
    if pb.shoot is not None:
        wander_max = 0                  # the segments' initial states hold the zero
    k_w = _choose_wander(pb, refit, wander_max)
    if k_w:
        pb.set_basis(pb.basis.with_(wander_terms=k_w))
        refit = pb.evaluate(refit.lin, {}, refit.k)       # polished once, below, with the lines
    r_ref0 = pb.y - pb.series(refit)
    pb.noise = _floor(pb, r_ref0, cmd_info).rms_m or pb.noise
    R.acc_clip = sensor_mod.flat_tops(R.acc)[0] if np.ptp(R.acc) > 0 else np.zeros(pb.n, bool)
    R.acc_use = R.use & ~R.acc_clip
    R.check = sensor_mod.accel_check(pb.y - pb.basis.zero(refit.coef), R.acc, fs,
                                     (band[0], max(band[1], cmd_info.wide_band_hz[1])), R.acc_use)
    R.acc_model = pb.plant.accel(refit.lin, R.cmd, fs) if R.check.usable else None
    R.pickup, force_lines, R.acc_pickup = _lines(pb, r_ref0, R.acc, R.acc_model, R.check, fs, cmd_info, R.acc_use)
    if R.pickup:
        pb.set_basis(pb.basis.with_(lines_hz=tuple(l.frequency_hz for l in R.pickup)))
    if R.pickup or k_w:
        refit = pb.fit(refit.lin, {}, max_iter=4)
    R.nom, R.refit = pb.evaluate(R.nominal_lin, {}, k=0), refit
    R.y_nom, R.y_ref = pb.series(R.nom), pb.series(refit)
    R.r_ref = pb.y - R.y_ref
    R.floor_ref = _floor(pb, R.r_ref, cmd_info)
    pb.noise = R.floor_ref.rms_m or pb.noise
    R.q = noise_mod.quantisation_step(R.pos)
    R.q_acc = noise_mod.quantisation_step(R.acc) if np.ptp(R.acc) > 0 else 0.0
    if R.q > 0:
        pb.noise = max(pb.noise, R.q / math.sqrt(12.0))
    R.lines = [{"frequency_hz": l.frequency_hz, "amplitude_m": l.amplitude, "accel_ratio": l.accel_ratio,
                "evidence": l.evidence} for l in sorted(force_lines, key=lambda l: -l.amplitude)]


def _distortion(R: _Run, r_harm: np.ndarray, x_multi: np.ndarray) -> tuple[str | None, dict | None, bool | None]:
    """Nonlinear distortion the command's own structure shows: a sweep's harmonics in r_harm, or a multisine's
    unexcited lines in x_multi. (mismatch key, measurement, distortion above the screen); None when the command
    has neither (or the multisine's lines could not be read)."""
    if command_mod.harmonic_window_ok(R.cmd_info):
        h = locate.harmonics(r_harm * R.use, R.cmd_info.phase, R.fs, R.pb.noise)
        return "harmonics", h, h["odd_over_noise"] > HARMONIC_SCREEN
    if R.cmd_info.kind == "multisine":
        ms = locate.multisine_lines(R.cmd_info, x_multi, R.use, R.floor_ref, [l["frequency_hz"] for l in R.lines])
        vals = [v for v in (ms.get("odd_z"), ms.get("even_z")) if v is not None]
        return "multisine_lines", ms, (bool(vals) and max(vals) > 2 * HARMONIC_SCREEN) if ms else None
    return None, None, None


def _screen(R: _Run) -> None:
    """What the refit leaves: lines, distortion; and whether the recording is excited enough for a claim."""
    pb = R.pb
    R.say("locating the mismatch")
    R.mm = {"uncorrelated": {"lines": R.lines, "pickup": [l.as_dict() for l in R.pickup + R.acc_pickup]},
            "command": {"kind": R.cmd_info.kind, "description": R.cmd_info.describe(),
                        "band_hz": [float(R.band[0]), float(R.band[1])]}}
    key, d, R.nonlinear_hint = _distortion(R, R.r_ref, pb.y - pb.basis.B @ R.refit.coef)
    if d:
        R.mm[key] = d
    moved = (pb.y - pb.basis.zero(R.refit.coef) - pb.basis.B[:, pb.basis.n_zero:] @
             R.refit.coef[pb.basis.n_zero:])[R.use]
    snr = float(np.std(moved) / pb.noise) if pb.noise > 0 else 0.0
    if not R.no_claim and snr < MIN_SNR:
        R.no_claim = (f"the position moves only {snr:.1f}x its noise (beyond the sensor's zero and lines): too "
                      "poorly excited for a claim")


def _search(R: _Run) -> None:
    """Forward selection of at most MAX_EFFECTS catalogue effects (the protocol above)."""
    pb = R.pb
    R.current = R.refit
    if R.no_claim:
        R.say(f"no claim: {R.no_claim}")
        return
    screen = [n for n, e in pb.plant.effects.items() if not e.projected or R.lines]
    harmonic_now = True if R.nonlinear_hint is None else R.nonlinear_hint
    # a broadband command's nonlinear distortion is not coherent with it and counts in its noise floor: there,
    # no round is skipped for having reached "the noise"
    stop_at_noise = R.cmd_info.kind not in ("noise", "steps")
    round1: dict[str, dict] = {}
    for step in range(MAX_EFFECTS):
        over = math.sqrt(R.current.rss_hold / max(pb.mhold.sum(), 1)) / pb.noise
        explained = EXPLAINED_SLOW if catalogue.slow_in(R.current.fx) else EXPLAINED
        R.say(f"round {step + 1}: held-out residual {over:.3f} x noise")
        results = _round(R, screen, harmonic_now, stop_at_noise and over < explained, explained, round1)
        if not R.chosen:
            round1 = {n_: dict(g.fx[n_]) for n_, g, _ in results if n_ in g.fx}
            R.round1 = {n_: g for n_, g, _ in results if n_ in g.fx}
        ok = sorted((r for r in results if r[2]["passed"]), key=lambda r: r[1].rss_hold)
        if not ok:
            break
        name, f, st = ok[0]
        nh = int(pb.mhold.sum())
        conf = [n_ for n_, g, s in ok[1:] if nh * math.log(g.rss_hold / f.rss_hold) < math.log(nh)]
        if conf:
            R.groups.append([name] + conf)
        R.chosen.append(name)
        R.stats_of[name] = st
        R.say(f"polishing {'+'.join(R.chosen)}")
        R.current = _polish(pb, f)
        r_cur = pb.y - pb.series(R.current)
        key, _, now = _distortion(R, r_cur, r_cur)       # distortion the current model leaves
        if key:
            harmonic_now = bool(now)
        if catalogue.get(name).projected and name in screen:
            screen.remove(name)         # one line at a time
    if getattr(pb.plant, "axis_search", False):
        # the polish frees everything at once: an effect it made inactive (a deadband polished to width 0 once
        # friction came in beside it) is no longer a finding
        for name in list(R.chosen):
            if not _active(pb, R.current, name):
                fx = {k: v for k, v in R.current.fx.items() if k != name}
                R.current = pb.evaluate(R.current.lin, fx, pb.n_params(fx))
                R.chosen.remove(name)
                R.stats_of.pop(name, None)
                R.groups = [g for g in R.groups if g[0] != name]


def _pairs(R: _Run) -> bool:
    """The pair step: a second chance for a recording the forward selection leaves above the noise (its verdict
    would not be "explained"). Two effects can hide each other: Coulomb friction and a deadband both stop
    the motion near zero force, friction and a saturation or a delay both bend the closed loop's moves, so each
    alone takes part of the other's share and the first one chosen spoils the start of the second. Every pair of
    the one-parameter candidates is therefore fitted jointly from the two effects' own first-round fits. A pair
    replaces the selection's model only when it passes the same tests as any effect: it beats that model (BIC on
    the fit blocks, likelihood ratio and gain on the held-out blocks), and EACH of its effects beats the pair's
    other effect alone, refitted (and is active: taking it out of the pair loses the margin). True when a pair
    was taken."""
    pb = R.pb
    if not getattr(pb.plant, "axis_search", False) or R.no_claim or len(R.round1) < 2:
        return False
    nh = max(int(pb.mhold.sum()), 1)
    if math.sqrt(R.current.rss_hold / nh) / pb.noise <= VERDICT_AT_NOISE:
        return False
    names = [n for n, e in pb.plant.effects.items() if n in R.round1 and not e.projected
             and len(pb.spec_keys(n)) == 1]
    fits = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            fa, fb = R.round1[a], R.round1[b]
            fx0 = {a: dict(fa.fx[a]), b: dict(fb.fx[b])}
            slow = catalogue.slow_in(fx0)
            R.say(f"pair {a}+{b}")
            f = pb.fit(min((fa, fb), key=lambda g: g.rss_fit).lin, fx0, max_iter=10,
                       rtol=SLOW_RTOL if slow else 1e-5)
            st = compare(pb, R.current, f)
            R.tried.append({"effects": [a, b], "step": "pair", "rss_fit": f.rss_fit, "rss_holdout": f.rss_hold,
                            **st})
            if st["passed"]:
                fits.append((f.rss_hold, a, b, f))
    for _, a, b, f in sorted(fits, key=lambda x: x[0]):
        stats = {}
        for x, other in ((a, b), (b, a)):
            if not _active(pb, f, x):
                break
            slow = catalogue.get(other).slow
            alone = pb.fit(f.lin, {other: dict(f.fx[other])}, max_iter=6 if slow else 10,
                           rtol=SLOW_RTOL if slow else 1e-5)
            st = compare(pb, alone, f)
            if not st["passed"]:
                break
            stats[x] = st
        if len(stats) == 2:
            R.say(f"pair {a}+{b} taken")
            R.chosen, R.stats_of, R.current = [a, b], stats, f
            R.groups = [g for g in R.groups if set(g) <= {a, b}]
            return True
    return False


def _round(R: _Run, screen: list[str], harmonic_now: bool, at_noise: bool, explained: float,
           round1: dict) -> list[tuple[str, Fit, dict]]:
    """One round of the forward selection: each screened candidate on top of the current model, tested."""
    pb, current, chosen = R.pb, R.current, R.chosen
    results: list[tuple[str, Fit, dict]] = []
    # the measurement without its sensor terms and without the fitted disturbance's response
    y_clean = pb.y - pb.basis.B @ current.coef - (pb.physics(current) - pb.model(current.lin, current.fx))
    base, null = current, None
    for name in screen:
        if name in chosen:
            continue
        effect = catalogue.get(name)
        if not effect.projected and at_noise and not (harmonic_now and effect.nonlinear):
            continue        # the held-out residual is already at the noise: nothing left to explain
        R.say(f"candidate {'+'.join(chosen + [name])}")
        lins = [current.lin] if chosen else [R.refit.lin, R.nominal_lin]
        floor_ = [g.rss_fit for _, g, _ in results if math.sqrt(g.rss_hold / pb.mhold.sum()) / pb.noise < explained]
        slow_name = effect.slow
        if floor_ and slow_name and not harmonic_now:
            continue        # a cheap candidate already reached the noise and nothing calls for these
        pb.quick = not harmonic_now
        skip = None
        if slow_name and results:  # a slow model is refined only when its best start rivals the best
            skip = 2.0 * min(g.rss_fit for _, g, _ in results)
        if floor_:
            skip = 2.0 * min(floor_)
        if not harmonic_now:       # without distortion a nonlinearity must at least show in its start
            skip = min(skip or np.inf, (0.95 if slow_name else 0.999) * current.rss_fit)
        prior = round1.get(name) if chosen else None
        f = _fit_candidate(pb, name, lins, current.fx, R.band, R.lines, y_clean, second=bool(chosen),
                           skip_above=skip, prior=prior if not effect.projected else None)
        if f is None:
            continue
        f = _refine_disturbance(pb, f)
        st = compare(pb, base, f)
        if st["passed"] and chosen and catalogue.slow_in(current.fx) and null is None:
            # a slow model's polish may stop short: a candidate must beat the current model given the same
            # extra iterations, not the extra iterations themselves (fitted once, when needed)
            null = pb.fit(current.lin, current.fx, max_iter=6, rtol=SLOW_RTOL)
            if null.rss_fit < base.rss_fit:
                base = null
                st = compare(pb, base, f)
        if st["passed"] and not _active(pb, f, name):
            st = {**st, "passed": False, "inactive": True}
        if st["passed"] and getattr(pb.plant, "axis_search", False) and _at_edge(pb, f, name):
            st = {**st, "passed": False, "at_edge": True}
        R.tried.append({"effects": chosen + [name], "rss_fit": f.rss_fit, "rss_holdout": f.rss_hold, **st})
        results.append((name, f, st))
    return results


def _final_lines(R: _Run) -> None:
    """Lines the distortion of the refit residual hid: pickup found now joins the sensor terms (every model is
    re-evaluated with it; the physics parameters stay). Then the noise floor of the augmented residual."""
    pb, aug = R.pb, R.current
    pb.noise = min(pb.noise, _floor(pb, pb.y - pb.series(aug), R.cmd_info).rms_m or pb.noise)
    more, _, _ = _lines(pb, pb.y - pb.series(aug), R.acc, R.acc_model, R.check, R.fs, R.cmd_info, R.acc_use)
    more = [l for l in more if all(abs(l.frequency_hz - x) > 2.0 / R.rec.duration_s for x in pb.basis.lines_hz)]
    if more:
        R.pickup += more
        pb.set_basis(pb.basis.with_(lines_hz=pb.basis.lines_hz + tuple(l.frequency_hz for l in more)))
        R.nom = pb.evaluate(R.nom.lin, R.nom.fx, R.nom.k)
        R.refit = pb.evaluate(R.refit.lin, R.refit.fx, R.refit.k)
        R.current = pb.evaluate(aug.lin, aug.fx, aug.k)
        R.y_nom, R.y_ref = pb.series(R.nom), pb.series(R.refit)
        R.r_ref = pb.y - R.y_ref
    R.y_aug = pb.series(R.current)
    R.floor_aug = _floor(pb, pb.y - R.y_aug, R.cmd_info)
    pb.noise = min(pb.noise, max(R.floor_aug.rms_m, R.q / math.sqrt(12.0) if R.q else 0.0)) or pb.noise


def _locate_mismatch(R: _Run) -> None:
    """Where the mismatch lives (bands, windows, regimes) for each model, and the fit figures."""
    pb, use, aug = R.pb, R.use, R.current
    B = pb.basis.B
    y_nom, y_ref, y_aug, r_ref = R.y_nom, R.y_ref, R.y_aug, R.r_ref
    R.frf = locate.frf_bands(pb.cmd * use, (pb.y - B @ aug.coef) * use,
                             {"nominal": (y_nom - B @ R.nom.coef) * use, "refit": (y_ref - B @ R.refit.coef) * use,
                              "augmented": (y_aug - B @ aug.coef) * use}, R.fs, *R.band)
    wins, worst, _ = locate.mismatch_windows((pb.y - y_nom) * use, R.fs, pb.noise)
    wins_r, worst_r, _ = locate.mismatch_windows(r_ref * use, R.fs, pb.noise)
    _, worst_a, _ = locate.mismatch_windows((pb.y - y_aug) * use, R.fs, pb.noise)
    R.mm.update({
        "bands_hz": locate.mismatch_bands(R.frf, "nominal"),
        "windows_s": wins,
        "after_refit": {"bands_hz": locate.mismatch_bands(R.frf, "refit"), "windows_s": wins_r},
        "after_augmented": {"bands_hz": locate.mismatch_bands(R.frf, "augmented")},
        "regimes": locate.regimes(pb.cmd, pb.y - B @ R.refit.coef, r_ref, R.fs, pb.noise, use),
        "worst_windows": {"nominal": worst, "refit": worst_r, "augmented": worst_a},
        "chirp_band_hz": [float(R.band[0]), float(R.band[1])],
    })
    R.mm["uncorrelated"]["fraction_of_refit_residual_in_lines"] = float(
        sum(l["amplitude_m"] ** 2 / 2 for l in R.lines) / max(np.mean(r_ref[use] ** 2), 1e-300)) if R.lines else 0.0
    R.fit = {"nominal": _metrics(pb, y_nom), "refit": _metrics(pb, y_ref), "augmented": _metrics(pb, y_aug)}
    m_sensor = pb.basis.m
    for m, k in (("nominal", 0), ("refit", R.refit.k), ("augmented", aug.k)):
        R.fit[m]["n_parameters"] = k + m_sensor
        R.fit[m]["n_sensor_parameters"] = m_sensor


def _clips(R: _Run) -> list[sensor_mod.Clip]:
    """Flat tops of the position that the refit goes beyond (a converter's range), and of the accelerometer."""
    pb, pos, fs = R.pb, R.pos, R.fs
    clip_cand, clip_lo, clip_hi = R.clip
    clips = []
    if clip_cand.any():
        pred = pb.series(R.refit)
        for lvl, side in ((clip_hi, 1), (clip_lo, -1)):
            if lvl is None:
                continue
            at = clip_cand & ((pos >= lvl - 1e-9 * abs(lvl)) if side > 0 else (pos <= lvl + 1e-9 * abs(lvl)))
            beyond = float(np.mean((pred[at] - lvl) * side)) if at.any() else 0.0
            if beyond > max(3 * pb.noise, R.q):
                clips.append(sensor_mod.Clip("position_m", lvl if side < 0 else None, lvl if side > 0 else None,
                                             int(at.sum()), float(np.argmax(at) / fs)))
        if clips:
            R.notes.append("position clipped at " + ", ".join(
                f"{(c.high if c.high is not None else c.low):.4g} m ({c.samples} samples, first at {c.first_s:.3f} s)"
                for c in clips) + ": the clipped samples are left out of the fit")
    if R.acc_clip.any():
        clips.append(sensor_mod.Clip("accel_mps2", float(np.min(R.acc)), float(np.max(R.acc)),
                                     int(R.acc_clip.sum()), float(np.argmax(R.acc_clip) / fs)))
        R.notes.append(f"accelerometer flat at its range in {int(R.acc_clip.sum())} samples: left out of the line "
                       "tests")
    return clips


def _sensor_terms(R: _Run) -> sensor_mod.SensorTerms:
    """The sensor terms of the augmented model, the accelerometer's offset and the odd samples."""
    pb, acc, check, q = R.pb, R.acc, R.check, R.q
    terms = pb.basis.terms(R.current.coef)
    for l, (f_, a_, ph_) in zip(R.pickup, terms["lines"]):
        l.amplitude, l.phase_rad = a_, ph_
    acc_off = None
    if np.ptp(acc) > 0:
        am = R.acc_model if R.acc_model is not None else 0.0
        acc_off = float(np.mean((acc - (check.gain.real * am if check.usable else 0.0))[R.acc_use]))
    sensor = sensor_mod.SensorTerms(
        offset_m=terms["offset_m"], drift_m_per_s=terms["drift_m_per_s"], wander_terms=pb.basis.wander_terms,
        wander_rms_m=terms["wander_rms_m"], lines=R.pickup + R.acc_pickup, accel_offset_mps2=acc_off, accel=check,
        quantisation_step_m=q, accel_quantisation_step_mps2=R.q_acc, clipped=_clips(R),
        start_transient_s=R.transient_s if R.cmd_info.starts_mid_run else 0.0, notes=[])
    if pb.shoot is not None:
        sensor.notes.append("no offset or drift is fitted: the segment-wise initial states hold the transducer's zero")
    if q > 0:
        sensor.notes.append(f"position quantised in steps of {q:.3g} m: a noise floor of {q / math.sqrt(12):.3g} m rms "
                            f"(step/sqrt(12)); residual structure below it means nothing")
    if check.note:
        sensor.notes.append(check.note)
    return sensor


def _conclude(R: _Run, sensor: sensor_mod.SensorTerms, t_start: float) -> Diagnosis:
    """The named effects with their evidence, the verdict and the summary."""
    pb, mm, fit, augmented = R.pb, R.mm, R.fit, R.current
    effects = []
    for name in R.chosen:
        st = R.stats_of[name]
        extra = R.lines[0]["evidence"] if catalogue.get(name).projected and R.lines else ""
        effects.append({"name": name, "parameters": _public_params(pb, name, augmented),
                        "evidence": _evidence(name, st, mm, extra), "score": float(st["lr_holdout"])})
    verdict = _verdict(pb, R.rec, R.no_claim, effects, fit, R.refit, R.cmd_info, R.check, R.use, R.r_ref)
    if verdict.status == "not_described" and effects:
        mm["not_claimed"] = [{"name": e["name"], "parameters": e["parameters"]} for e in effects]
        effects = []
    what = _summary_effects(effects) if effects else "none"
    held = {m: fit[m]["residual_over_noise_holdout"] for m in ("nominal", "refit", "augmented")}
    summary = (f"{verdict.text} Missing physics: {what}. Held-out residual/noise nominal {held['nominal']:.1f}, "
               f"refit {held['refit']:.1f}, augmented {held['augmented']:.2f} (noise {pb.noise:.2g} m). "
               f"Mismatch vs nominal in {len(mm['bands_hz'])} band(s), after refit in "
               f"{len(mm['after_refit']['bands_hz'])}.")
    if R.groups and effects:
        summary += " Confounded: " + "; ".join(" ~ ".join(g) for g in R.groups) + "."
    sens_txt = _sensor_summary(sensor) if verdict.status != "not_described" else ""
    if sens_txt:
        summary += f" Sensor terms (not physics): {sens_txt}."
    for s in verdict.suggestions:
        summary += f" {s}"
    frf_out = {k: (v.tolist() if not np.iscomplexobj(v) else {"re": v.real.tolist(), "im": v.imag.tolist()})
               for k, v in R.frf.items()}
    frf_out["residual_spectra"] = _residual_spectra(pb, {"nominal": R.y_nom, "refit": R.y_ref,
                                                         "augmented": R.y_aug})
    ev = evidence_mod.collect(pb, R.cmd_info, R.refit, augmented, effects, sensor, R.acc, R.acc_use, R.check,
                              R.acc_model, R.floor_aug)
    series = {"nominal_m": R.y_nom, "refit_m": R.y_ref, "augmented_m": R.y_aug,
              "augmented_sensor_m": pb.basis.B @ augmented.coef}
    mm["notes"] = R.notes
    return Diagnosis(effects=effects, group=R.groups if effects else [], mismatch=mm, fit=fit,
                     params_refit=pb.plant.public_linear(R.refit.lin),
                     noise_m=float(pb.noise), summary=summary, series=series, frf=frf_out, candidates=R.tried,
                     timing_s=time.perf_counter() - t_start, sensor=sensor, command=R.cmd_info, verdict=verdict,
                     evidence=ev, used=R.use, noise_floor=R.floor_aug, plant=_plant_doc(pb, augmented))


def _plant_doc(pb: Problem, augmented: Fit) -> dict:
    """What diagnosis.json says of the plant: its family, the command's unit, the linear parameters of the
    augmented model, and the segment-wise initial states when the plant integrates."""
    doc = {"family": pb.plant.family, "input_unit": pb.plant.input_unit,
           "free_parameters": list(pb.lin_keys),
           "augmented_linear": pb.plant.public_linear(augmented.lin)}
    if pb.shoot is not None:
        doc["shooting"] = pb.shoot.as_dict(pb.fs)
    return doc


def _sensor_summary(s: sensor_mod.SensorTerms) -> str:
    parts = [f"offset {s.offset_m * 1e6:.3g} um", f"drift {s.drift_m_per_s * 1e9:.3g} nm/s"] \
        if (s.offset_m or s.drift_m_per_s) else []     # none: the segment-wise initial states hold the zero
    if s.wander_terms:
        parts.append(f"slow wander {s.wander_rms_m * 1e9:.3g} nm rms")
    for l in s.lines:
        unit = "nm" if l.channel == "position_m" else "mm/s^2"
        scale = 1e9 if l.channel == "position_m" else 1e3
        parts.append(f"{l.source} line {l.frequency_hz:.2f} Hz on {l.channel} ({l.amplitude * scale:.3g} {unit})")
    if s.quantisation_step_m:
        parts.append(f"quantisation step {s.quantisation_step_m:.3g} m")
    for c in s.clipped:
        parts.append(f"{c.channel} clipped ({c.samples} samples)")
    return ", ".join(parts)


def _file_bound_hints(pb, refit) -> list[str]:
    """A plant file's free parameters the refit left at a bound of their range. A bound of zero reached is the data
    asking for no such term (a pure integrator has no den[-1]), not a different plant: said so."""
    hints = []
    for k, edge in at_bounds(pb.plant.bounds_lin, refit.lin, pb.lin_keys).items():
        lo, hi = pb.plant.bounds_lin[k]
        v = refit.lin[k]
        if edge == 0.0:
            hints.append(f"The refit took {k} to 0, the bound of its range in the plant file ({lo:g}..{hi:g}): the "
                         f"data ask for no such term; fix {k} = 0 in the plant file if that is the physics.")
        else:
            hints.append(f"The refit pushed {k} to {v:.4g}, the {'lower' if edge == lo else 'upper'} bound of its "
                         f"range in the plant file ({lo:g}..{hi:g}): widen the range if that value is plausible, "
                         f"else the plant (or its units) differs from the file's.")
    return hints


def _verdict(pb: Problem, rec, no_claim: str, effects: list[dict], fit: dict, refit: Fit, cmd_info, check,
             use: np.ndarray, r_ref: np.ndarray) -> Verdict:
    """Say whether the models describe the recording, and if not, what the evidence suggests. Closed-loop data
    is named whatever the verdict: the fits assume the command is independent of the noise."""
    sugg = []
    loop = pb.loop or closedloop.check(pb.cmd, pb.y, pb.fs, getattr(rec, "meta", None),
                                       stated=getattr(rec, "closed_loop", ""))
    if loop.closed and pb.plant.family == "eha":
        sugg.append(f"Closed-loop data: {loop.reason}; a fit of the open-loop plant from command to position does "
                    "not apply (identify the plant from an open-loop run, e.g. `rig chirp`).")
    elif loop.closed:
        sugg.append(f"Closed-loop data: {loop.reason}. The plant is simulated from the recorded command (what the "
                    "drive received), so the claims stand, but the command carries the position's noise back in: "
                    "the linear parameters can lean toward the controller's inverse, and only effects that predict "
                    "the held-out blocks are named.")
    if no_claim:
        return Verdict("no_claim", f"No claim: {no_claim}.", sugg)
    over = fit["augmented"]["residual_over_noise_holdout"]
    over_ref = fit["refit"]["residual_over_noise_holdout"]
    if over <= VERDICT_AT_NOISE:
        if effects:
            return Verdict("explained", f"The augmented model explains the recording (residual {over:.2f}x noise).",
                           sugg)
        return Verdict("explained", f"The refit of the linear parameters explains the recording (residual "
                                    f"{over:.2f}x noise).", sugg)
    if pb.plant.family == "eha":
        at_edge = [k for k in pb.lin_keys
                   if min(abs(math.log(refit.lin[k] / pb.nominal[k]) - math.log(b)) for b in LIN_BOUNDS) < 0.02]
        if at_edge:
            sugg.append("The refit pushed " + ", ".join(at_edge) + " to the edge of the physical range: a "
                        "different plant (or different units) than the configured model.")
    else:
        sugg += _file_bound_hints(pb, refit)
    if fit["refit"]["nrmse"] > 0.5:
        sugg.append(f"Even the refit leaves {100 * fit['refit']['nrmse']:.0f} % of the motion unexplained: the "
                    "position does not follow the command as this plant would.")
    if check is not None and not check.usable:
        sugg.append(check.note[0].upper() + check.note[1:] + ".")
    if pb.fs < 500.0 and pb.plant.family == "eha":
        sugg.append(f"The recording is sampled at {pb.fs:g} Hz, too slowly for the valve's dynamics.")
    if over > VERDICT_NOT_DESCRIBED:
        return Verdict("not_described",
                       f"The model does not describe this recording: neither the refit ({over_ref:.1f}x noise) nor "
                       f"the catalogue effects ({over:.1f}x noise) bring the residual near the noise, so no effect "
                       f"is named.", sugg)
    return Verdict("partly", f"The augmented model explains the recording only in part: the residual stays "
                             f"{over:.2f}x the noise (something outside the catalogue remains).", sugg)

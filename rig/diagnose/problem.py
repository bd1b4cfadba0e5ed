"""The fitting problem of one recording: the recorded command and position, the samples every fit uses, the
interleaved fit and held-out blocks, the sensor terms projected out of every residual (variable projection), the
noise the residuals are weighed by, and for a plant that integrates the segment-wise initial states (multiple
shooting, docs/PLANT.md). A Problem is built whole by its constructor; a changed noise estimate, sensor basis or
superposition proxy is a new Problem (`with_`), never an attribute set from outside.

`ModelFit` is one model fitted to it (linear parameters, effects, residual sums of squares); `compare` is the test
every effect passes: BIC on the fit blocks and a likelihood ratio on the held-out blocks.
"""
from __future__ import annotations

import copy
import math
import threading
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve, lu_factor, lu_solve

from rig.diagnose import catalogue, sensor as sensor_mod
from rig.diagnose.lm import lm_fit
from rig.diagnose.plants import model_for

LIN_BOUNDS = (0.7, 1.4)            # x nominal: physically bounded refit (recordings move them +-15 %)
N_BLOCKS = 51                      # interleaved blocks (2 s blocks of a 100 s chirp); odd: the first and the last
                                   # are fit blocks, so the slow sensor terms never extrapolate into a held-out end
MIN_GAIN = 0.003                   # an effect must cut the held-out residual variance by at least 0.3 %
_KEEP = object()


@dataclass
class ModelFit:
    """One model fitted to the problem."""
    lin: dict                     # linear parameter values
    fx: dict                      # effects {name: {key: value}} (disturbance: frequency_hz only)
    rss_fit: float
    rss_hold: float
    k: int                        # number of fitted physics parameters
    dist: tuple | None = None     # (freq, coef_sin, coef_cos)
    coef: np.ndarray | None = None   # sensor-basis coefficients
    state: np.ndarray | None = None  # segment-wise initial states' response (multiple shooting), metres
    tau: float = 1.0              # correlation time of its held-out residual, samples (1: white; eha: not measured)


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
SHOOT_GN_STEPS = 2                 # Gauss-Newton steps on the segment states of a model nonlinear in them: slow
SHOOT_GN_PLAY_STEPS = 40           # ... a fast one with a play (the load answers a drive's state only outside the play,
                                   # so each step corrects a part; ~4 ms a step on 12 s at 1 kHz). Friction beside a
                                   # play keeps SHOOT_GN_STEPS: each of its steps is a friction simulation
SHOOT_GN_SETTLED = 0.1             # the steps stop once no segment's start moves by more than this share of the noise
SHOOT_GN_GAIN = 1.0                # ... or once a step lowers the fit blocks' rss by less than noise^2 (a chi^2 of 1)
SHOOT_AITKEN_COS = 0.99            # a play's steps extrapolated where two successive ones point the same way ...
SHOOT_AITKEN_RHO = 0.95            # ... by at most 1 / (1 - 0.95) = 20 x


def _aitken(dX: np.ndarray, last: np.ndarray, O: np.ndarray) -> np.ndarray:
    """Per segment, the factor that takes a state step to the end of its series where the steps shrink
    geometrically (a play answers each correction only in part: step k+1 = rho step k, the rest of the series
    step rho / (1 - rho), Aitken's extrapolation): 1 / (1 - rho) where two successive steps point the same way
    (their responses' cosine above SHOOT_AITKEN_COS) and 0 < rho < 1, at most 1 / (1 - SHOOT_AITKEN_RHO); else 1.
    The response norm: the segment states' output over a segment (O's rows)."""
    W = O.T @ O
    num = np.einsum("si,ij,sj->s", dX, W, last)
    a = np.einsum("si,ij,sj->s", last, W, last)
    b = np.einsum("si,ij,sj->s", dX, W, dX)
    den = np.sqrt(np.maximum(a * b, 1e-300))
    rho = num / np.maximum(a, 1e-300)
    ok = (num / den > SHOOT_AITKEN_COS) & (rho > 0.0) & (rho < 1.0)
    return np.where(ok, 1.0 / (1.0 - np.minimum(rho, SHOOT_AITKEN_RHO)), 1.0)


def _n_blocks(plant, n: int, fs: float) -> int:
    if not plant.segmented:
        return N_BLOCKS
    k = int(round(n / fs / SHOOT_BLOCK_S))
    return int(min(201, max(21, k | 1)))            # odd: the first and the last are fit blocks


class _Recent:
    """The last few simulations of one command, by model: a fit evaluates its end point again, and the search, the
    polish and the conclusions evaluate the same models more than once (a friction simulation ~45 ms on 100 s at
    2 kHz). A copy out each time: the caller may change its array."""
    SIZE = 16                       # a fit's point outlives its Jacobian's columns and refused steps (<= 16)

    def __init__(self):
        self._lock = threading.Lock()
        self._items: dict = {}

    def get(self, lin: dict, fx: dict, make):
        key = (tuple(sorted(lin.items())), tuple(sorted((n, tuple(sorted(v.items()))) for n, v in fx.items())))
        with self._lock:
            hit = self._items.pop(key, None)
            if hit is not None:
                self._items[key] = hit               # the most recent last
        if hit is None:
            hit = make()
            with self._lock:
                self._items[key] = hit
                while len(self._items) > self.SIZE:
                    del self._items[next(iter(self._items))]
        return hit.copy()


class Problem:
    """cmd, y: the recorded command and position; plant: rig.diagnose.plants model_for's argument; use: the
    samples every fit uses; base_band: where a mode can be told apart (the excited band); broadband: a noise or
    steps command; loop: rig.recordings.closedloop's evidence of feedback; noise: what the residuals are weighed by."""

    def __init__(self, cmd: np.ndarray, y: np.ndarray, fs: float, p0, use: np.ndarray, *,
                 base_band: tuple[float, float] | None = None, broadband: bool = False, loop=None,
                 noise: float = 1.0):
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
        self.blk = blk                              # block of each sample (even: fit, odd: held out)
        self.mfit = ((blk % 2) == 0) & self.use
        self.mhold = ((blk % 2) == 1) & self.use
        self.scale = self.plant.scale(self.cmd, self.fs)   # what effects' bounds and starts are relative to
        self.noise = noise
        self.base_band = base_band or (5.0, 0.45 * self.fs)
        self.broadband = broadband
        self.loop = loop
        self.proxy = None
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
        self._normal = (None, None, None)          # _project_shooting's factored normal matrix (F = None)
        self._rows = (None, None)
        self._simulated = _Recent()                 # shared by its with_ copies: the same command
        self._set_basis(sensor_mod.SensorBasis(self.n, self.fs, zero_terms=self.shoot is None))

    def with_(self, *, noise: float | None = None, basis: sensor_mod.SensorBasis | None = None,
              proxy=_KEEP, y: np.ndarray | None = None) -> "Problem":
        """The same problem with another noise estimate, sensor basis or superposition proxy (the data and the
        blocks shared), or another position y of the same command (a simulated twin, rig.diagnose.reduction)."""
        new = copy.copy(self)
        if y is not None:
            if self.shoot is not None:
                raise ValueError("a segmented plant's start states are read from its own data")
            new.y = np.asarray(y, dtype=float)
        if noise is not None:
            new.noise = noise
        if basis is not None:
            new._set_basis(basis)
        if proxy is not _KEEP:
            new.proxy = proxy
        return new

    # -- sensor terms
    def _set_basis(self, basis: sensor_mod.SensorBasis) -> None:
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
        cached = self._free                 # read once: the Jacobian's two threads share the cache
        if cached[0] != key:
            L = int(np.max(self.shoot.ends - self.shoot.starts))
            cached = (key, self.plant.free_response(lin, fx, self.fs, L))
            self._free = cached
        return cached[1]

    def _shooting_normal(self, E: np.ndarray, O: np.ndarray):
        """The Jacobi-scaled normal matrix of _project_shooting, LU-factored (None: singular), and its scaling: it
        depends on the sensor basis, F and the model's free response, not on the residual, so the segment-state
        steps of one model reuse it (cached for F = None)."""
        w = self.mfit
        q = E.shape[1]
        nx = O.shape[1]
        sh = self.shoot
        N = q + nx * sh.count
        G = np.zeros((N, N))
        Ef = E[w]
        G[:q, :q] = Ef.T @ Ef
        for s, (a, e) in enumerate(zip(sh.starts, sh.ends)):
            ws = w[a:e]
            Ow = O[:e - a][ws]
            i = q + s * nx
            G[i:i + nx, i:i + nx] = Ow.T @ Ow
            if q:
                X = E[a:e][ws].T @ Ow
                G[:q, i:i + nx] = X
                G[i:i + nx, :q] = X.T
        d = np.sqrt(np.maximum(np.diag(G), 1e-300))
        Gn = G / np.outer(d, d) + 1e-12 * np.eye(N)
        lu = lu_factor(Gn, check_finite=False)
        return (lu if np.all(np.diag(lu[0]) != 0.0) else None), Gn, d

    def _segment_rows(self, L: int):
        """(segments, L) sample indices of each segment (clipped to its last sample), whether each is in the segment,
        and whether it is a fit sample of it: the segment-wise sums as one product."""
        key = ("rows", L)
        if self._rows[0] != key:
            sh = self.shoot
            j = np.arange(L)
            idx = sh.starts[:, None] + j[None, :]
            inside = idx < sh.ends[:, None]
            idx = np.minimum(idx, sh.ends[:, None] - 1)
            self._rows = (key, (idx, inside, inside & self.mfit[idx]))
        return self._rows[1]

    def _project_shooting(self, r: np.ndarray, F: np.ndarray | None, O: np.ndarray, states: bool = False):
        """_project with the segment-wise initial states: block-sparse normal equations (each segment's state
        touches only its own rows), Jacobi-scaled. Returns (residual, sensor coef, F coef, state response) and,
        with states=True, the (segments, n) initial-state corrections too."""
        w = self.mfit
        E = self.basis.B if F is None else np.column_stack([self.basis.B, F])
        q = E.shape[1]
        nx = O.shape[1]
        sh = self.shoot
        L = O.shape[0]
        if F is None:
            cached = self._normal
            if cached[0] is not O or cached[1] is not self.basis:
                cached = (O, self.basis, self._shooting_normal(E, O))
                self._normal = cached
            lu, Gn, d = cached[2]
        else:
            lu, Gn, d = self._shooting_normal(E, O)
        idx, inside, fit = self._segment_rows(L)
        b = np.empty(q + nx * sh.count)
        b[:q] = E[w].T @ r[w]
        b[q:] = (np.where(fit, r[idx], 0.0) @ O).ravel()
        if lu is not None:
            sol = lu_solve(lu, b / d, check_finite=False) / d
        else:
            sol = np.linalg.lstsq(Gn, b / d, rcond=None)[0] / d
        X = sol[q:].reshape(sh.count, nx)
        state = np.zeros(self.n)          # before the first segment (samples no fit uses): no state
        state[idx[inside]] = (X @ O.T)[inside]
        out = r - E @ sol[:q] - state
        m = self.basis.m
        if states:
            return out, sol[:m], (sol[m:q] if F is not None else None), state, X
        return out, sol[:m], (sol[m:q] if F is not None else None), state

    def model(self, lin: dict, fx: dict) -> np.ndarray:
        return self._model(lin, fx)[0]

    def _model(self, lin: dict, fx: dict, states: np.ndarray | None = None):
        """The model and the segment states it was simulated from (simulate_from)."""
        sfx = catalogue.simulated(fx)
        if self.proxy is not None:
            # superposition proxy: the exact slow model at its fit plus the change that the fast linear-sim
            # effects (delay, base, clip) and linear parameters make
            y_cur, base_c = self.proxy
            fl = catalogue.fast(sfx)
            return y_cur + self.simulate(lin, fl) - base_c, None
        return self.simulate_from(lin, sfx, states)

    def simulate(self, lin: dict, fx: dict) -> np.ndarray:
        """The plant with the effects fx (no disturbance) from the recorded command; a segmented plant from the
        data's state at each segment start."""
        return self.simulate_from(lin, fx)[0]

    def simulate_from(self, lin: dict, fx: dict, states: np.ndarray | None = None):
        """simulate, and the segment states its refinement ended at (None: no refinement). states: those refined
        at a nearby model (the fit's current point, Problem.fit), simulated from as they are (no refinement) where
        friction is in; a play alone is refined as ever (from its states as they are, a play's fit named a base
        resonance beside it: rig prove --plant emps_axis.toml seed 1, a10)."""
        if self.shoot is None:
            return self._simulated.get(lin, fx, lambda: self.plant.simulate(lin, self.cmd, self.fs, fx)), None
        nonlinear = catalogue.state_nonlinear_in(fx)
        nx = self.plant.matrices(lin, fx)[0].shape[0]
        if nx not in self.shoot.X0:
            self.shoot.X0[nx] = self.plant.state_from_data(self.y, self.fs, self.shoot.starts, fx)
        X0 = self.plant.drive_states(self.shoot.X0[nx], fx)
        # a play without friction: the load answers the drive's state only outside the play
        partial = nonlinear and not catalogue.slow_in(fx)
        if nonlinear and not partial and states is not None and states.shape == X0.shape:
            return self.plant.simulate(lin, self.cmd, self.fs, fx, self.shoot.starts, states), states
        if not nonlinear:       # linear in the initial state: the projection's correction is exact
            return self.plant.simulate(lin, self.cmd, self.fs, fx, self.shoot.starts, X0), None
        O = self.free_response(lin, fx)
        sim = self._play_reading(lin, fx, O) if partial else \
            (lambda X: self.plant.simulate(lin, self.cmd, self.fs, fx, self.shoot.starts, X))
        y = sim(X0)
        # friction makes the response nonlinear in the initial state (a wrong start velocity moves the reversals
        # and the sticking), and so does a play (where the drive starts inside it decides when the load moves):
        # Gauss-Newton steps on the segment states, the correction the projection finds from
        # the data's start applied to the simulation itself; the projection then corrects what is left
        # Each step must lower the fit blocks' residual (the projection's, what the fits see) by more than
        # SHOOT_GN_GAIN x noise^2: the steps end at the best states, where a step gains nothing (a model that
        # cannot follow the data has no states to settle on; its steps wander) or they settle. A play's steps that
        # shrink geometrically are taken to the end of their series (_aitken); one that overshoots is taken plain.
        best = None                                   # (rss, y, X0, dX) of the best states
        last = None                                   # the previous plain step (its ratio to this one: _aitken)
        extrapolated = False
        for _ in range(SHOOT_GN_PLAY_STEPS if partial else SHOOT_GN_STEPS):
            r, _, _, _, dX = self._project_shooting(self.y - y, None, O, states=True)
            rss = float(np.sum(r[self.mfit] ** 2))
            if best is None or rss < best[0] - SHOOT_GN_GAIN * self.noise ** 2:
                best = (rss, y, X0, dX)
            elif extrapolated:                        # overshot: a plain step from the best states
                _, y, X0, dX = best
                last = None
            else:
                break
            if np.max(np.abs(dX @ O[0]), initial=0.0) < SHOOT_GN_SETTLED * self.noise:
                break
            step = dX
            if partial and last is not None:
                step = dX * _aitken(dX, last, O)[:, None]
            extrapolated = step is not dX
            last = None if extrapolated else dX       # the ratio is read from two plain steps
            X0 = X0 + step
            y = sim(X0)
        else:
            r = self._project_shooting(self.y - y, None, O)[0]
            if float(np.sum(r[self.mfit] ** 2)) < best[0]:
                return y, X0
        return best[1], best[2]

    def _play_reading(self, lin: dict, fx: dict, O: np.ndarray):
        """X0 -> the reading of a drive without friction from segment states X0: linear in them until the sensor's
        reading (the play), so the drive is simulated once from zero states and each X0 adds its free response O
        (superposition; the same to rounding as simulating from X0: a play's ~10 refinement steps, one simulation)."""
        forced = self.plant.simulate_drive(lin, self.cmd, self.fs, fx, self.shoot.starts,
                                           np.zeros((self.shoot.count, O.shape[1])))
        idx, inside, _ = self._segment_rows(O.shape[0])
        rows = idx[inside]

        def reading(X: np.ndarray) -> np.ndarray:
            drive = forced.copy()
            drive[rows] += (X @ O.T)[inside]
            return self.plant.read(drive, fx)
        return reading

    def _residual_full(self, lin: dict, fx: dict, states: np.ndarray | None = None):
        y, X0 = self._model(lin, fx, states)
        r = self.y - y
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
        return r, dist, c, state, X0

    def residual(self, lin: dict, fx: dict):
        """Full-length residual with the sensor terms (and the disturbance) projected out on the fit blocks,
        the disturbance coefficients and the sensor coefficients."""
        r, dist, c, _, _ = self._residual_full(lin, fx)
        return r, dist, c

    def residual_fit(self, lin: dict, fx: dict) -> np.ndarray:
        """The residual on the fit blocks only (what the least squares see)."""
        return self._residual_fit(lin, fx)[0]

    def _residual_fit(self, lin: dict, fx: dict, states: np.ndarray | None = None):
        """residual_fit and the segment states the model was simulated from (simulate_from)."""
        if self.shoot is not None:
            r, _, _, _, X0 = self._residual_full(lin, fx, states)
            return r[self.mfit], X0
        rf = self.y[self.mfit] - self.model(lin, fx)[self.mfit]
        Ff = self.force_basis(lin, fx)[self.mfit] if catalogue.projected(fx) else None
        c, d = self._coef(rf, Ff)
        rf = rf - self._Bf @ c
        if Ff is not None:
            rf = rf - Ff @ d
        return rf, None

    def force_basis(self, lin: dict, fx: dict) -> np.ndarray:
        """Position responses to a unit sin/cos load force at the disturbance frequency (linear model with
        the base mode if named; the nonlinear effects are not applied to this small line)."""
        return self.plant.force_response(lin, fx, self.fs, catalogue.line_frequency(fx), self.n)

    def spec_keys(self, name: str) -> tuple[str, ...]:
        return self.plant.effects[name].keys(self.plant.input_unit)

    def n_params(self, fx: dict) -> int:
        """Fitted physics parameters: the linear ones, each effect's keys, the disturbance's frequency + 2."""
        return len(self.lin_keys) + sum(catalogue.get(n).n_free for n in fx)

    def space(self, lin0: dict, fx0: dict, free_lin=None, free_fx: dict | None = None):
        """The fitted coordinates of a model: (names, lo, hi, x0, step, unpack), the free linear keys on a log scale
        where positive (eha: within LIN_BOUNDS x nominal), the free effect keys as they are; unpack(x) -> (lin,
        fx)."""
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
        lo, hi = np.array(lo, float), np.array(hi, float)
        x0 = np.clip(np.array(x0, float), lo + 1e-12, hi - 1e-12)

        def unpack(x):
            lin = dict(lin0); fx = {n: dict(v) for n, v in fx0.items()}
            for (grp, key), val in zip(names, x):
                if grp == "lin":
                    lin[key] = (self.nominal[key] * math.exp(val) if (eha or self.plant.log_scale[key])
                                else float(val))
                else:
                    fx[grp][key] = float(val)
            return lin, fx
        return names, lo, hi, x0, np.array(scale) * 1e-3, unpack

    def fit(self, lin0: dict, fx0: dict, free_lin=None, free_fx: dict | None = None, max_iter=20,
            rtol: float = 1e-5) -> ModelFit:
        """Least squares on the fit blocks over free linear keys (log scale where positive) and the free effect
        keys."""
        names, lo, hi, x0, step, unpack = self.space(lin0, fx0, free_lin, free_fx)
        # with friction the Jacobian's columns (lm_fit's near) are simulated from the segment states refined at the
        # point the fit stands on, as they are: one simulation, not the refinement's two or three. The projection
        # still corrects the states linearly, as it does there; keyed on that point, so the columns' two threads and
        # their order change nothing. Every point the fit stands on, and its result, is refined from the data's
        # states as any other model.
        refined = {}

        def fun(x):
            rf, X0 = self._residual_fit(*unpack(x))
            if X0 is not None:
                refined[x.tobytes()] = X0
            return rf / self.noise

        def near(xp, x):
            return self._residual_fit(*unpack(xp), states=refined.get(x.tobytes()))[0] / self.noise

        if names:
            x, _ = lm_fit(fun, x0, lo, hi, step, max_iter=max_iter, rtol=rtol, near=near)
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

    def evaluate(self, lin: dict, fx: dict, k: int) -> ModelFit:
        with np.errstate(all="ignore"):                # numpy's words on overflow: the check below says it once
            r, dist, c, state, _ = self._residual_full(lin, fx)
            rss = float(np.sum(r * r))
        if not fx and not math.isfinite(rss):          # the plant alone (the plant file's values): no fit from it
            raise self.plant.plant.not_computable(self.plant.public_linear(lin),
                                                  f"the residual sum of squares ({rss}) of the model's position")
        # a plant file's plant: how correlated the held-out residual is (the tests count independent samples);
        # the eha plant's tests stay as its proofs measured them
        tau = correlation_time(r, self.mhold, self.n // (2 * int(self.blk[-1] + 1))) \
            if self.plant.axis_search else 1.0
        return ModelFit(lin=lin, fx=fx, rss_fit=float(np.sum(r[self.mfit] ** 2)), rss_hold=float(np.sum(r[self.mhold] ** 2)),
                   k=k, dist=dist, coef=c, state=state, tau=tau)

    def physics(self, f: ModelFit) -> np.ndarray:
        """The physics part of a fitted model (with the disturbance's response and the segment states), metres."""
        yhat = self.model(f.lin, f.fx)
        if f.dist is not None:
            yhat = yhat + self.force_basis(f.lin, f.fx) @ np.array(f.dist[1:])
        if f.state is not None:
            yhat = yhat + f.state
        return yhat

    def series(self, f: ModelFit) -> np.ndarray:
        """The measurement as the model has it: physics plus the fitted sensor terms."""
        return self.physics(f) + self.basis.B @ f.coef


# ---- tests -------------------------------------------------------------------------------------------------

def correlation_time(r: np.ndarray, mask: np.ndarray, max_lag: int) -> float:
    """The integrated correlation time of r on the masked samples, in samples: 1 + 2 sum rho(k) over the lags
    where the autocorrelation stays positive (at most max_lag). n / tau independent samples carry the information
    of n correlated ones: a residual full of model error (a real recording's) is far from white."""
    m = np.asarray(mask, float)
    x = np.asarray(r, float) * m
    n = len(x)
    L = int(max(1, min(max_lag, n // 4, 4000)))
    nf = 1 << int(math.ceil(math.log2(2 * n)))
    acf = np.fft.irfft(np.abs(np.fft.rfft(x, nf)) ** 2, nf)[:L + 1]
    cnt = np.fft.irfft(np.abs(np.fft.rfft(m, nf)) ** 2, nf)[:L + 1]
    if cnt[0] < 2 or acf[0] <= 0:
        return 1.0
    rho = (acf[1:] / np.maximum(cnt[1:], 1.0)) / (acf[0] / cnt[0])
    neg = np.flatnonzero(rho <= 0.0)
    upto = int(neg[0]) if len(neg) else len(rho)
    return float(max(1.0, 1.0 + 2.0 * np.sum(rho[:upto])))


def n_eff(n: int, f: ModelFit) -> float:
    """The independent samples among n of a model's residual (its held-out residual's correlation time)."""
    return max(2.0, n / max(f.tau, 1.0))


def compare(pb: Problem, base: ModelFit, cand: ModelFit) -> dict:
    """BIC on the fit blocks and a likelihood ratio on the held-out blocks (parameters frozen), each counting the
    independent samples of the candidate's residual (a plant file's plant; on the eha plant every sample)."""
    nf = n_eff(int(pb.mfit.sum()), cand); nh = n_eff(int(pb.mhold.sum()), cand)
    dk = max(1, cand.k - base.k)
    dbic = nf * math.log(base.rss_fit / cand.rss_fit) - dk * math.log(nf)
    lr_h = nh * math.log(base.rss_hold / cand.rss_hold)
    gain_h = 1.0 - cand.rss_hold / base.rss_hold
    passed = dbic > 0 and lr_h > dk * math.log(nh) and gain_h > MIN_GAIN
    return {"delta_bic_fit": dbic, "lr_holdout": lr_h, "lr_needed": dk * math.log(nh), "holdout_gain": gain_h,
            "dk": dk, "passed": bool(passed)}

"""Diagnosis engine (issue 7): refit the linear model first, locate the mismatch, choose missing physics from the
catalogue, fit the augmented model and prove each effect on a held-out segment.

Protocol
  * Fit/holdout split: interleaved blocks (even blocks fit, odd blocks held out), so both cover the whole chirp.
  * Refit: the identified parameters K_L, K_C, K_Q, w_nv, zeta within physical bounds (0.7-1.4 x nominal; C is
    not identifiable from position below w_h and stays nominal). A parameter change is not missing physics.
  * Candidates: each catalogue effect fitted jointly with the linear parameters (exact fast models, models.py).
    An effect counts only when it passes BOTH: BIC on the fit blocks (noise variance from the data) and a
    likelihood-ratio test on the held-out blocks with the parameters frozen from the fit blocks.
  * Forward selection: best single effect, then the best second effect on top of it (pairs), max two; a round
    is skipped once the held-out residual is at the noise. Each chosen model is polished (all parameters).
  * Screening for speed: the disturbance only with a spectral line; slow nonlinear models (deadband, friction)
    are refined only when their best grid start rivals the best candidate so far (and, without odd harmonics
    of the chirp, improves the current fit). A fast effect added to a slow model is fitted on a superposition
    proxy (exact slow model + change of the fast linear model) and then scored with the exact model.
  * Confounded groups: other passing candidates whose held-out likelihood is statistically indistinguishable
    from the chosen one's (log-likelihood ratio below ln n) are reported as a group.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from rig.diagnose import locate
from rig.diagnose.effects import NONLINEAR, SPECS, bounds, simulate
from rig.diagnose.lm import _POOL, lm_fit
from rig.diagnose.models import force_response
from rig.errors import RecordingError
from sim_backend.linear import ActuatorParams

LIN_KEYS = ("K_L", "K_C", "K_Q", "w_nv", "zeta")
LIN_BOUNDS = (0.7, 1.4)            # x nominal: physically bounded refit (recordings move them +-15 %)
N_BLOCKS = 50                      # interleaved 2 s blocks of a 100 s chirp
MAX_EFFECTS = 2
LINEAR_SIM = ("transport_delay", "base_resonance", "valve_saturation")   # exact in sim_linear
SLOW = ("valve_deadband", "coulomb_friction")                           # need sim_reduced
HARMONIC_SCREEN = 4.0              # odd-harmonic amplitude / noise that makes nonlinear candidates worth fitting
LINE_RATIO = 40.0                  # spectral line / local median for a disturbance candidate
EXPLAINED = 1.01                   # held-out residual rms / noise below which no further effect is sought
EXPLAINED_SLOW = 1.02              # the same once a reduced (deadband/friction) model is in
CMD_LIMIT_V = 1000.0               # servo-valve commands are +-10 V: beyond this the file is not in volts
POS_LIMIT_M = 10.0                 # the stroke is mm: beyond this the file is not in metres
MIN_BAND_RATIO = 2.0               # the chirp's band must span an octave for band FRFs and the fits
MIN_GAIN = 0.003                   # an effect must cut the held-out residual variance by at least 0.3 %


@dataclass
class Diagnosis:
    effects: list[dict] = field(default_factory=list)        # [{"name","parameters","evidence","score"}]
    group: list[list[str]] = field(default_factory=list)     # confounded groups
    mismatch: dict = field(default_factory=dict)             # bands_hz, windows_s, regimes, harmonics, uncorrelated
    fit: dict = field(default_factory=dict)                  # nominal/refit/augmented -> {"nrmse", ...}
    params_refit: dict = field(default_factory=dict)
    noise_m: float = 0.0
    summary: str = ""
    series: dict = field(default_factory=dict)               # nominal_m, refit_m, augmented_m (aligned with t_s)
    frf: dict = field(default_factory=dict)                  # freqs_hz, measured, nominal, refit, augmented, coherence
    candidates: list[dict] = field(default_factory=list)     # every candidate tried with its test statistics
    timing_s: float = 0.0

    def names(self) -> list[str]:
        return sorted(e["name"] for e in self.effects)


# ---- fitting machinery ------------------------------------------------------------------------------------

@dataclass
class Fit:
    lin: dict                     # linear parameter values
    fx: dict                      # effects {name: {key: value}} (disturbance: frequency_hz only)
    rss_fit: float
    rss_hold: float
    k: int                        # number of fitted parameters
    dist: tuple | None = None     # (freq, coef_sin, coef_cos)


class Problem:
    def __init__(self, rec, p0: ActuatorParams):
        self.cmd = np.asarray(rec.valve_cmd_V, dtype=float)
        self.y = np.asarray(rec.position_m, dtype=float)
        self.fs = float(rec.fs_hz)
        self.n = len(self.y)
        self.p0 = p0
        self.t = np.arange(self.n) / self.fs
        blk = np.arange(self.n) * N_BLOCKS // self.n
        self.mfit = (blk % 2) == 0
        self.mhold = ~self.mfit
        self.mfit[: int(0.05 * self.fs)] = False               # start-up instants carry no information
        self.peak_ma = float(np.max(np.abs(self.cmd))) * p0.K_v
        self.noise = 1.0
        self.n_eval = 0
        self.base_band = (5.0, 0.45 * self.fs)     # set to the chirp's band once known
        self.quick = False
        self.proxy = None
        self._basis: dict = {}

    def params(self, lin: dict) -> ActuatorParams:
        return self.p0.with_(**lin)

    def model(self, lin: dict, fx: dict) -> np.ndarray:
        self.n_eval += 1
        sfx = {k: v for k, v in fx.items() if k != "periodic_disturbance"}
        if self.proxy is not None:
            # superposition proxy: the exact slow model at its fit plus the change that the fast linear-sim
            # effects (delay, base, clip) and linear parameters make
            y_cur, base_c = self.proxy
            fl = {k: v for k, v in sfx.items() if k in LINEAR_SIM}
            return y_cur + simulate(self.params(lin), self.cmd, self.fs, fl) - base_c
        return simulate(self.params(lin), self.cmd, self.fs, sfx)

    def dist_basis(self, f_hz: float) -> np.ndarray:
        if f_hz not in self._basis:
            if len(self._basis) > 8:
                self._basis.clear()
            w = 2 * math.pi * f_hz * self.t
            B = np.c_[np.sin(w), np.cos(w)]
            self._basis[f_hz] = (B, np.linalg.pinv(B[self.mfit]))
        return self._basis[f_hz][0]

    def residual(self, lin: dict, fx: dict):
        """Full-length residual (disturbance projected out on the fit blocks) and the disturbance coefficients."""
        r = self.y - self.model(lin, fx)
        dist = None
        if "periodic_disturbance" in fx:
            f = fx["periodic_disturbance"]["frequency_hz"]
            B = self.force_basis(lin, fx)
            c, *_ = np.linalg.lstsq(B[self.mfit], r[self.mfit], rcond=None)
            r = r - B @ c
            dist = (f, float(c[0]), float(c[1]))      # force amplitudes [N] of sin and cos
        return r, dist

    def force_basis(self, lin: dict, fx: dict) -> np.ndarray:
        """Position responses to a unit sin/cos piston force at the disturbance frequency (linear model with
        the stand mode if named; the nonlinear effects are not applied to this small line)."""
        b = fx.get("base_resonance")
        base = (b["frequency_hz"], b["damping_ratio"], b.get("mass_kg", 280.0)) if b else None
        return force_response(self.params(lin), self.fs, fx["periodic_disturbance"]["frequency_hz"], self.n, base)

    def fit(self, lin0: dict, fx0: dict, free_lin=LIN_KEYS, free_fx: dict | None = None, max_iter=20) -> Fit:
        """Least squares on the fit blocks over free linear keys (log scale) and the free effect keys."""
        free_fx = {n: SPECS[n].keys for n in fx0 if n != "periodic_disturbance"} if free_fx is None else free_fx
        names, lo, hi, x0, scale = [], [], [], [], []
        for k in free_lin:
            names.append(("lin", k)); nom = getattr(self.p0, k)
            lo.append(math.log(LIN_BOUNDS[0])); hi.append(math.log(LIN_BOUNDS[1]))
            x0.append(math.log(lin0.get(k, nom) / nom)); scale.append(0.05)
        for n, keys in free_fx.items():
            bnd = bounds(n, fs=self.fs, peak_ma=self.peak_ma, p=self.p0)
            if n == "base_resonance":     # a stand mode is only told apart (a pair) inside the excited band
                bnd = [self.base_band] + list(bnd[1:])
            for key, (a, b) in zip(SPECS[n].keys, bnd):
                if key not in keys:
                    continue
                names.append((n, key)); lo.append(a); hi.append(b)
                x0.append(fx0[n][key]); scale.append(0.02 * (b - a))
        x0 = np.clip(np.array(x0), np.array(lo) + 1e-12, np.array(hi) - 1e-12)

        def unpack(x):
            lin = dict(lin0); fx = {n: dict(v) for n, v in fx0.items()}
            for (grp, key), val in zip(names, x):
                if grp == "lin":
                    lin[key] = getattr(self.p0, key) * math.exp(val)
                else:
                    fx[grp][key] = float(val)
            return lin, fx

        def fun(x):
            lin, fx = unpack(x)
            r, _ = self.residual(lin, fx)
            return r[self.mfit] / self.noise

        if names:
            x, _ = lm_fit(fun, x0, lo, hi, np.array(scale) * 1e-3, max_iter=max_iter)
            lin, fx = unpack(x)
        else:
            lin, fx = dict(lin0), {n: dict(v) for n, v in fx0.items()}
        return self.evaluate(lin, fx, k=n_params(fx))

    def evaluate(self, lin: dict, fx: dict, k: int) -> Fit:
        r, dist = self.residual(lin, fx)
        return Fit(lin=lin, fx=fx, rss_fit=float(np.sum(r[self.mfit] ** 2)), rss_hold=float(np.sum(r[self.mhold] ** 2)),
                   k=k, dist=dist)

    def series(self, f: Fit) -> np.ndarray:
        yhat = self.model(f.lin, f.fx)
        if f.dist is not None:
            yhat = yhat + self.force_basis(f.lin, f.fx) @ np.array(f.dist[1:])
        return yhat


def n_params(fx: dict) -> int:
    """Fitted parameters of a model: the linear ones, each effect's keys, the disturbance's frequency + 2."""
    return len(LIN_KEYS) + sum(3 if n == "periodic_disturbance" else len(SPECS[n].keys) for n in fx)


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

def _grid_best(pb: Problem, lins: list[dict], fx_base: dict, name: str, key: str, grid) -> tuple[dict, dict, float]:
    jobs = []
    for lin in lins:
        for g in grid:
            fx = {n: dict(v) for n, v in fx_base.items()}
            fx.setdefault(name, {})[key] = float(g)
            jobs.append((lin, fx))

    def rss(job):
        r, _ = pb.residual(*job)
        return float(np.sum(r[pb.mfit] ** 2))
    costs = list(_POOL.map(rss, jobs))               # the simulators release the GIL
    i = int(np.argmin(costs))
    return jobs[i][0], jobs[i][1], costs[i]


def _base_init(pb: Problem, lin: dict, fx_base: dict, f_lo: float, f_hi: float) -> dict:
    """Stand-mode start from the FRF ratio measured / model: B(s) = (s^2+2zws+w^2) / ((1+mu) s^2+2zws+w^2)."""
    yhat = pb.model(lin, {k: v for k, v in fx_base.items() if k != "base_resonance"})
    U = np.fft.rfft(pb.cmd); Y = np.fft.rfft(pb.y); Ym = np.fft.rfft(yhat)
    f = np.fft.rfftfreq(pb.n, 1.0 / pb.fs)
    sel = np.flatnonzero((f > max(f_lo, 3.0)) & (f < f_hi))
    sel = sel[:: max(1, len(sel) // 4000)]
    R = Y[sel] / Ym[sel]; w = np.abs(Ym[sel]) ** 2
    s = 2j * math.pi * f[sel]
    best = (np.inf, None)
    for fb in np.geomspace(*pb.base_band, 160):
        wb = 2 * math.pi * fb
        for zb in (0.01, 0.03, 0.08):
            for mu in (0.05, 0.1, 0.2, 0.4):
                B = (s * s + 2 * zb * wb * s + wb * wb) / ((1 + mu) * s * s + 2 * zb * wb * s + wb * wb)
                c = float(np.sum(w * np.abs(R - B) ** 2))
                if c < best[0]:
                    best = (c, (fb, zb, mu))
    fb, zb, mu = best[1]
    return {"frequency_hz": fb, "damping_ratio": zb, "mass_kg": pb.p0.M / mu}


def _init_candidate(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines) -> tuple[dict, dict] | None:
    slow = any(n in fx_base for n in ("coulomb_friction", "valve_deadband"))
    if name == "transport_delay":
        grid = np.r_[0.0, 0.5e-3, 1e-3, 1.5e-3, 2.2e-3, 3.2e-3, 4.5e-3] if slow else \
            np.r_[0.0, 0.2e-3, np.arange(0.5e-3, 6.01e-3, 0.5e-3)]
        lin, fx, _ = _grid_best(pb, lins, fx_base, name, "delay_s", grid)
        return lin, fx
    if name == "valve_saturation":
        lin, fx, _ = _grid_best(pb, lins, fx_base, name, "limit_ma", pb.peak_ma * np.array([0.2, 0.35, 0.5, 0.6, 0.7, 0.8, 0.88, 0.94, 0.98]))
        return lin, fx
    if name == "valve_deadband":
        grid = [0.15, 0.4, 1.0] if pb.quick else [0.01, 0.08, 0.15, 0.3, 0.5, 0.7, 1.0, 1.5]
        lin, fx, _ = _grid_best(pb, lins, fx_base, name, "width_ma", grid)
        return lin, fx
    if name == "coulomb_friction":
        grid = [60, 200, 600] if pb.quick else [3, 40, 100, 200, 400, 800, 1400]
        lin, fx, _ = _grid_best(pb, lins[:1], fx_base, name, "force_n", grid)
        return lin, fx
    if name == "base_resonance":
        best = None
        for lin in lins:
            fx = {n: dict(v) for n, v in fx_base.items()}
            fx[name] = _base_init(pb, lin, fx_base, *band)
            r, _ = pb.residual(lin, fx)
            s = float(np.sum(r[pb.mfit] ** 2))
            if best is None or s < best[2]:
                best = (lin, fx, s)
        return best[0], best[1]
    if name == "periodic_disturbance":
        if not lines:
            return None
        fx = {n: dict(v) for n, v in fx_base.items()}
        fx[name] = {"frequency_hz": lines[0]["frequency_hz"]}
        return lins[0], fx
    raise KeyError(name)


def _fit_candidate(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines, second=False,
                   skip_above: float | None = None) -> Fit | None:
    if second and name not in SLOW and any(n in fx_base for n in SLOW):
        return _fit_by_proxy(pb, name, lins, fx_base, band, lines)
    init = _init_candidate(pb, name, lins, fx_base, band, lines)
    if init is None:
        return None
    lin0, fx0 = init
    slow = any(n in fx0 for n in SLOW)
    if (slow or name == "valve_saturation") and skip_above is not None:
        # another candidate already reached the noise, or no harmonics call for this one: refine only a start
        # that is already competitive
        st = pb.evaluate(lin0, fx0, k=0)
        if st.rss_fit > skip_above:
            return Fit(lin=lin0, fx=fx0, rss_fit=st.rss_fit, rss_hold=st.rss_hold, k=n_params(fx0))
    if slow and second:   # on a slow model: the effects with the gain and lag; the polish frees all
        return pb.fit(lin0, fx0, free_lin=("K_Q", "K_C"), max_iter=6)
    if slow:
        return pb.fit(lin0, fx0, max_iter=6)
    return pb.fit(lin0, fx0, max_iter=10)


def _fit_by_proxy(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines) -> Fit | None:
    """A fast effect added to a slow (deadband/friction) model: fit it on the superposition proxy (one slow
    simulation), then score the result with the exact slow model."""
    lin_c = lins[0]
    y_cur = pb.model(lin_c, fx_base)
    base_c = simulate(pb.params(lin_c), pb.cmd, pb.fs, {k: v for k, v in fx_base.items() if k in LINEAR_SIM})
    pb.proxy = (y_cur, base_c)
    try:
        init = _init_candidate(pb, name, lins, fx_base, band, lines)
        if init is None:
            return None
        lin0, fx0 = init
        free_fx = {n: SPECS[n].keys for n in fx0 if n in LINEAR_SIM}
        f = pb.fit(lin0, fx0, free_fx=free_fx, max_iter=12)
    finally:
        pb.proxy = None
    return pb.evaluate(f.lin, f.fx, k=n_params(f.fx))


def _without_lines(pb: Problem, r: np.ndarray, lines: list[dict]) -> np.ndarray:
    """The residual with its stationary spectral lines projected out (they are not harmonics of the chirp)."""
    if not lines:
        return r
    B = np.hstack([pb.dist_basis(l["frequency_hz"]) for l in lines])
    c, *_ = np.linalg.lstsq(B, r, rcond=None)
    return r - B @ c


def _polish(pb: Problem, f: Fit) -> Fit:
    """All linear and effect parameters together (the disturbance frequency refined after)."""
    slow = any(n in f.fx for n in ("coulomb_friction", "valve_deadband"))
    pol = _refine_disturbance(pb, pb.fit(f.lin, f.fx, max_iter=5 if slow else 15))
    return pol if pol.rss_fit < f.rss_fit else f


def _refine_disturbance(pb: Problem, f: Fit) -> Fit:
    if "periodic_disturbance" not in f.fx:
        return f
    fx = {n: {k: v for k, v in d.items()} for n, d in f.fx.items()}
    r = pb.y - pb.model(f.lin, fx)
    fx["periodic_disturbance"]["frequency_hz"] = locate.refine_line(r, pb.fs, fx["periodic_disturbance"]["frequency_hz"])
    out = pb.evaluate(f.lin, fx, f.k)
    return out if out.rss_fit <= f.rss_fit else f


# ---- report helpers ------------------------------------------------------------------------------------------

def _metrics(pb: Problem, yhat: np.ndarray) -> dict:
    r = pb.y - yhat
    def nrmse(m):
        yy = pb.y[m]
        return float(np.sqrt(np.sum(r[m] ** 2) / np.sum((yy - yy.mean()) ** 2)))
    rr = float(np.sqrt(np.mean(r ** 2)))
    allm = np.ones(pb.n, bool)
    return {"nrmse": nrmse(allm), "residual_rms_m": rr, "residual_over_noise": rr / pb.noise,
            "nrmse_fit": nrmse(pb.mfit), "nrmse_holdout": nrmse(pb.mhold),
            "residual_over_noise_fit": float(np.sqrt(np.mean(r[pb.mfit] ** 2)) / pb.noise),
            "residual_over_noise_holdout": float(np.sqrt(np.mean(r[pb.mhold] ** 2)) / pb.noise)}


def _public_params(pb: Problem, name: str, f: Fit) -> dict:
    prm = dict(f.fx.get(name, {}))
    if name == "periodic_disturbance" and f.dist is not None:
        fq, a, b = f.dist
        line = pb.force_basis(f.lin, f.fx) @ np.array([a, b])
        tail = line[-max(10, int(pb.fs)):]                      # steady state: the last second
        prm.update(force_n=math.hypot(a, b), phase_rad=math.atan2(b, a),
                   amplitude_m=float(math.sqrt(2.0) * np.sqrt(np.mean(tail ** 2))))
    return {k: float(v) for k, v in prm.items()}


def _evidence(name: str, st: dict, mm: dict) -> str:
    sig = {
        "transport_delay": "phase lag growing with frequency, magnitude unchanged",
        "base_resonance": "local resonance/antiresonance pair in the FRF",
        "valve_saturation": "gain loss at large command with odd harmonics",
        "valve_deadband": "gain loss at small command, distortion at command zero crossings (odd harmonics)",
        "coulomb_friction": "distortion at velocity reversals, largest at low frequency (odd harmonics)",
        "periodic_disturbance": "spectral line not coherent with the command",
    }[name]
    h = mm.get("harmonics", {})
    extra = ""
    if name in NONLINEAR and h:
        extra = f"; odd harmonics {h.get('odd_over_noise', 0):.0f}x noise, even {h.get('even_over_noise', 0):.0f}x"
    return (f"{sig}{extra}; fit-block BIC gain {st['delta_bic_fit']:.0f} (needs > 0), held-out log-likelihood "
            f"ratio {st['lr_holdout']:.0f} (needs > {st['lr_needed']:.0f}), held-out residual variance cut by "
            f"{100 * st['holdout_gain']:.1f} % (needs > {100 * MIN_GAIN:.1f} %)")


# ---- main entry ------------------------------------------------------------------------------------------------

def diagnose(rec, p0: ActuatorParams, *, progress: Callable[[str], None] | None = None, seed: int = 0) -> Diagnosis:
    """Diagnose a recording (rig.recording.Recording) against the nominal ActuatorParams p0."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: None)
    src = getattr(rec, "source", "recording")
    cmd = np.asarray(rec.valve_cmd_V, dtype=float); pos = np.asarray(rec.position_m, dtype=float)
    if len(cmd) < 200 or not (np.all(np.isfinite(cmd)) and np.all(np.isfinite(pos))):
        raise RecordingError(f"{src}: diagnosis needs at least 200 finite samples of valve_cmd_V and position_m")
    if np.ptp(cmd) <= 0 or np.ptp(pos) <= 0:
        raise RecordingError(f"{src}: valve_cmd_V or position_m is constant; diagnosis needs a chirp recording")
    for name, a, limit, unit in (("valve_cmd_V", cmd, CMD_LIMIT_V, "V"), ("position_m", pos, POS_LIMIT_M, "m")):
        peak = float(np.max(np.abs(a)))
        if peak > limit:     # a wrong unit or a broken file; 1e300 would overflow the fits' squares
            raise RecordingError(f"{src}: {name} reaches {peak:.3g} {unit}, expected |{name}| <= {limit:g} {unit}")
    pb = Problem(rec, p0)
    phase, f_inst = locate.chirp_phase(pb.cmd, pb.fs)
    band = locate.chirp_band(f_inst, pb.fs)
    if not band[1] >= MIN_BAND_RATIO * band[0]:
        raise RecordingError(f"{src}: the valve command sweeps only {band[0]:.3g}-{band[1]:.3g} Hz over "
                             f"{pb.n / pb.fs:.3g} s; diagnosis needs a chirp over at least "
                             f"{MIN_BAND_RATIO:g}x in frequency")
    nominal_lin = {k: getattr(p0, k) for k in LIN_KEYS}

    say("nominal model")
    y_nom = pb.model(nominal_lin, {})
    pb.noise = locate.noise_rms(pb.y - y_nom, pb.fs)

    say("refit of the linear parameters")
    refit = pb.fit(nominal_lin, {}, max_iter=10)
    y_ref = pb.series(refit)
    r_ref = pb.y - y_ref
    pb.noise = locate.noise_rms(r_ref, pb.fs)

    say("locating the mismatch")
    pb.base_band = (max(5.0, 1.1 * band[0]), 0.97 * band[1])
    lines = locate.spectral_lines(r_ref, pb.fs, pb.noise, ratio=LINE_RATIO)
    harm = locate.harmonics(_without_lines(pb, r_ref, lines), phase, pb.fs, pb.noise)
    mm = {"harmonics": harm, "uncorrelated": {"lines": lines}}

    # candidates, cheap first and the slow reduced models last: the disturbance only when a line stands out of
    # the residual spectrum; a clip that bites only at the command peaks leaves weak harmonics, so the
    # nonlinear ones are always looked at, but without odd harmonics only a start that already fits is refined
    screen = ["transport_delay", "base_resonance"]
    if lines:
        screen.append("periodic_disturbance")
    screen += ["valve_saturation", "valve_deadband", "coulomb_friction"]

    harmonic_now = harm["odd_over_noise"] > HARMONIC_SCREEN
    chosen: list[str] = []
    current = refit
    tried: list[dict] = []
    groups: list[list[str]] = []
    stats_of: dict[str, dict] = {}
    for step in range(MAX_EFFECTS):
        results = []
        over = math.sqrt(current.rss_hold / pb.mhold.sum()) / pb.noise
        # the noise level is known to ~0.4 % (median of ~10^4 bins): 1 % above it is real; the reduced
        # (deadband/friction) model's own error is up to ~2 % of the noise variance
        explained = EXPLAINED_SLOW if any(n in current.fx for n in SLOW) else EXPLAINED
        say(f"round {step + 1}: held-out residual {over:.3f} x noise")
        for name in screen:
            if name in chosen:
                continue
            if name != "periodic_disturbance" and over < explained:
                continue        # the held-out residual is already at the noise: nothing left to explain
            say(f"candidate {'+'.join(chosen + [name])}")
            lins = [current.lin] if chosen else [refit.lin, nominal_lin]
            floor = [g.rss_fit for _, g, _ in results
                     if math.sqrt(g.rss_hold / pb.mhold.sum()) / pb.noise < explained]
            slow_name = name in ("valve_deadband", "coulomb_friction")
            if floor and slow_name and not harmonic_now:
                continue        # a cheap candidate already reached the noise and no harmonics call for these
            pb.quick = not harmonic_now       # no harmonics: a coarse look at the slow models suffices
            skip = None
            if slow_name and results:  # a slow model is refined only when its best start rivals the best so far
                skip = 2.0 * min(g.rss_fit for _, g, _ in results)
            if floor:
                skip = 2.0 * min(floor)
            if not harmonic_now:       # without harmonics a nonlinearity must at least show in its best start
                skip = min(skip or np.inf, (0.95 if slow_name else 0.999) * current.rss_fit)
            f = _fit_candidate(pb, name, lins, current.fx, band, lines, second=bool(chosen), skip_above=skip)
            if f is None:
                continue
            f = _refine_disturbance(pb, f)
            st = compare(pb, current, f)
            tried.append({"effects": chosen + [name], "rss_fit": f.rss_fit, "rss_holdout": f.rss_hold, **st})
            results.append((name, f, st))
        ok = [r for r in results if r[2]["passed"]]
        if not ok:
            break
        ok.sort(key=lambda r: r[1].rss_hold)
        name, f, st = ok[0]
        # confounded: another candidate whose held-out likelihood is statistically indistinguishable
        nh = int(pb.mhold.sum())
        conf = [n for n, g, s in ok[1:] if nh * math.log(g.rss_hold / f.rss_hold) < math.log(nh)]
        if conf:
            groups.append([name] + conf)
        chosen.append(name); stats_of[name] = st
        say(f"polishing {'+'.join(chosen)}")
        current = _polish(pb, f)
        # with a new effect, candidates may need a fresh screen (e.g. harmonics hidden under a delay mismatch)
        r_cur = pb.y - pb.series(current)
        h2 = locate.harmonics(_without_lines(pb, r_cur, locate.spectral_lines(r_cur, pb.fs, pb.noise, ratio=LINE_RATIO)),
                              phase, pb.fs, pb.noise)
        harmonic_now = h2["odd_over_noise"] > HARMONIC_SCREEN
        # the lines left after the chosen effect (a ring-down peak of a stand mode is gone once it is modelled)
        lines = locate.spectral_lines(r_cur, pb.fs, pb.noise, ratio=LINE_RATIO)
        if lines and "periodic_disturbance" not in screen:
            screen.insert(2, "periodic_disturbance")
        elif not lines and "periodic_disturbance" in screen:
            screen.remove("periodic_disturbance")

    augmented = current
    y_aug = pb.series(augmented)

    # where the mismatch lives (nominal, and what remains after the refit)
    frf = locate.frf_bands(pb.cmd, pb.y, {"nominal": y_nom, "refit": y_ref, "augmented": y_aug}, pb.fs, *band)
    wins, worst, _ = locate.mismatch_windows(pb.y - y_nom, pb.fs, pb.noise)
    wins_r, worst_r, _ = locate.mismatch_windows(r_ref, pb.fs, pb.noise)
    _, worst_a, _ = locate.mismatch_windows(pb.y - y_aug, pb.fs, pb.noise)
    mm.update({
        "bands_hz": locate.mismatch_bands(frf, "nominal"),
        "windows_s": wins,
        "after_refit": {"bands_hz": locate.mismatch_bands(frf, "refit"), "windows_s": wins_r},
        "after_augmented": {"bands_hz": locate.mismatch_bands(frf, "augmented")},
        "regimes": locate.regimes(pb.cmd, pb.y, r_ref, pb.fs, pb.noise),
        "worst_windows": {"nominal": worst, "refit": worst_r, "augmented": worst_a},
        "chirp_band_hz": [float(band[0]), float(band[1])],
    })
    ref_lines = mm["uncorrelated"]["lines"]
    mm["uncorrelated"]["fraction_of_refit_residual_in_lines"] = float(
        sum(l["amplitude_m"] ** 2 / 2 for l in ref_lines) / max(np.mean(r_ref ** 2), 1e-300)) if ref_lines else 0.0

    effects = []
    for name in chosen:
        st = stats_of[name]
        effects.append({"name": name, "parameters": _public_params(pb, name, augmented),
                        "evidence": _evidence(name, st, mm), "score": float(st["lr_holdout"])})

    fit = {"nominal": _metrics(pb, y_nom), "refit": _metrics(pb, y_ref), "augmented": _metrics(pb, y_aug)}
    fit["nominal"]["n_parameters"] = 0
    fit["refit"]["n_parameters"] = refit.k
    fit["augmented"]["n_parameters"] = augmented.k
    noise = pb.noise
    if chosen:
        what = ", ".join(f"{e['name']} ({', '.join(f'{k}={_fmt(v)}' for k, v in e['parameters'].items())})" for e in effects)
    else:
        what = "none: the refit of the linear parameters explains the recording"
    summary = (f"mismatch vs nominal in {len(mm['bands_hz'])} band(s), after refit in "
               f"{len(mm['after_refit']['bands_hz'])}; missing physics: {what}. Residual/noise "
               f"nominal {fit['nominal']['residual_over_noise']:.1f}, refit {fit['refit']['residual_over_noise']:.1f}, "
               f"augmented {fit['augmented']['residual_over_noise']:.2f} (noise {noise:.2g} m).")
    if groups:
        summary += " Confounded: " + "; ".join(" ~ ".join(g) for g in groups) + "."
    frf_out = {k: (v.tolist() if not np.iscomplexobj(v) else {"re": v.real.tolist(), "im": v.imag.tolist()})
               for k, v in frf.items()}
    frf_out["residual_spectra"] = _residual_spectra(pb, {"nominal": y_nom, "refit": y_ref, "augmented": y_aug})
    return Diagnosis(effects=effects, group=groups, mismatch=mm, fit=fit,
                     params_refit={k: float(v) for k, v in refit.lin.items()} | {"C": float(p0.C)},
                     noise_m=float(noise), summary=summary,
                     series={"nominal_m": y_nom, "refit_m": y_ref, "augmented_m": y_aug},
                     frf=frf_out, candidates=tried, timing_s=time.perf_counter() - t_start)


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def _residual_spectra(pb: Problem, models: dict) -> dict:
    """Welch amplitude spectral densities of each residual (m/sqrt(Hz)) and the noise floor."""
    from scipy.signal import welch
    out = {}
    nper = int(min(pb.n, 4 * pb.fs))
    for k, yhat in models.items():
        f, P = welch(pb.y - yhat, fs=pb.fs, nperseg=nper)
        out[k] = np.sqrt(P).tolist()
    out["freqs_hz"] = f.tolist()
    out["noise_asd"] = float(pb.noise / math.sqrt(pb.fs / 2))
    return out

"""Identification of the six actuator parameters x_d = {K_L, C, w_nv, zeta, K_Q, K_C} from a chirp (Eq. 11).

Steps, as in the paper plus what its Section 3 asks for:
1. H1 FRF valve voltage -> position with coherence, Savitzky-Golay smoothed (rig.frf).
2. Bounded least squares of Eq. 10 x ZOH half-sample delay against the smoothed FRF (log-magnitude and phase,
   equal weight per decade), from several starts (the paper saw start-dependent solutions).
3. Output-error refinement in the time domain: the exact ZOH discretisation of Eq. 10 (valve Eq. 1 + full
   actuator Eq. 8) driven by the recorded command, fitted to the recorded position. This uses the low- and
   high-frequency ends of the chirp where the FRF estimate is poor.
4. Uncertainty from the Jacobian at the optimum: cov = s^2 (J^T J)^-1 (white-residual assumption).

Fitting is in log-parameters, so bounds are ratios and the std is relative. M, A_p, V_t, beta, K_v stay at
their design (CAD) values, as in the paper.

Identifiability in the 0.1-100 Hz band (well below w_h ~ 2 kHz): G_EHA ~ valve(w_nv, zeta) x
(K_Q/A_p) / (d1 s + d0) with d0 = K_C K_L / A_p^2 and d1 = 1 + C K_C/A_p^2 + K_L V_t/(4 beta A_p^2) ~ 1.07.
So the data fix w_nv, zeta, K_Q/d1 and the lag corner d0/d1 (the product K_C K_L); K_L alone only through its
~7 % share of d1, K_C alone through the tiny s^2 term, and C hardly at all. A weak prior (log-normal around the
design, PRIOR_REL) keeps those directions from wandering to the bounds; the report flags them.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba
import numpy as np
import scipy.optimize

from rig.recordings import closedloop
from rig.errors import RecordingError, RigError
from rig.frf import FRF, frf_estimate
from rig.recordings.recording import Recording, check_plausible
from sim_backend.linear import IDENTIFIED, ActuatorParams, discretize_zoh, g_eha_frf, zoh_delay

# Bounds as ratios to the design value (p0). K_L +-50 % (issue 6); the valve's by realistic ranges for a
# proportional servo valve of this size: natural frequency 20-300 Hz, apparent damping 0.2-2 (proportional valves
# are often overdamped), flow gain and flow-pressure coefficient within a factor 4 and 10 of the catalogue.
UNITS = {"K_L": "N/m", "C": "N s/m", "w_nv": "rad/s", "zeta": "-", "K_Q": "m^3/s/mA", "K_C": "m^3/s/Pa"}
BOUNDS_REL = {
    "K_L": (0.5, 1.5),
    "C": (0.1, 10.0),
    "w_nv": None,            # absolute, below
    "zeta": None,
    "K_Q": (0.25, 4.0),
    "K_C": (0.1, 10.0),
}
BOUNDS_ABS = {"w_nv": (2 * math.pi * 20.0, 2 * math.pi * 300.0), "zeta": (0.2, 2.0)}
PRIOR_REL = 0.5              # 1-sigma of the weak log-normal prior around the design value (~ +-50 %)
TD_TOL = 1e-6               # relative tolerances of the time-domain fit (its optimum is 1e-4 sharp)
WEAK_SHRINK = 1 / 3           # posterior sd above this fraction of the prior's: "weakly identified"
POOR_NRMSE = 0.2              # rig identify's poor fit, either path: a fifth of the motion unexplained (exit 5)
POOR_COHERENCE = 0.95         # ... or, for the eha's FRF fit, a band bin this incoherent


NOTES = ("SI units, w_nv in rad/s. std: 1 sigma from the Jacobian at the optimum (white-residual assumption, so "
         "optimistic when the fit residual is far above the sensor noise), with the weak log-normal design prior "
         "(+-50 %) included, so a parameter the data do not fix shows about the prior's spread. The chirp band "
         "(well below w_h) fixes w_nv, zeta, K_Q and the lag corner K_C*K_L/A_p^2; K_L, K_C and C alone are weak.")


def bounds_for(p0: ActuatorParams) -> dict[str, tuple[float, float]]:
    out = {}
    for k in IDENTIFIED:
        if BOUNDS_REL[k] is not None:
            lo, hi = BOUNDS_REL[k]
            v = getattr(p0, k)
            out[k] = (lo * v, hi * v)
        else:
            out[k] = BOUNDS_ABS[k]
    return out


@dataclass
class IdentResult:
    params: ActuatorParams
    std: dict[str, float]
    fit: dict[str, float]
    frf: FRF
    p0: ActuatorParams
    correlation: dict[str, float] = field(default_factory=dict)
    weakly_identified: dict[str, str] = field(default_factory=dict)
    starts: list[dict] = field(default_factory=list)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    timing_s: dict[str, float] = field(default_factory=dict)
    model_position_m: np.ndarray | None = None     # the identified model driven by the recorded command
    frf_source: str = ""                            # the recording's file name

    def change_pct(self) -> dict[str, float]:
        """Each identified parameter's change from the start (Table 1's design unless a config gave another), in %
        to 0.1 %, as `rig identify`'s change column."""
        d = self.p0.identified()
        # + 0.0: a change that rounds to zero prints 0.0, never -0.0
        return {k: round(100.0 * (v / d[k] - 1.0), 1) + 0.0 for k, v in self.params.identified().items()}

    def to_json(self) -> dict:
        return {"parameters": self.params.identified(), "std": self.std, "fit": self.fit, "notes": NOTES,
                "correlation": self.correlation, "weakly_identified": self.weakly_identified,
                "bounds": {k: list(v) for k, v in self.bounds.items()},
                "design": self.p0.identified(), "timing_s": self.timing_s, "source": self.frf_source,
                "multi_start": [{"frf_cost": r["cost"], "start": r["start"], "end": r["end"]} for r in self.starts]}


# ---- parameter vector <-> ActuatorParams -------------------------------------------------------------

def _to_params(theta: np.ndarray, p0: ActuatorParams) -> ActuatorParams:
    return p0.with_(**{k: float(math.exp(v)) for k, v in zip(IDENTIFIED, theta)})


def _theta(p: ActuatorParams) -> np.ndarray:
    return np.log([getattr(p, k) for k in IDENTIFIED])


# ---- frequency-domain fit ---------------------------------------------------------------------------

def model_frf(p: ActuatorParams, w: np.ndarray, fs_hz: float) -> np.ndarray:
    """Eq. 10 (full Eq. 8 actuator) with the ZOH half-sample delay of the recorded command."""
    return g_eha_frf(p, w) * zoh_delay(w, fs_hz)


def _frf_weights(frf: FRF) -> np.ndarray:
    """Equal weight per decade (sqrt(df/f)); zero outside the fitted bins."""
    f = frf.freqs_hz
    df = np.gradient(f)
    return np.where(frf.use, np.sqrt(df / f), 0.0)


def _frf_residual(theta, p0, w, Hm, wt, fs):
    r = np.log(model_frf(_to_params(theta, p0), w, fs) / Hm)
    return np.concatenate([wt * r.real, wt * np.angle(np.exp(1j * r.imag))])


def _prior_residual(theta, theta0, weight):
    return weight * (theta - theta0) / math.log(1 + PRIOR_REL)


def _start_points(p0: ActuatorParams, lo: np.ndarray, hi: np.ndarray, starts: int, seed: int) -> list[np.ndarray]:
    """The design point, then a seeded Latin hypercube in log-space inside the bounds (inner 80 %)."""
    th0 = np.clip(_theta(p0), lo + 1e-9, hi - 1e-9)
    pts = [th0]
    n = max(0, starts - 1)
    if n:
        rng = np.random.default_rng(seed)
        u = (np.argsort(rng.random((n, len(lo))), axis=0) + rng.random((n, len(lo)))) / n
        pts += [lo + (hi - lo) * (0.1 + 0.8 * row) for row in u]
    return pts


def fit_frf(frf: FRF, p0: ActuatorParams, *, starts: int = 8, seed: int = 0,
            bounds: dict | None = None, source: str = "recording") -> tuple[np.ndarray, list[dict]]:
    """Multi-start bounded least squares on the smoothed FRF. Returns the best theta and every start's result."""
    b = bounds or bounds_for(p0)
    lo = np.log([b[k][0] for k in IDENTIFIED])
    hi = np.log([b[k][1] for k in IDENTIFIED])
    sel = frf.use
    if sel.sum() < 8:
        raise RecordingError(f"{source}: the FRF has only {int(sel.sum())} usable bins (coherence >= threshold in the "
                             f"excited band {frf.band_hz[0]:.3g}-{frf.band_hz[1]:.3g} Hz): not a chirp recording?")
    w = frf.w[sel]
    Hm = frf.H_smooth[sel]
    wt = _frf_weights(frf)[sel]
    wt = wt / math.sqrt(np.sum(wt ** 2))
    th0 = _theta(p0)
    # the prior is light here: it only breaks ties between equivalent minima
    prior_w = 1e-3
    results = []
    for x0 in _start_points(p0, lo, hi, starts, seed):
        def fun(th):
            return np.concatenate([_frf_residual(th, p0, w, Hm, wt, frf.fs_hz), _prior_residual(th, th0, prior_w)])
        sol = scipy.optimize.least_squares(fun, x0, bounds=(lo, hi), method="trf", x_scale=1.0,
                                           xtol=1e-10, ftol=1e-12, gtol=1e-12, max_nfev=400)
        r = _frf_residual(sol.x, p0, w, Hm, wt, frf.fs_hz)
        results.append({"theta": sol.x, "cost": float(np.sum(r ** 2)), "nfev": int(sol.nfev),
                        "start": _to_params(x0, p0).identified(), "end": _to_params(sol.x, p0).identified()})
    best = min(results, key=lambda d: d["cost"])
    return best["theta"], results


# ---- exact discrete model and time-domain output error ---------------------------------------------

# State scaling for a well-conditioned matrix exponential: x_v [mA], its rate [mA/ms], P_L [MPa], x_p [um],
# v_p [mm/s].
_SCALE = np.array([1.0, 1e3, 1e6, 1e-6, 1e-3])


def continuous_ss(p: ActuatorParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 1, 3, 6, 7 (F_L = 0) as x' = A x + B u, y = C x; physical states, scaled (see _SCALE)."""
    A = np.zeros((5, 5))
    w2, zw = p.w_nv ** 2, 2 * p.zeta * p.w_nv
    A[0, 1] = 1.0
    A[1, 0], A[1, 1] = -w2, -zw
    g = 4 * p.beta / p.V_t
    A[2, 0], A[2, 2], A[2, 4] = g * p.K_Q, -g * p.K_C, -g * p.A_p
    A[3, 4] = 1.0
    A[4, 2], A[4, 3], A[4, 4] = p.A_p / p.M, -p.K_L / p.M, -p.C / p.M
    B = np.zeros((5, 1))
    B[1, 0] = w2 * p.K_v
    C = np.zeros((1, 5))
    C[0, 3] = 1.0
    S = _SCALE
    return A * S[None, :] / S[:, None], B / S[:, None], C * S[None, :]


def discrete_ss(p: ActuatorParams, fs_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact ZOH discretisation: Phi = e^{AT}, Gamma = int_0^T e^{As} ds B (one augmented expm)."""
    A, B, C = continuous_ss(p)
    Phi, Gam = discretize_zoh(A, B, 1.0 / fs_hz)
    return Phi, Gam, C


@numba.njit(cache=True, nogil=True)     # nogil: a signal reaches the main thread meanwhile
def _dlsim(Phi, Gam, C, u, y):
    # y_k is sampled before u_k acts (DAC/ADC pair at the same instant), x_0 = 0
    n = Phi.shape[0]
    x = np.zeros(n)
    xn = np.zeros(n)
    for k in range(u.shape[0]):
        acc = 0.0
        for i in range(n):
            acc += C[0, i] * x[i]
        y[k] = acc
        for i in range(n):
            s = Gam[i, 0] * u[k]
            for j in range(n):
                s += Phi[i, j] * x[j]
            xn[i] = s
        for i in range(n):
            x[i] = xn[i]


def simulate_linear(p: ActuatorParams, cmd_V: np.ndarray, fs_hz: float) -> np.ndarray:
    """Position [m] of the linear model (Eq. 10) for a ZOH command sampled at fs_hz, from rest."""
    Phi, Gam, C = discrete_ss(p, fs_hz)
    u = np.ascontiguousarray(cmd_V, dtype=float)
    y = np.empty_like(u)
    _dlsim(Phi, Gam, C, u, y)
    return y


def _td_residual(theta, p0, u, y, fs):
    r = y - simulate_linear(_to_params(theta, p0), u, fs)
    return r - r.mean()      # a constant transducer offset is not a model error


def fit_time_domain(rec: Recording, theta_init: np.ndarray, p0: ActuatorParams, lo, hi, *,
                    prior_weight: float = 1.0, max_nfev: int = 60):
    u, y, fs = rec.valve_cmd_V, rec.position_m, rec.fs_hz
    th0 = _theta(p0)
    r0 = _td_residual(theta_init, p0, u, y, fs)
    # residual scale: the noise floor is unknown before the fit; use the start's rms (prior weight relative)
    s0 = float(np.sqrt(np.mean(r0 ** 2))) or 1.0

    def fun(th):
        return np.concatenate([_td_residual(th, p0, u, y, fs) / s0, _prior_residual(th, th0, prior_weight)])

    sol = scipy.optimize.least_squares(fun, np.clip(theta_init, lo + 1e-12, hi - 1e-12), bounds=(lo, hi),
                                       method="trf", x_scale="jac", xtol=TD_TOL, ftol=TD_TOL, gtol=TD_TOL,
                                       max_nfev=max_nfev)
    return sol


# ---- uncertainty --------------------------------------------------------------------------------------

def _covariances(J_data: np.ndarray, sigma: float, prior_sd: float) -> tuple[np.ndarray, np.ndarray]:
    """Data-only (pinv, may be huge along unidentifiable directions) and posterior (data + weak prior) log-param
    covariances. J_data is d(residual [m])/d(theta)."""
    info = J_data.T @ J_data / sigma ** 2
    cov_data = np.linalg.pinv(info, rcond=1e-15, hermitian=True)
    cov_post = np.linalg.inv(info + np.eye(info.shape[0]) / prior_sd ** 2)
    return cov_data, cov_post


def _distinct(results: list[dict], rel: float = 0.02) -> int:
    """Number of distinct end points among the starts that reached within 10 % of the best cost."""
    best = min(r["cost"] for r in results)
    ends = [r["theta"] for r in results if r["cost"] <= 1.1 * best + 1e-30]
    groups: list[np.ndarray] = []
    for e in ends:
        if not any(np.max(np.abs(e - g)) < rel for g in groups):
            groups.append(e)
    return len(groups)


def frf_errors(p: ActuatorParams, frf: FRF) -> tuple[float, float, float, float]:
    """rms and max error of the model against the raw FRF over the fitted bins: dB and degrees."""
    sel = frf.use
    r = np.log(model_frf(p, frf.w[sel], frf.fs_hz) / frf.H[sel])
    db = 20 / math.log(10) * r.real
    deg = np.degrees(np.angle(np.exp(1j * r.imag)))
    return (float(np.sqrt(np.mean(db ** 2))), float(np.sqrt(np.mean(deg ** 2))),
            float(np.max(np.abs(db))), float(np.max(np.abs(deg))))


def time_domain_errors(p: ActuatorParams, rec: Recording) -> tuple[float, float, np.ndarray]:
    """(NRMSE, residual rms [m], model position) of the linear model driven by the recorded command."""
    ym = simulate_linear(p, rec.valve_cmd_V, rec.fs_hz)
    r = rec.position_m - ym
    off = r.mean()
    r = r - off
    yc = rec.position_m - rec.position_m.mean()
    rms = float(np.sqrt(np.mean(r ** 2)))
    return rms / float(np.sqrt(np.mean(yc ** 2)) or 1.0), rms, ym + off


# ---- the whole identification -------------------------------------------------------------------------

def _uncertainty(J: np.ndarray, sigma: float, prior_sd: float, p: ActuatorParams):
    """Standard deviations, correlations and the weakly identified parameters from the Jacobian (with the
    design prior): (std, correlation matrix, relative std of K_C*K_L, weak)."""
    cov_data, cov_post = _covariances(J, sigma, prior_sd)
    sd_post = np.sqrt(np.clip(np.diag(cov_post), 0, None))
    sd_data = np.sqrt(np.clip(np.diag(cov_data), 0, None))
    std = {k: float(getattr(p, k) * math.expm1(s)) for k, s in zip(IDENTIFIED, sd_post)}
    iL, iC = IDENTIFIED.index("K_L"), IDENTIFIED.index("K_C")
    corr = cov_post / np.outer(sd_post, sd_post)
    v_prod = cov_post[iL, iL] + cov_post[iC, iC] + 2 * cov_post[iL, iC]
    prod_rel = float(math.expm1(math.sqrt(max(v_prod, 0.0))))
    weak = {}
    for k, s_data, s_post in zip(IDENTIFIED, sd_data, sd_post):
        # data that shrink the prior's spread by less than 3x leave the value to the prior and the bounds
        if s_post > WEAK_SHRINK * prior_sd:
            weak[k] = (f"weakly identified: +-{100 * math.expm1(s_post):.0f} % (1 sigma), the data alone "
                       f"{'do not fix it' if s_data > 1 else f'fix it to +-{100 * math.expm1(s_data):.0f} %'}; "
                       f"held by the design prior (+-{100 * PRIOR_REL:.0f} %) and the bounds")
    weak["K_C*K_L"] = (f"the lag corner fixes the product K_C*K_L to +-{100 * prod_rel:.2g} %, each factor only to "
                       f"+-{100 * math.expm1(sd_post[iC]):.2g} % (K_C) and +-{100 * math.expm1(sd_post[iL]):.2g} % "
                       f"(K_L), corr(K_C, K_L) = {corr[iL, iC]:+.2f}")
    return std, corr, prod_rel, weak


def _fit_quality(rec: Recording, p: ActuatorParams, p0: ActuatorParams, frf: FRF, th, lo, hi, prod_rel: float, *,
                 n_starts: int, distinct: int, refine_time_domain: bool) -> tuple[dict, np.ndarray]:
    """The fit figures of the identified model against the design's, with warnings (poor fit, closed loop), and
    the model's position."""
    nrmse, res_rms, ym = time_domain_errors(p, rec)
    nrmse0, res_rms0, _ = time_domain_errors(p0, rec)
    db, deg, db_max, deg_max = frf_errors(p, frf)
    db0, deg0, _, _ = frf_errors(p0, frf)
    fit = {
        "nrmse": nrmse, "residual_rms_m": res_rms, "frf_err_db": db, "frf_err_deg": deg,
        "frf_err_db_max": db_max, "frf_err_deg_max": deg_max,
        "initial_nrmse": nrmse0, "initial_residual_rms_m": res_rms0, "initial_frf_err_db": db0,
        "initial_frf_err_deg": deg0,
        "coherence_min": float(np.min(frf.coherence[frf.use])) if frf.use.any() else 0.0,
        "band_hz": [float(frf.freqs_hz[frf.use][0]), float(frf.freqs_hz[frf.use][-1])],
        "n_frf_bins": int(frf.use.sum()), "n_samples": rec.n, "fs_hz": rec.fs_hz,
        "starts": n_starts, "distinct_minima": distinct,
        "K_C*K_L": p.K_C * p.K_L, "K_C*K_L_rel_std": prod_rel,
        "lag_corner_rad_s": p.lag_corner, "dc_gain_m_per_V": p.dc_gain_m_per_V,
        "refined_time_domain": bool(refine_time_domain),
        "at_bounds": [k for k, t, l, h in zip(IDENTIFIED, th, lo, hi) if min(t - l, h - t) < 0.01],
    }
    poor = poor_fit(nrmse, "this linear model", fit["coherence_min"])
    if poor:
        fit["warning"] = poor
    loop = closedloop.check(rec.valve_cmd_V, rec.position_m, rec.fs_hz, getattr(rec, "meta", None))
    fit["closed_loop"] = loop.as_dict()
    if loop.closed:
        fit["warning"] = (f"closed-loop data ({loop.reason}): the command is not independent of the noise, so "
                          f"these open-loop parameters are biased; identify from an open-loop run (rig chirp)"
                          + (f"; also {fit['warning']}" if "warning" in fit else ""))
    return fit, ym


def poor_fit(nrmse: float, model: str, coherence_min: float | None = None) -> str | None:
    """rig identify's one poor-fit rule, for the eha's fit and a plant file's (which has no FRF, so no
    coherence): the warning's text, None for a fit that is not poor."""
    if not (nrmse > POOR_NRMSE or coherence_min is not None and coherence_min < POOR_COHERENCE):
        return None
    if coherence_min is None:
        return f"poor fit (NRMSE {nrmse:.2f}): the recording is not a clean response of {model}"
    return (f"poor fit (NRMSE {nrmse:.2f}, lowest coherence used {coherence_min:.2f}): the recording is not a clean "
            f"chirp response of {model}")


def refuse_feedback_only(rec: Recording) -> None:
    """RigError when the command was a function of the measured stroke alone (feedback, no external reference):
    an FRF fit of position over command then gives the loop's sensitivity, not the actuator, and looks
    confident doing so. A track run has its reference as external excitation: it may be identified."""
    if rec.closed_loop and rec.reference_m is None:
        raise RigError(f"{rec.source}: closed-loop recording ({rec.closed_loop}): the valve command depends on the "
                       "measured stroke, so an actuator fit would be biased; record an open-loop chirp (rig chirp)")


def identify(rec: Recording, p0: ActuatorParams | None = None, *, starts: int = 8, refine_time_domain: bool = True,
             seed: int = 0, frf: FRF | None = None, progress=None) -> IdentResult:
    """Identify x_d = {K_L, C, w_nv, zeta, K_Q, K_C} from a chirp recording (valve_cmd_V -> position_m).

    p0: the design (Table 1) values; the bounds are around it and the start of the multi-start.
    progress: optional callable(stage: str, fraction: float) for a progress bar.
    """
    p0 = p0 or ActuatorParams()
    check_plausible(rec)
    tick = progress or (lambda stage, frac: None)
    timing = {}
    t0 = time.perf_counter()
    c0 = time.process_time()
    tick("FRF estimate", 0.0)
    frf = frf or frf_estimate(rec)
    timing["frf_s"] = time.perf_counter() - t0
    b = bounds_for(p0)
    lo = np.log([b[k][0] for k in IDENTIFIED])
    hi = np.log([b[k][1] for k in IDENTIFIED])
    tick("FRF fit (multi-start)", 0.1)
    t1 = time.perf_counter()
    th_frf, results = fit_frf(frf, p0, starts=starts, seed=seed, bounds=b, source=rec.source)
    timing["frf_fit_s"] = time.perf_counter() - t1
    th = th_frf
    prior_sd = math.log(1 + PRIOR_REL)
    if refine_time_domain:
        tick("time-domain output-error refinement", 0.3)
        t2 = time.perf_counter()
        sol = fit_time_domain(rec, th_frf, p0, lo, hi)
        th = sol.x
        timing["time_domain_s"] = time.perf_counter() - t2
        n = rec.n
        r_final = _td_residual(th, p0, rec.valve_cmd_V, rec.position_m, rec.fs_hz)
        sigma = float(np.sqrt(np.sum(r_final ** 2) / max(1, n - len(th))))
        s0 = float(np.sqrt(np.mean(_td_residual(th_frf, p0, rec.valve_cmd_V, rec.position_m, rec.fs_hz) ** 2)))
        J = sol.jac[:n] * (s0 or 1.0)          # back to metres per unit log-parameter
    else:
        sel = frf.use
        wt = _frf_weights(frf)[sel]
        wt = wt / math.sqrt(np.sum(wt ** 2))
        def f(t):
            return _frf_residual(t, p0, frf.w[sel], frf.H_smooth[sel], wt, frf.fs_hz)
        J = _num_jac(f, th)
        r = f(th)
        sigma = float(np.sqrt(np.sum(r ** 2) / max(1, r.size - len(th)))) or 1e-12
    tick("uncertainty", 0.9)
    p = _to_params(th, p0)
    std, corr, prod_rel, weak = _uncertainty(J, sigma, prior_sd, p)
    iL, iC = IDENTIFIED.index("K_L"), IDENTIFIED.index("K_C")
    # fit quality
    tick("fit quality", 0.95)
    fit, ym = _fit_quality(rec, p, p0, frf, th, lo, hi, prod_rel, n_starts=len(results),
                           distinct=_distinct(results), refine_time_domain=refine_time_domain)
    for k in fit["at_bounds"]:
        weak.setdefault(k, "")
        weak[k] = (weak[k] + "; " if weak[k] else "") + (
            f"at its bound {getattr(p, k):.4g}: the linear model is straining to fit (an effect it lacks?)")
    timing["total_s"] = time.perf_counter() - t0
    timing["cpu_s"] = time.process_time() - c0      # all threads of the process (the machine may be shared)
    tick("done", 1.0)
    res = IdentResult(params=p, std=std, fit=fit, frf=frf, p0=p0,
                      correlation={"K_C,K_L": float(corr[iL, iC]),
                                   "K_Q,K_L": float(corr[IDENTIFIED.index("K_Q"), iL]),
                                   "w_nv,zeta": float(corr[IDENTIFIED.index("w_nv"), IDENTIFIED.index("zeta")])},
                      weakly_identified=weak, starts=[{k: v for k, v in r.items() if k != "theta"} for r in results],
                      bounds=b, timing_s=timing, model_position_m=ym, frf_source=rec.source)
    return res


def _num_jac(f, x, h: float = 1e-6) -> np.ndarray:
    f0 = f(x)
    J = np.empty((f0.size, x.size))
    for i in range(x.size):
        xp = x.copy()
        xp[i] += h
        J[:, i] = (f(xp) - f0) / h
    return J

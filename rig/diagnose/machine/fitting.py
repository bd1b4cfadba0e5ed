"""Fitting the rig model's parameters to the replay's residual, and the tests an effect must pass.

A fit moves named slots of theta (Slot: a key of rigmodel.neutral and an index, on a log or linear scale within
physical bounds) by bounded least squares (scipy's trust-region reflective) on the fit bins; every nuisance
term is projected out inside each evaluation (residual.Replay). A weak prior holds the common refit factors
near the configured model where the recording does not excite them (isolation off: the valves barely move).

The tests are today's (rig/diagnose: BIC on the fit bins, a likelihood ratio on the held-out bins with the
parameters frozen, a minimum share of the held-out residual explained), on the whitened residuals.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from rig.diagnose.machine.residual import Evaluation, Replay
from rig.diagnose.machine.rigmodel import copy_theta

MIN_GAIN = 0.01                 # an effect must cut the held-out residual by at least 1 %
PRIOR_SD = 0.25                 # log-factor spread of the common refit factors' prior (x/÷ 1.28: a valve's
                                # and a membrane's tolerances)


@dataclass(frozen=True)
class Slot:
    key: str
    index: int
    scale: str                  # "log" (a positive factor or frequency), "lin", or "signed" (a gain: log of its
                                # size, its sign kept as theta has it)
    lo: float
    hi: float
    prior: bool = False         # held near its start by the weak prior (common refit factors)

    def get(self, th: dict) -> float:
        v = float(th[self.key][self.index])
        return abs(v) if self.scale == "signed" else v

    def to_x(self, v: float) -> float:
        v = min(max(v, self.lo), self.hi)
        return math.log(v) if self.scale in ("log", "signed") else v

    def from_x(self, x: float) -> float:
        return math.exp(x) if self.scale in ("log", "signed") else x

    def bounds_x(self) -> tuple[float, float]:
        return (math.log(self.lo), math.log(self.hi)) if self.scale in ("log", "signed") else (self.lo, self.hi)


def put(th: dict, slots, values) -> dict:
    """theta with the slots set to values (a signed slot keeps theta's sign)."""
    out = copy_theta(th)
    for s, v in zip(slots, values):
        out[s.key][s.index] = math.copysign(v, out[s.key][s.index]) if s.scale == "signed" else v
    return out


def residual_vector(ev: Evaluation) -> np.ndarray:
    return residual_vector_of(ev.r)


@dataclass
class FitResult:
    th: dict
    ev: Evaluation              # on the fit bins
    nfev: int
    slots: tuple


def fit(rp: Replay, th0: dict, slots, mask: np.ndarray, *, U_of=None, max_nfev: int = 30) -> FitResult:
    """Least squares over `slots` from th0 on the bins of mask. U_of(th): the valve commands the model sees
    (a deadband's effective command), None: the recorded ones. The Jacobian holds the nuisance terms of the
    point it is taken at (Replay.linear)."""
    slots = tuple(slots)
    cmd = (lambda th: U_of(th)) if U_of else (lambda th: None)
    if not slots:
        return FitResult(th0, rp.evaluate(th0, mask, U=cmd(th0)), 1, slots)
    lo = np.array([s.bounds_x()[0] for s in slots])
    hi = np.array([s.bounds_x()[1] for s in slots])
    x0 = np.clip([s.to_x(s.get(th0)) for s in slots], lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    pri = np.array([s.prior for s in slots])
    h = np.array([1e-4 if s.scale != "lin" else 1e-4 * (s.hi - s.lo) for s in slots])
    state: dict = {}

    def thx(x):
        return put(th0, slots, [s.from_x(v) for s, v in zip(slots, x)])

    def fun(x):
        th = thx(x)
        ev = rp.evaluate(th, mask, U=cmd(th))
        state.update(ev=ev, x=np.array(x, copy=True), nfev=state.get("nfev", 0) + 1)
        res = residual_vector(ev)
        return np.concatenate([res, (x[pri] - x0[pri]) / PRIOR_SD]) if pri.any() else res

    def jac(x):
        if not np.array_equal(state.get("x"), x):
            fun(x)
        ev = state["ev"]
        base = residual_vector(ev)
        cols = []
        for j in range(len(x)):
            x1 = np.array(x, copy=True)
            x1[j] = x1[j] + h[j] if x1[j] + h[j] <= hi[j] else x1[j] - h[j]
            th1 = thx(x1)
            cols.append((residual_vector_of(rp.linear(th1, ev, U=cmd(th1))) - base) / (x1[j] - x[j]))
        J = np.column_stack(cols)
        if pri.any():
            J = np.vstack([J, np.eye(len(x))[pri] / PRIOR_SD])
        return J
    sol = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=max_nfev,
                        xtol=1e-6, ftol=1e-6)
    th = thx(sol.x)
    ev = state["ev"] if np.array_equal(state.get("x"), sol.x) else rp.evaluate(th, mask, U=cmd(th))
    return FitResult(th, ev, int(sol.nfev), slots)


def residual_vector_of(r: np.ndarray) -> np.ndarray:
    v = r.reshape(-1)
    return np.concatenate([v.real, v.imag])


def grid_search(rp: Replay, th0: dict, slot: Slot, values, mask: np.ndarray, *, U_of=None) -> tuple[float, float]:
    """The value of one slot on a grid with the best fit-bin rss (everything else held): (value, rss)."""
    best = (slot.get(th0), math.inf)
    for v in values:
        th = put(th0, (slot,), (v,))
        rss = rp.evaluate(th, mask, U=U_of(th) if U_of else None).rss
        if rss < best[1]:
            best = (v, rss)
    return best


def compare(base_fit: float, base_hold: float, cand_fit: float, cand_hold: float, n_fit: int, n_hold: int,
            dk: int) -> dict:
    """BIC on the fit bins and a likelihood ratio on the held-out bins (parameters frozen from the fit bins):
    the tests every effect passes (rig/diagnose/engine.py compare, on the replay's whitened residuals)."""
    dk = max(1, dk)
    dbic = n_fit * math.log(base_fit / cand_fit) - dk * math.log(n_fit)
    lr = n_hold * math.log(base_hold / cand_hold)
    gain = 1.0 - cand_hold / base_hold
    passed = dbic > 0 and lr > dk * math.log(n_hold) and gain > MIN_GAIN
    return {"delta_bic_fit": dbic, "lr_holdout": lr, "lr_needed": dk * math.log(n_hold), "holdout_gain": gain,
            "dk": dk, "passed": bool(passed)}

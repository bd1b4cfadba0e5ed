"""How sure each named effect is, and what it carries (docs/DIAGNOSIS.md, "A verdict for real data"):

  interval   its size's 95 % confidence interval: a bootstrap over the fit blocks, linearised at the fit (each
             resample of whole blocks moves the parameters by one Gauss-Newton step on the Jacobian and residual
             of the blocks it drew). Blocks, not samples: a real recording's residual is correlated within a
             block, and resampling samples would hide it; the linear parameters and the other effects are free in
             every step, so what they trade with the effect widens its interval.
  share      the part of the refit's held-out residual variance the effect removes, the others kept: the held-out
             residual of the model without it, fitted again (the others alone, as the search's first round fitted
             them; one effect alone: the refit), less the augmented model's, over the refit's. The linear
             parameters are fitted again because, fitted beside the effect, they lean on it: taken out with them
             frozen, a delay would "remove" 400 % of the refit's residual.
  evidence   the held-out log-likelihood ratio of taking it out (the same two models, the independent samples
             of the residual counted): the effects are ranked by it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.diagnose import catalogue
from rig.diagnose.lm import _POOL
from rig.diagnose.problem import ModelFit, Problem, n_eff

RESAMPLES = 400
LEVEL = 0.95
METHOD = (f"{RESAMPLES} resamples of the fit blocks, each one Gauss-Newton step from the fit (linearised block "
          f"bootstrap), {100 * LEVEL:.0f} %")


@dataclass(frozen=True)
class Standing:
    """One named effect's interval (key -> (low, high)), share of the refit's held-out residual variance and the
    held-out log-likelihood ratio of taking it out."""
    interval: dict
    share: float
    evidence: float


def _jacobian(pb: Problem, f: ModelFit):
    """(J, r, names, x, lo, hi, unpack) of the fit-block residual over every free parameter of f, at f."""
    names, lo, hi, x, step, unpack = pb.space(f.lin, f.fx)
    r = pb.residual_fit(*unpack(x))
    J = np.empty((len(r), len(names)))

    def column(i):
        h = step[i] if x[i] + step[i] <= hi[i] else -step[i]
        xp = x.copy(); xp[i] += h
        J[:, i] = (pb.residual_fit(*unpack(xp)) - r) / h
    list(_POOL.map(column, range(len(names))))      # the simulators release the GIL
    return J, r, names, x, lo, hi, unpack


def intervals(pb: Problem, f: ModelFit, effects, seed: int = 0) -> dict[str, dict]:
    """name -> {key: (low, high)} for the named effects' fitted parameters (a projected line: its frequency)."""
    J, r, names, x, lo, hi, _ = _jacobian(pb, f)
    if not names:
        return {}
    blocks = pb.blk[pb.mfit]
    ids = np.unique(blocks)
    p = len(names)
    A = np.empty((len(ids), p, p)); g = np.empty((len(ids), p))
    for i, b in enumerate(ids):
        sel = blocks == b
        A[i] = J[sel].T @ J[sel]
        g[i] = J[sel].T @ r[sel]
    rng = np.random.default_rng(seed)
    ridge = 1e-12 * np.maximum(np.diag(A.sum(axis=0)), 1e-300)
    draws = np.empty((RESAMPLES, p))
    for k in range(RESAMPLES):
        c = rng.multinomial(len(ids), np.full(len(ids), 1.0 / len(ids)))
        Ak = np.tensordot(c, A, 1) + np.diag(ridge)
        try:
            d = -np.linalg.solve(Ak, c @ g)
        except np.linalg.LinAlgError:
            d = -np.linalg.lstsq(Ak, c @ g, rcond=None)[0]
        draws[k] = np.clip(x + d, lo, hi)
    a = 100 * (1 - LEVEL) / 2
    low, high = np.percentile(draws, a, axis=0), np.percentile(draws, 100 - a, axis=0)
    out: dict[str, dict] = {}
    for i, (grp, key) in enumerate(names):
        if grp in effects:
            out.setdefault(grp, {})[key] = (float(min(low[i], x[i])), float(max(high[i], x[i])))
    return out


def _without(pb: Problem, f: ModelFit, refit: ModelFit, name: str, round1: dict) -> ModelFit:
    """The model without the effect name, its linear parameters fitted again (see the module's docstring)."""
    others = [k for k in f.fx if k != name]
    if not others:
        return refit
    if len(others) == 1 and others[0] in round1:
        return round1[others[0]]
    without = {k: v for k, v in f.fx.items() if k != name}
    return pb.fit(f.lin, without, max_iter=6, rtol=1e-4)


def standings(pb: Problem, f: ModelFit, refit: ModelFit, effects, round1: dict | None = None,
              seed: int = 0) -> dict[str, Standing]:
    """Each named effect's interval, share and evidence (see the module's docstring); round1: each effect alone,
    fitted (the search's first round)."""
    iv = intervals(pb, f, effects, seed) if effects else {}
    nh = n_eff(int(pb.mhold.sum()), f)
    out = {}
    for name in effects:
        wo = _without(pb, f, refit, name, round1 or {})
        share = (wo.rss_hold - f.rss_hold) / max(refit.rss_hold, 1e-300)
        lr = nh * math.log(max(wo.rss_hold, 1e-300) / max(f.rss_hold, 1e-300))
        keys = pb.spec_keys(name) if not catalogue.get(name).projected else ("frequency_hz",)
        out[name] = Standing({k: iv.get(name, {}).get(k) for k in keys if iv.get(name, {}).get(k) is not None},
                             float(share), float(lr))
    return out

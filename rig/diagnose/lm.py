"""A small bounded Levenberg-Marquardt for a few parameters and many residuals (normal equations, forward
differences). scipy's trf spends most of its time in SVDs of the tall Jacobian; here J^T J is 8x8 at most."""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_POOL = ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1))


def lm_fit(fun, x0, lo, hi, step, *, max_iter: int = 20, rtol: float = 1e-5, near=None):
    """Minimise sum(fun(x)^2) within [lo, hi]. step: forward-difference step per parameter (its own units).
    near(xp, x), if given, is fun at xp, one difference step from the point x the fit stands on (which fun has
    evaluated): the Jacobian's columns, which may reuse what fun found at x."""
    lo = np.asarray(lo, float); hi = np.asarray(hi, float); step = np.asarray(step, float)
    x = np.clip(np.asarray(x0, float), lo, hi)
    r = fun(x); c = float(r @ r)
    lam = 1e-3
    n = len(x)
    for _ in range(max_iter):
        J = np.empty((len(r), n))

        def column(i):
            h = step[i] if x[i] + step[i] <= hi[i] else -step[i]
            xp = x.copy(); xp[i] += h
            J[:, i] = ((fun(xp) if near is None else near(xp, x)) - r) / h
        list(_POOL.map(column, range(n)))       # the simulators release the GIL: two cores share the columns
        with np.errstate(over="ignore", invalid="ignore"):
            g = J.T @ r
            A = J.T @ J
        if not (np.isfinite(J).all() and np.isfinite(A).all() and np.isfinite(g).all()):
            break                               # a model not computable one step away: no step to take from here
        d = np.sqrt(np.maximum(np.diag(A), 1e-300))
        An = A / np.outer(d, d); gn = g / d
        improved = False
        for _ in range(8):
            try:
                dx = -np.linalg.solve(An + lam * np.eye(n), gn) / d
            except np.linalg.LinAlgError:
                lam *= 10; continue
            xn = np.clip(x + dx, lo, hi)
            rn = fun(xn); cn = float(rn @ rn)
            if cn < c:
                rel = (c - cn) / c
                x, r, c = xn, rn, cn
                lam = max(lam / 5, 1e-9)
                improved = True
                break
            lam *= 8
        if not improved or rel < rtol:
            break
    return x, c

"""Where the search starts an effect's fit (an effect's definition names one of these as its `start`):

  Grid        the best of a few values of its first parameter, the others as the definition gives
  StandMode   a stand mode's frequency, damping and mass from the ratio of the measured FRF to the model's
  ForceLine   the strongest line the two-sensor test called a force
Each start returns (linear parameters, effects) to fit from, or None when there is nothing to start from.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.signal import csd, welch

from rig.diagnose.catalogue.effect import Scale
from rig.diagnose.lm import _POOL


def grid_best(pb, lins: list[dict], fx_base: dict, name: str, key: str, grid) -> tuple[dict, dict, float]:
    """The (linear parameters, effects, fit-block rss) of the best grid value of fx[name][key]."""
    jobs = []
    for lin in lins:
        for g in grid:
            fx = {n: dict(v) for n, v in fx_base.items()}
            fx.setdefault(name, {})[key] = float(g)
            jobs.append((lin, fx))

    def rss(job):
        r, _, _ = pb.residual(*job)
        return float(np.sum(r[pb.mfit] ** 2))
    costs = list(_POOL.map(rss, jobs))               # the simulators release the GIL
    i = int(np.argmin(costs))
    return jobs[i][0], jobs[i][1], costs[i]


@dataclass(frozen=True)
class Grid:
    """values(scale, slow, coarse) -> start values of the first parameter; slow: a slow effect is already in the
    model; coarse: nothing calls for a nonlinearity (a short grid). rest(scale) -> start values of the other
    parameters ({key: value} each), the grid tried at each (an effect of more than one parameter)."""
    values: Callable[[Scale, bool, bool], Sequence[float]]
    rest: Callable[[Scale], Sequence[dict]] | None = None

    def initial(self, pb, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean, slow: bool,
                coarse: bool):
        grid = self.values(pb.scale, slow, coarse)
        best = None
        for other in (self.rest(pb.scale) if self.rest else [{}]):
            base = {n: dict(v) for n, v in fx_base.items()}
            base.setdefault(name, {}).update(other)
            found = grid_best(pb, lins, base, name, pb.spec_keys(name)[0], grid)
            if best is None or found[2] < best[2]:
                best = found
        return best[0], best[1]


def _frf_ratio(pb, yhat: np.ndarray, y_clean: np.ndarray, f_lo: float, f_hi: float):
    """(frequencies, measured / model, weights) inside f_lo..f_hi."""
    if pb.broadband:
        # noise or steps: the command's content falls off fast, and one transform of the whole record (or a hard
        # mask) mixes in jumps at the ends, which the stand mode does not shape. Welch's averaged
        # H1 = S_my / S_mm of the continuous signals instead, the left-out samples filled with the model's
        nper = int(min(pb.n // 4, 4.0 * pb.fs))
        f, Smy = csd(yhat, np.where(pb.use, y_clean, yhat), fs=pb.fs, nperseg=nper)
        _, Smm = welch(yhat, fs=pb.fs, nperseg=nper)
        sel = np.flatnonzero((f > max(f_lo, 3.0)) & (f < f_hi) & (Smm > 0))
        return f[sel], Smy[sel] / Smm[sel], Smm[sel]
    w_use = pb.use.astype(float)
    Y = np.fft.rfft(y_clean * w_use); Ym = np.fft.rfft(yhat * w_use)
    f = np.fft.rfftfreq(pb.n, 1.0 / pb.fs)
    sel = np.flatnonzero((f > max(f_lo, 3.0)) & (f < f_hi) & (np.abs(Ym) > 0))
    sel = sel[:: max(1, len(sel) // 4000)]
    return f[sel], Y[sel] / Ym[sel], np.abs(Ym[sel]) ** 2


def stand_mode_from_frf(pb, name: str, lin: dict, fx_base: dict, f_lo: float, f_hi: float,
                        y_clean: np.ndarray) -> dict:
    """Stand-mode start from the FRF ratio measured / model: B(s) = (s^2+2zws+w^2) / ((1+mu) s^2+2zws+w^2)."""
    yhat = pb.model(lin, {k: v for k, v in fx_base.items() if k != name})
    f, R, w = _frf_ratio(pb, yhat, y_clean, f_lo, f_hi)
    s = 2j * math.pi * f
    best = (np.inf, (0.5 * sum(pb.base_band), 0.03, 0.2))
    fbs = np.geomspace(*pb.base_band, 160)
    wb = 2 * math.pi * fbs[:, None]
    ss_ = (s * s)[None, :]
    for zb in (0.01, 0.03, 0.08):
        num = ss_ + 2 * zb * wb * s[None, :] + wb * wb
        for mu in (0.05, 0.1, 0.2, 0.4):
            B = num / (num + mu * ss_)
            c = np.abs(R[None, :] - B) ** 2 @ w
            i = int(np.argmin(c))
            if c[i] < best[0]:
                best = (float(c[i]), (float(fbs[i]), zb, mu))
    fb, zb, mu = best[1]
    return {"frequency_hz": fb, "damping_ratio": zb, "mass_kg": pb.plant.moving_mass_kg(lin) / mu}


@dataclass(frozen=True)
class StandMode:
    """A mode of what the plant stands on, from the measured FRF over the model's (for each start of the linear
    parameters; the best by the fit blocks' rss)."""

    def initial(self, pb, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean, slow: bool,
                coarse: bool):
        best = None
        for lin in lins:
            fx = {n: dict(v) for n, v in fx_base.items()}
            fx[name] = stand_mode_from_frf(pb, name, lin, fx_base, min(band[0], pb.base_band[0]),
                                           pb.base_band[1] * 1.03, y_clean)
            r, _, _ = pb.residual(lin, fx)
            s = float(np.sum(r[pb.mfit] ** 2))
            if best is None or s < best[2]:
                best = (lin, fx, s)
        return best[0], best[1]


@dataclass(frozen=True)
class ForceLine:
    """The strongest force line (lines: the two-sensor test's, strongest first); none: nothing to start from."""

    def initial(self, pb, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean, slow: bool,
                coarse: bool):
        if not lines:
            return None
        fx = {n: dict(v) for n, v in fx_base.items()}
        fx[name] = {"frequency_hz": lines[0]["frequency_hz"]}
        return lins[0], fx

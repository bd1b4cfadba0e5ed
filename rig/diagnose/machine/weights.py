"""What the replay's residual should be under the right model, per bin and channel: the weights of every fit.

  s2 = the sensor's own noise (its top band, spectra.Spectra.noise)
     + with floor accelerometers, their noise carried into the prediction by the floor's response
       (sum over mounts of |gain Hg|^2 sigma_g^2 / w^4: the floor is an input known only through them)
     + |the model's own error|^2 (residual.own_error: the floor's path held between samples or continuous; two
       faithful models of one rig differ by that much)
then raised band by band where the refit's whitened residual is larger (the robust median: noise that is not
white, a sensor filter, what no catalogue effect explains) -- never lowered.
"""
from __future__ import annotations

import math

import numpy as np

from rig.diagnose.machine.residual import Evaluation, own_error
from rig.diagnose.machine.rigmodel import Base, modal, responses
from rig.diagnose.machine.spectra import BANDS_HZ, Spectra


def expected(sp: Spectra, base: Base, th: dict) -> np.ndarray:
    """s2 (K, 8) before the band inflation, from the model at theta at all of sp's bins."""
    md = modal(base, th)
    R = responses(base, th, sp.w, md=md)
    s2 = np.broadcast_to(sp.noise[:8], sp.Y.shape).copy()
    if sp.G is not None:
        g = R.gain_out[None, :, None]
        sg = sp.noise[8:12][None, None, :] / np.abs(R.gain_floor[None, None, :]) ** 2
        s2 += np.sum(np.abs(g * R.Hg) ** 2 * sg, axis=2) / (sp.w ** 4)[:, None]
    return s2 + np.abs(own_error(base, md, th, sp.w, sp.Y, sp.U, sp.G, np.sqrt(s2))) ** 2


def inflation(ev: Evaluation, f_hz: np.ndarray) -> np.ndarray:
    """(n_bands, 8): the factor each band's variance is raised by, per kind of sensor (accelerometers,
    strokes): the least over the four mounts of the median whitened residual power over the band's bins (over
    ln 2, the median of an exponential variable; corrected for what the floor projection keeps), at least 1.
    The least over the mounts, so that what one mount (or two) shows is never taken for noise."""
    out = np.ones((len(BANDS_HZ), ev.r.shape[1]))
    f = f_hz[ev.mask]
    for b, (lo, hi) in enumerate(BANDS_HZ):
        sel = (f >= lo) & (f < hi)
        if sel.sum() < 8:
            continue
        p = np.abs(ev.r[sel]) ** 2 / np.maximum(ev.keep[sel], 0.05)
        med = np.median(p, axis=0) / math.log(2)
        for a in (0, 4):                                   # accelerometers, stroke transducers
            out[b, a:a + 4] = max(1.0, float(np.min(med[a:a + 4])))
    return out


def inflated(s2: np.ndarray, factors: np.ndarray, f_hz: np.ndarray) -> np.ndarray:
    out = s2.copy()
    for b, (lo, hi) in enumerate(BANDS_HZ):
        sel = (f_hz >= lo) & (f_hz < hi)
        out[sel] *= factors[b][None, :]
    return out

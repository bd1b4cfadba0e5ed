"""`rig identify REC --plant FILE` for the families other than eha: the plant file's free parameters by output
error against the recorded position, the diagnosis's refit stage alone (rig.diagnose.problem.Problem: the sensor's
zero, or for an integrating plant the segment-wise initial states, projected out; fit and held-out blocks).

Uncertainty: 1 sigma from the Jacobian at the optimum with the residual's variance (white-residual assumption:
optimistic when the residual is far above the noise, as it is when the plant lacks physics -- run rig diagnose).
"""
from __future__ import annotations

import math
import time

import numpy as np

from rig.recordings import closedloop
from rig.diagnose.problem import Problem
from rig.diagnose.plants import at_bounds
from rig.errors import RecordingError
from rig.identify import poor_fit
from rig.plant.model import Plant
from rig.recordings.recording import check_plausible


def identify_plant(rec, plant: Plant, progress=None) -> dict:
    """{"parameters", "std", "start", "bounds", "fit", "closed_loop", "shooting"} of the plant's free
    parameters."""
    tick = progress or (lambda stage, frac: None)
    check_plausible(rec)
    unit = getattr(rec, "command_unit", "V")
    if plant.input_unit != unit:
        raise RecordingError(f"{rec.source}: the command is in {unit} but the plant ({plant.source}) takes "
                             f"input_unit = {plant.input_unit!r}")
    t0 = time.perf_counter()
    use = np.ones(rec.n, bool)
    use[: int(0.05 * rec.fs_hz)] = False
    pb = Problem(rec.command, rec.position_m, rec.fs_hz, plant, use)
    tick("nominal model", 0.0)
    nom = pb.evaluate(dict(pb.nominal), {}, k=0)
    pb = pb.with_(noise=float(np.sqrt(nom.rss_fit / max(pb.mfit.sum(), 1))) or 1.0)
    tick("output-error fit", 0.1)
    f = pb.fit(dict(pb.nominal), {}, max_iter=30)
    keys = list(pb.lin_keys)
    std = {}
    if keys:
        tick("uncertainty", 0.9)
        x = np.array([f.lin[k] for k in keys])
        r0 = pb.residual_fit(f.lin, {})
        J = np.empty((len(r0), len(keys)))
        for i, k in enumerate(keys):
            h = 1e-6 * max(abs(x[i]), 1e-12)
            J[:, i] = (pb.residual_fit({**f.lin, k: x[i] + h}, {}) - r0) / h
        s2 = float(r0 @ r0) / max(1, len(r0) - len(keys))
        cov = np.linalg.pinv(J.T @ J) * s2
        std = {k: float(math.sqrt(max(cov[i, i], 0.0))) for i, k in enumerate(keys)}
    y = pb.series(f)
    r = (pb.y - y)[use]
    yc = pb.y[use] - pb.y[use].mean()
    hold = math.sqrt(f.rss_hold / max(pb.mhold.sum(), 1))
    loop = closedloop.check(pb.cmd, pb.y, pb.fs, getattr(rec, "meta", None), stated=getattr(rec, "closed_loop", ""))
    out = {"plant": plant.family, "input_unit": plant.input_unit, "source": rec.source,
           "parameters": pb.plant.public_linear(f.lin), "std": std,
           "start": {k: plant.params[k].value for k in keys},
           "bounds": {k: [plant.params[k].lo, plant.params[k].hi] for k in keys},
           "at_bounds": list(at_bounds(pb.plant.bounds_lin, f.lin, keys, pb.plant.log_scale)),
           "fit": {"nrmse": float(np.sqrt(np.sum(r ** 2) / max(np.sum(yc ** 2), 1e-300))),
                   "residual_rms_m": float(np.sqrt(np.mean(r ** 2))), "holdout_residual_rms_m": hold,
                   "n_samples": rec.n, "fs_hz": rec.fs_hz},
           "closed_loop": loop.as_dict(), "timing_s": time.perf_counter() - t0}
    if pb.shoot is not None:
        out["shooting"] = pb.shoot.as_dict(pb.fs)
    poor = poor_fit(out["fit"]["nrmse"], f"the plant of {plant.source}")
    if poor:
        out["warning"] = poor
    if loop.closed:
        out["warning"] = (f"closed-loop data ({loop.reason}): the command carries the position's noise, so these "
                          "parameters can be biased" + (f"; also {poor}" if poor else ""))
    tick("done", 1.0)
    return out

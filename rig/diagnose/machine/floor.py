"""The floor: how it moved the four mounts, and whether it rocked as well as heaved.

The floor is the replay's input, not its model, so a floor that rocks leaves no mismatch in the replay. What
the model assumes about it (rig design's views, the simulated floor: a common heave plus an independent part
at each mount, sim_backend/rig_plant.py FloorMotion) is tested on the floor's motion itself, decomposed over
the mounts into its four patterns (MOUNTS order front_left, front_right, rear_left, rear_right):

  heave (+ + + +) / 2, pitch (+ + - -) / 2 (front against rear), roll (+ - + -) / 2 (left against right),
  twist (+ - - +) / 2

Independent motion at the mounts puts the same power into pitch, roll and twist; a rocking floor puts more into
pitch or roll. The test: that pattern's mean share of the non-common motion over twist's, bin by bin in the
floor's band (log ratio in standard errors taken from the bins' scatter). With floor accelerometers the floor is measured; without
them it is estimated bin by bin from the mounts through the model (least squares, the same weights as the
replay): what the four mounts cannot tell apart stays unknown, and the report says so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.diagnose.machine.effects import FLOOR_ROCKING, worth_naming
from rig.diagnose.machine.rigmodel import predict, modal, responses
from rig.diagnose.machine.residual import Replay

PATTERNS = {"heave": np.array([1, 1, 1, 1]) / 2, "pitch": np.array([1, 1, -1, -1]) / 2,
            "roll": np.array([1, -1, 1, -1]) / 2, "twist": np.array([1, -1, -1, 1]) / 2}
BAND_HZ = (1.0, 50.0)           # the floor's band (the paper's 1-50 Hz)
MIN_Z = 6.0


@dataclass(frozen=True)
class FloorMotion:
    measured: bool
    rms_m: dict                 # pattern -> rms displacement in BAND_HZ (m)
    n_bins: int
    axis: str                   # the rocking axis with the larger excess ("pitch" or "roll")
    ratio: float                # its mean share per bin over twist's
    z: float                    # log ratio in standard errors
    rocking_over_heave: float   # the rocking's rms over the common heave's (independent part taken out)

    @property
    def rocking(self) -> bool:
        return worth_naming(FLOOR_ROCKING, {"ratio": self.ratio}) and self.z >= MIN_Z


def floor_estimate(rp: Replay, th: dict, U=None) -> np.ndarray:
    """The floor's displacement (K, 4) at every bin: measured (floor accelerometers over -w^2) or estimated
    from the mounts through the model (weighted least squares, bin by bin)."""
    sp = rp.sp
    md = modal(rp.base, th)
    if sp.G is not None:
        return -(sp.G / md.gain_floor[None, :]) / (sp.w ** 2)[:, None]
    R = responses(rp.base, th, sp.w, md=md)
    sd = np.sqrt(rp.s2)
    e = (sp.Y - predict(md, sp.w, sp.U if U is None else U, None) * md.gain_out[None, :]) / sd
    A = R.Hg * md.gain_out[None, :, None] / sd[:, :, None]
    AH = np.conj(np.transpose(A, (0, 2, 1)))
    return np.linalg.solve(AH @ A, (AH @ e[:, :, None]))[:, :, 0]


def floor_motion(rp: Replay, th: dict, U=None) -> FloorMotion:
    sp = rp.sp
    X = floor_estimate(rp, th, U)
    sel = (sp.f_hz >= BAND_HZ[0]) & (sp.f_hz <= BAND_HZ[1])
    Xb = X[sel]
    step = max(1, int(round(np.median(np.diff(sp.bin_index)))))
    per_bin = {k: np.abs(Xb @ p) ** 2 for k, p in PATTERNS.items()}
    power = {k: float(np.sum(v)) for k, v in per_bin.items()}
    rms = {k: math.sqrt(2 * step * v) / sp.n for k, v in power.items()}
    n = int(sel.sum())
    # the test on each bin's shares of the non-common motion: the floor's spectrum falls steeply (1/f in
    # displacement), so sums of raw power rest on the lowest few bins and their ratio scatters far more than
    # 4 / n_bins says; shares weigh every bin alike, and their scatter is taken from the data
    rest = np.maximum(per_bin["pitch"] + per_bin["roll"] + per_bin["twist"], 1e-300)
    share = {k: per_bin[k] / rest for k in ("pitch", "roll", "twist")}
    axis = max(("pitch", "roll"), key=lambda a: float(np.mean(share[a])))
    a, b = share[axis], share["twist"]
    ma, mb = max(float(np.mean(a)), 1e-300), max(float(np.mean(b)), 1e-300)
    ratio = ma / mb
    cov = np.cov(np.vstack([a, b])) if n > 2 else np.full((2, 2), np.inf)
    se = math.sqrt(max(cov[0, 0] / ma ** 2 + cov[1, 1] / mb ** 2 - 2 * cov[0, 1] / (ma * mb), 1e-300) / max(n, 1))
    z = math.log(ratio) / se
    tw = power["twist"]
    excess = max(power[axis] - tw, 0.0)
    heave = max(power["heave"] - tw, 1e-300)
    return FloorMotion(sp.G is not None, rms, n, axis, ratio, z, math.sqrt(excess / heave))

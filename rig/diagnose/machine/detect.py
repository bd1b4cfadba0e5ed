"""What this recording can tell: for each instance of the catalogue, the smallest size at which the diagnosis
would name it, from how much a typical size of it would move the replay's whitened held-out residual (the
noncentrality of its test, with this record's inputs, noise and nuisance terms; Kaufman's projection).

An effect is named when it cuts the held-out residual by MIN_GAIN and passes the likelihood ratio; the
noncentrality grows as the square of a small effect's size, so the smallest size named is
typical x sqrt(needed / noncentrality). Without floor accelerometers the same figure with the floor as if
measured (its estimate from the mounts taken for the measurement) says what fitting them would add.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.diagnose.machine import effects as fx
from rig.diagnose.machine.fitting import MIN_GAIN
from rig.diagnose.machine.residual import Replay

@dataclass(frozen=True)
class Detectability:
    key: str
    effect: str
    location: str
    smallest: float             # the smallest size named: relative (%), a factor (x), or absolute
    unit: str
    smallest_with_floor: float | None     # without floor accelerometers: the same with the floor measured

    def text(self) -> str:
        def fmt(v):
            if not math.isfinite(v):
                return "not at any size"
            if self.unit == "%":
                return f"+-{v:.1f} %"
            if self.unit == "x":
                return f"x{v:.2f}" if v < 100 else "beyond x100"
            if self.unit == "s":
                return f"{v * 1e3:.3g} ms"
            return f"{v:.3g} {self.unit}"
        s = f"{self.effect} at {self.location}: from {fmt(self.smallest)}"
        if self.smallest_with_floor is not None:
            s += f" (with floor accelerometers: {fmt(self.smallest_with_floor)})"
        return s


def _typical(th: dict, inst: fx.Instance):
    size, unit = inst.effect.typical
    slot = inst.slots[0]
    out = {k: np.array(v, copy=True) for k, v in th.items()}
    v0 = out[slot.key][slot.index]
    out[slot.key][slot.index] = v0 * size if unit in ("%", "x") else v0 + size
    return out, size, unit


def _smallest(lam: float, needed: float, size: float, unit: str) -> float:
    """The size whose noncentrality reaches `needed` (inf beyond a hundred times the typical one)."""
    if lam <= 0 or needed > 1e4 * lam:
        return math.inf
    k = math.sqrt(needed / lam)
    if unit == "%":
        return 100 * (size - 1.0) * k
    if unit == "x":
        return math.exp(math.log(size) * k)
    return size * k


def _least(eff: fx.Effect, unit: str) -> float:
    """The effect's least size worth naming (effects.Effect.least) in the unit of its smallest size: below it
    nothing is named, however strong the evidence (a relative least for a "%" size)."""
    if eff.size is None:
        return 0.0
    return 100 * eff.least if unit == "%" else eff.least


def detectability(rp: Replay, th: dict, mask: np.ndarray, U_of, ctx, *, rp_floor: Replay | None = None) -> list:
    """Per instance of the replay's catalogue (valve effects included whether the valves moved or not)."""
    at = rp.evaluate(th, mask, U=U_of(th))
    at_f = rp_floor.evaluate(th, mask, U=U_of(th)) if rp_floor is not None else None
    n = at.r.size
    needed = max(MIN_GAIN * at.rss, 0.5 * math.log(2 * n) + 2.0)
    out = []
    for inst in fx.instances(ctx, valves_driven=True):
        if not inst.effect.typical:
            continue
        th1, size, unit = _typical(th, inst)
        lam = float(np.sum(np.abs(rp.linear(th1, at, U=U_of(th1)) - at.r) ** 2))
        with_floor = None
        if at_f is not None:
            lam_f = float(np.sum(np.abs(rp_floor.linear(th1, at_f, U=U_of(th1)) - at_f.r) ** 2))
            with_floor = _smallest(lam_f, max(MIN_GAIN * at_f.rss, needed), size, unit)
        least = _least(inst.effect, unit)
        out.append(Detectability(inst.key, inst.effect.name, inst.location, max(_smallest(lam, needed, size, unit),
                                 least), unit, None if with_floor is None else max(with_floor, least)))
    return out

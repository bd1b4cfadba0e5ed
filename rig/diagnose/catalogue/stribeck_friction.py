"""stribeck_friction: friction above its sliding (Coulomb) level at low speed, the breakaway force F_s that fades
with speed: F(v) = (F_c + F_s exp(-(v / v_S)^2)) tanh(v / v_s), v_S the Stribeck velocity (lubricated contacts:
the carriage's guides, a screw's nut). It sits on a Coulomb level: it is fitted and named only on top of the
coulomb_friction entry, whose force_n is F_c."""
from dataclasses import dataclass

import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid

COULOMB = "coulomb_friction"                 # the sliding level it rises above
STRIBECK_VELOCITIES_M_PER_S = (2e-3, 8e-3, 3e-2)     # the start's Stribeck velocities: lubricated guides, screws


@dataclass(frozen=True)
class _OnCoulomb(Grid):
    """The grid's start, only where the model already holds a Coulomb level (without one there is no level for a
    breakaway to rise above: the fit would be a low-speed Coulomb friction under another name)."""

    def initial(self, pb, name, lins, fx_base, *rest):
        if COULOMB not in fx_base:
            return None
        return super().initial(pb, name, lins, fx_base, *rest)


def _on_coulomb(pb, f, name: str) -> bool:
    return COULOMB in f.fx


EFFECT = Effect(
    name="stribeck_friction", short="strib", order=92, families=("mechanical_axis",), needs_load=True,
    params=(Param("breakaway_n", "N"), Param("stribeck_velocity_m_per_s", "mm/s", 1e3)),
    meaning=lambda family, load: "breakaway friction breakaway_n above the Coulomb level, fading as "
                                 "exp(-(v / stribeck_velocity)^2) (Stribeck)",
    # the breakaway above zero (its lower edge: no breakaway) and the Stribeck velocity from a lubricated
    # guide's fraction of a mm/s to a fifth of a metre per second (beyond it: a Coulomb level)
    bounds=lambda s: [(1e-4 * s.peak_force_n, 2.0 * s.peak_force_n), (2e-4, 0.2)],
    start=_OnCoulomb(lambda s, slow, coarse: s.peak_force_n * np.array(
        [0.02, 0.08] if (coarse or slow) else [0.01, 0.03, 0.08, 0.2]),
        lambda s: [{"stribeck_velocity_m_per_s": v} for v in STRIBECK_VELOCITIES_M_PER_S]),
    slow=True, nonlinear=True, costly_start=True, edge_test=True, check=_on_coulomb,
    evidence=Evidence("velocity", "friction above the sliding level at low speed: a breakaway at each start from "
                                  "rest and a residual near zero velocity that the Coulomb level leaves"),
    terms={"axis_model": lambda p, u: {"stribeck_n": p["breakaway_n"],
                                       "stribeck_m_per_s": p["stribeck_velocity_m_per_s"]},
           "axis": lambda p, u: {"stribeck_n": p["breakaway_n"],
                                 "stribeck_m_per_s": p["stribeck_velocity_m_per_s"]}},
    draws={"axis": Draw(6, lambda rng, c: ({"breakaway_n": float(rng.uniform(0.05, 0.15) * c.F_peak),
                                            "stribeck_velocity_m_per_s": float(10 ** rng.uniform(-2.5, -1.7))},
                                           {}), with_=(COULOMB,))},
)

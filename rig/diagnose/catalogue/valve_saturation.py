"""valve_saturation: the valve driver's current clipped at +-limit before the spool (the paper's actuator)."""
import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid

EFFECT = Effect(
    name="valve_saturation", short="sat", order=40, families=("eha",),
    params=(Param("limit_ma", "mA"),),
    meaning=lambda family, load: "driver current clipped before the spool",
    bounds=lambda s: [(0.03 * s.peak, 1.02 * s.peak)],
    start=Grid(lambda s, slow, coarse: s.peak * np.array([0.2, 0.35, 0.5, 0.6, 0.7, 0.8, 0.88, 0.94, 0.98])),
    nonlinear=True, costly_start=True,
    evidence=Evidence("amplitude", "gain loss at large command with odd distortion"),
    terms={"eha_model": lambda p, u: {"sat_ma": p["limit_ma"]},
           "stand": lambda p, u: {"saturation_limit_ma": p["limit_ma"]}},
    draws={"stand": Draw(3, lambda rng, c: ({"limit_ma": round(float(rng.uniform(0.5, 0.85) *
                                                                       (c.p.K_v * c.amplitude_V)), 3)}, {}))},
)

"""input_saturation: a plant file's command clipped at +-limit before the drive (a drive's current limit, a
converter's range)."""
import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid

EFFECT = Effect(
    name="input_saturation", short="sat", order=60, families=("mechanical_axis", "transfer_function"),
    params=(Param("limit_{u}", "{u}"),),
    meaning=lambda family, load: "the command clipped at +-limit before the drive",
    bounds=lambda s: [(0.03 * s.peak, 1.02 * s.peak)],
    start=Grid(lambda s, slow, coarse: s.peak * np.array([0.2, 0.35, 0.5, 0.6, 0.7, 0.8, 0.88, 0.94, 0.98])),
    nonlinear=True,
    evidence=Evidence("amplitude", "gain loss at large command with odd distortion"),
    terms={"axis_model": lambda p, u: {"saturation": p[f"limit_{u}"]},
           "axis": lambda p, u: {"saturation": p[f"limit_{u}"]}},
    draws={"axis": Draw(2, lambda rng, c: ({f"limit_{c.u}": float(rng.uniform(0.45, 0.75) * c.u_peak)}, {}),
                        loop_scaled=True)},
)

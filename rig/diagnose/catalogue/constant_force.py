"""constant_force: a constant force on the load (a cable, a weight component, the drive's offset)."""
import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid

EFFECT = Effect(
    name="constant_force", short="force", order=80, families=("mechanical_axis", "transfer_function"),
    needs_load=True,
    params=(Param("force_n", "N"),),
    meaning=lambda family, load: "a constant force on the load (a cable, a weight component, the drive's offset)",
    bounds=lambda s: [(-s.peak_force_n, s.peak_force_n)],
    # linear in the force: a coarse start, the fit does the rest
    start=Grid(lambda s, slow, coarse: s.peak_force_n * np.array([-0.1, -0.03, -0.01, 0.0, 0.01, 0.03, 0.1])),
    evidence=Evidence("velocity", "a residual that a constant force on the load explains (position drifting one "
                                  "way under the same command)"),
    terms={"axis_model": lambda p, u: {"force_n": p["force_n"]},
           "axis": lambda p, u: {"constant_force_n": p["force_n"]}},
    draws={"axis": Draw(5, lambda rng, c: ({"force_n": float(rng.choice([-1, 1]) * rng.uniform(0.02, 0.08) *
                                                             c.F_peak)}, {}))},
)

"""input_deadband: no drive output within +-width of a plant file's command (static, before the drive)."""
import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid

EFFECT = Effect(
    name="input_deadband", short="dead", order=70, families=("mechanical_axis", "transfer_function"),
    params=(Param("width_{u}", "{u}"),),
    meaning=lambda family, load: "no drive output within +-width of the command",
    bounds=lambda s: [(0.0, 0.6 * s.peak)],
    # a fraction of the peak command (the model is static: no coarse grid)
    start=Grid(lambda s, slow, coarse: s.peak * np.array([0.003, 0.01, 0.03, 0.06, 0.1, 0.2, 0.35])),
    nonlinear=True,
    evidence=Evidence("amplitude", "gain loss at small command, distortion at command zero crossings"),
    terms={"axis_model": lambda p, u: {"deadband": p[f"width_{u}"]},
           "axis": lambda p, u: {"deadband": p[f"width_{u}"]}},
    # drawn with a saturation it gives way to friction (the two static input terms together are not a case)
    draws={"axis": Draw(3, lambda rng, c: ({f"width_{c.u}": float(rng.uniform(0.04, 0.12) * c.u_peak)}, {}),
                        not_with=("input_saturation",), instead="coulomb_friction")},
)

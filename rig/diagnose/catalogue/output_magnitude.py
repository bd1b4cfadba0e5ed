"""output_magnitude: a sensor that cannot see the sign of what it measures (a pulse counter, a speed read from an
encoder's pulse rate without its direction): it reads |y| of the plant's output y. Its parameter is the command's
offset before the drive, which moves the output's zero: under |.| an offset no longer passes into the sensor's
own offset (a linear model's output offset does), so the magnitude's shape depends on it."""
import numpy as np

from rig.diagnose.catalogue.effect import Effect, Evidence, Param
from rig.diagnose.starts import Grid

EFFECT = Effect(
    name="output_magnitude", short="|y|", order=95, families=("mechanical_axis", "transfer_function"),
    params=(Param("bias_{u}", "{u}"),),
    meaning=lambda family, load: "the sensor reads the magnitude |y| of the output (it cannot see its sign); "
                                 "bias: the command's offset before the drive",
    bounds=lambda s: [(-0.5 * s.peak, 0.5 * s.peak)],
    start=Grid(lambda s, slow, coarse: s.peak * np.array([-0.1, 0.0, 0.1])),
    nonlinear=True,
    evidence=Evidence("amplitude", "an output that never changes sign while the command does, and doubles the "
                                   "command's frequencies"),
    terms={"axis_model": lambda p, u: {"rectify": True, "bias": p[f"bias_{u}"]}},
)

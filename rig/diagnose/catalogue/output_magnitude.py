"""output_magnitude: a sensor that cannot see the sign of what it measures (a pulse counter, a speed read from an
encoder's pulse rate without its direction): it reads |y| of the plant's output y. Its parameter is the command's
offset before the drive, which moves the output's zero: under |.| an offset no longer passes into the sensor's
own offset (a linear model's output offset does), so the magnitude's shape depends on it."""
import numpy as np

from rig.diagnose import catalogue        # the registry (used at call time: it imports this module)

from rig.diagnose.catalogue.effect import Effect, Evidence, Param
from rig.diagnose.starts import Grid

MIN_SIDE = 0.2            # the fitted output runs each way at least a fifth of the time
MIN_CROSSINGS = 4


def _runs_both_ways(pb, f, name: str) -> bool:
    """A sensor blind to the sign shows only on a motion that runs both ways: the fitted model's output, before the
    magnitude, must change sign at least MIN_CROSSINGS times and spend at least MIN_SIDE of the used samples on
    each side. A V-shaped bend fitted to a plant nonlinear some other way (a tank's square-root outflow: an output
    on one side 95 % of the time) is no sensor's."""
    bias = f.fx[name][pb.spec_keys(name)[0]]
    others = {k: v for k, v in catalogue.simulated(f.fx).items() if k != name}
    y = pb.plant.simulate(f.lin, pb.cmd + bias, pb.fs, others)[pb.use]
    crossings = int(np.sum(np.sign(y[1:]) != np.sign(y[:-1])))
    up = float(np.mean(y > 0))
    return crossings >= MIN_CROSSINGS and min(up, 1.0 - up) >= MIN_SIDE


EFFECT = Effect(
    name="output_magnitude", short="|y|", order=95, families=("mechanical_axis", "transfer_function"),
    params=(Param("bias_{u}", "{u}"),),
    meaning=lambda family, load: "the sensor reads the magnitude |y| of the output (it cannot see its sign); "
                                 "bias: the command's offset before the drive",
    bounds=lambda s: [(-0.5 * s.peak, 0.5 * s.peak)],
    start=Grid(lambda s, slow, coarse: s.peak * np.array([-0.1, 0.0, 0.1])),
    nonlinear=True, check=_runs_both_ways,
    evidence=Evidence("amplitude", "an output that never changes sign while the command does, and doubles the "
                                   "command's frequencies"),
    terms={"axis_model": lambda p, u: {"rectify": True, "bias": p[f"bias_{u}"]}},
)

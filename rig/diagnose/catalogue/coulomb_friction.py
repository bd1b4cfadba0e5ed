"""coulomb_friction: friction F_c tanh(v / v_s) against the motion of the load (the actuator's seals: v_s =
2e-5 m/s, as the recordings' simulator; a plant file's carriage: v_s = 1e-7 m/s, it sticks)."""
import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid


def _grid(s, slow: bool, coarse: bool):
    if s.family == "eha":
        return [60, 200, 600] if (coarse or slow) else [3, 40, 100, 200, 400, 800, 1400]
    frac = [0.01, 0.05, 0.2] if (coarse or slow) else [0.003, 0.01, 0.03, 0.07, 0.15, 0.3, 0.6]
    return s.peak_force_n * np.array(frac)        # a fraction of the peak drive force


EFFECT = Effect(
    name="coulomb_friction", short="fric", order=90,
    families=("eha", "mechanical_axis", "transfer_function"), needs_load=True,
    params=(Param("force_n", "N"),),
    meaning=lambda family, load: ("seal friction force_n tanh(v / 2e-5 m/s)" if family == "eha" else
                                  "friction force_n tanh(v / 1e-07 m/s) against the motion"),
    bounds=lambda s: [(0.0, 5000.0)] if s.family == "eha" else [(0.0, 2.0 * s.peak_force_n)],
    start=Grid(_grid), slow=True, nonlinear=True,
    evidence=Evidence("velocity", "distortion at velocity reversals, largest at low velocity"),
    terms={"eha_model": lambda p, u: {"fric_n": p["force_n"]},
           "axis_model": lambda p, u: {"friction_n": p["force_n"]},
           "stand": lambda p, u: {"friction_force_n": p["force_n"]},
           "axis": lambda p, u: {"coulomb_n": p["force_n"]}},
    draws={"stand": Draw(5, lambda rng, c: ({"force_n": round(float(rng.uniform(150.0, 600.0)), 1)}, {})),
           "axis": Draw(4, lambda rng, c: ({"force_n": float(rng.uniform(0.05, 0.2) * c.F_peak)}, {}))},
)

"""valve_deadband: spool overlap, no flow while the spool is within +-width of centre (the paper's actuator)."""
from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid


def _grid(s, slow: bool, coarse: bool):
    grid = [0.15, 0.4, 1.0] if (coarse or slow) else [0.01, 0.08, 0.15, 0.3, 0.5, 0.7, 1.0, 1.5]
    return [g for g in grid if g < 0.6 * s.peak] or [0.1 * s.peak]


EFFECT = Effect(
    name="valve_deadband", short="dead", order=50, families=("eha",),
    params=(Param("width_ma", "mA"),),
    meaning=lambda family, load: "spool overlap: no flow within +-width",
    bounds=lambda s: [(0.0, 0.6 * s.peak)],
    start=Grid(_grid), slow=True, nonlinear=True,
    evidence=Evidence("amplitude", "gain loss at small command, distortion at command zero crossings"),
    terms={"eha_model": lambda p, u: {"dead_ma": p["width_ma"]},
           "stand": lambda p, u: {"deadband_width_ma": p["width_ma"]}},
    draws={"stand": Draw(4, lambda rng, c: ({"width_ma": round(float(rng.uniform(0.2, 1.0)), 3)}, {}))},
)

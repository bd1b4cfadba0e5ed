"""backlash: play in the transmission between the drive and the load the sensor reads (gears, a coupling, a
worn nut). The load stays where it is until the drive has crossed the play, then is pushed by its near side:
after each reversal the reading stands still while the model moves, and on each direction of travel the reading
lags the drive by half the play (rig/plant/zoh.py play; the load's own inertia small)."""
from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid

LARGEST_M = 0.02       # a transmission's play up to 20 mm at the load (a worn rack, a slack belt)

EFFECT = Effect(
    name="backlash", short="play", order=93, families=("mechanical_axis",), outputs=("position",),
    params=(Param("width_m", "mm", 1e3),),
    meaning=lambda family, load: "play of width_m (total) between the drive and the load the sensor reads",
    bounds=lambda s: [(0.0, LARGEST_M)],
    start=Grid(lambda s, slow, coarse: [1e-4, 1e-3] if (coarse or slow) else [2e-5, 1e-4, 3e-4, 1e-3, 3e-3]),
    nonlinear=True,
    # the load stays put until the drive crosses the play: the reading is not linear in the drive's state at a
    # segment's start, so the segment states are refined as friction's are (without it a Coulomb friction of 0 N
    # beside a play "removed" 88 % of the held-out residual: its slow model's state refinement did)
    state_nonlinear=True,
    evidence=Evidence("velocity", "the reading stands still after each reversal while the drive crosses the "
                                  "play, then lags the model by half the play"),
    terms={"axis_model": lambda p, u: {"backlash_m": p["width_m"]},
           "axis": lambda p, u: {"backlash_m": p["width_m"]}},
    draws={"axis": Draw(7, lambda rng, c: ({"width_m": float(rng.uniform(2e-4, 1.5e-3))}, {}))},
)

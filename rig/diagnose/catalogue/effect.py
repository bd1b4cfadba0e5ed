"""What one effect of the catalogue is: its definition (`Effect`) and the parts it is made of.

An effect is physics a plant's linear model leaves out. Its definition says everything the diagnosis, the
report and the blind proofs need to know of it; the code that fits, reports or draws effects asks the
definition and never the effect's name (tests/structure/test_catalogue.py)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

# the simulators an effect has a term in (its parameters -> that simulator's keyword arguments):
#   "eha_model"   rig.diagnose.models sim_linear / sim_reduced (the diagnosis's model of the paper's actuator)
#   "axis_model"  rig.diagnose.plants AxisModel -> rig.plant.zoh run_segments (a plant file's axis)
#   "stand"       sim_backend.actuator Effects -> simulate_stand (the proof's recordings of the actuator)
#   "axis"        sim_backend.axis Axis -> simulate_axis (the proof's recordings of a plant file's axis)
SIMULATORS = ("eha_model", "axis_model", "stand", "axis")


@dataclass(frozen=True)
class Param:
    """A parameter in SI units. `key` and `unit` may hold "{u}", the plant's input unit (limit_{u} -> limit_V);
    the report shows value x scale in `unit`."""
    key: str
    unit: str = ""
    scale: float = 1.0

    def key_for(self, u: str) -> str:
        return self.key.format(u=u)

    def unit_for(self, u: str) -> str:
        return self.unit.format(u=u)


@dataclass(frozen=True)
class Scale:
    """What an effect's bounds and start grid are relative to, for one recording on one plant."""
    family: str
    fs: float                      # sample rate, Hz
    peak: float                    # peak command on the effect's scale (eha: driver current, mA; else its unit)
    peak_force_n: float            # peak drive force (a plant with a load; nan for eha)
    mass_kg: float                 # nominal moving mass


@dataclass(frozen=True)
class Evidence:
    """Which plot shows the effect (rig/diagnose/evidence.py: "amplitude" gain by level or distortion, "velocity"
    residual by velocity, "frf" the response over the model without it, "line" both sensors around a line), the
    one-line signature it leaves in the data, and for "frf" the finding from its parameters and the band."""
    kind: str
    signature: str
    finding: Callable[[dict, tuple], str] | None = None


@dataclass(frozen=True)
class Draw:
    """How a blind proof draws the effect. `rank`: its place in that proof's catalogue (the cases' random draws
    follow it). `draw(rng, ctx) -> (parameters, simulator-only extras)`; ctx holds what the proof knows (see
    rig/diagnose/prove.py and prove_axis.py). `apart_from_pickup`: a line drawn away from the sensor's pickup
    lines; `not_with`/`instead`: drawn together with one of not_with it gives way to `instead`; `with_`: always drawn
    together with these (a breakaway above a Coulomb level needs that level); `loop_scaled`: in
    closed loop its first parameter is drawn again against the peak command the loop asks for."""
    rank: int
    draw: Callable[[Any, Any], tuple[dict, dict]]
    apart_from_pickup: bool = False
    not_with: tuple[str, ...] = ()
    instead: str | None = None
    with_: tuple[str, ...] = ()
    loop_scaled: bool = False


@dataclass(frozen=True)
class Effect:
    """One effect: one definition, in one module of rig/diagnose/catalogue/.

    order       its place in the search (the candidates of a round are tried in this order)
    families    the plant families it applies to (rig/plant/model.py FAMILIES); needs_load: only where the
                model has a load for a force to act on; outputs: only on a plant whose sensor reads one of these
                (rig/plant/model.py Plant.output; empty: any)
    params      the fitted parameters, in order; reported: what the report adds (computed by the engine)
    meaning     one line for people, given the plant's family and whether it has a load
    bounds      Scale -> [(lo, hi)] per fitted parameter (physical: wider than any plausible rig)
    start       how the search starts its fit (rig/diagnose/starts.py: a grid, the FRF, a line)
    evidence    the plot and the signature (above)
    terms       simulator name -> (params, input unit) -> that simulator's keyword arguments
    draws       proof name ("stand": rig prove, "axis": rig prove --plant) -> Draw
    slow        simulated by the reduced nonlinear model (friction, spool deadband): screened, refined last
    nonlinear   makes harmonics of the excitation (worth fitting when distortion shows)
    projected   a line whose amplitude and phase are projected out (not simulated); its frequency is fitted by
                a line search; it is tried only when the two-sensor test found a force line
    in_band     its first parameter is a frequency told apart only inside the excited band
    edge_test   pinned at the edge of its range it is not named (three parameters spent on nothing)
    costly_start refined only when its start already rivals the best candidate
    derived     (fitted parameters, sample rate) -> values the report adds in other words (a delay in samples)
    check       (problem, fit, name) -> does the fitted effect show in the data the way the physics says it must
                (beyond the held-out tests: a sensor reading |y| reads its floor where y changes sign)
    state_nonlinear  its reading answers a segment's initial state only in part (a play's load does not move
                while the drive is inside the play): under multiple shooting the segment states are refined by
                Gauss-Newton steps, as for every slow effect (the sticking of friction), until they settle
    """
    name: str
    short: str
    order: int
    families: tuple[str, ...]
    params: tuple[Param, ...]
    meaning: Callable[[str, bool], str]
    bounds: Callable[[Scale], list[tuple[float, float]]]
    start: Any
    evidence: Evidence
    terms: Mapping[str, Callable[[dict, str], dict]]
    draws: Mapping[str, Draw] = field(default_factory=dict)
    reported: tuple[Param, ...] = ()
    needs_load: bool = False
    outputs: tuple[str, ...] = ()
    slow: bool = False
    nonlinear: bool = False
    projected: bool = False
    in_band: bool = False
    edge_test: bool = False
    costly_start: bool = False
    derived: Callable[[dict, float], dict] | None = None
    check: Callable[[Any, Any, str], bool] | None = None
    state_nonlinear: bool = False

    def keys(self, u: str = "V") -> tuple[str, ...]:
        """The fitted parameters' keys for a plant whose input is in unit u."""
        return tuple(p.key_for(u) for p in self.params)

    @property
    def n_free(self) -> int:
        """Fitted physics parameters it adds (a projected line: its frequency, amplitude and phase)."""
        return len(self.params) + (2 if self.projected else 0)

    @property
    def has_state_nonlinearity(self) -> bool:
        """Its response is not linear in a segment's initial state: a slow model's (friction sticks, a spool's
        deadband) or one declared so (a play)."""
        return self.slow or self.state_nonlinear

    def applies_to(self, family: str, has_load: bool, output: str = "position") -> bool:
        return family in self.families and (has_load or not self.needs_load) and \
            (not self.outputs or output in self.outputs)

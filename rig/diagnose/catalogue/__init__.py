"""The effect catalogue: one definition per effect, one module each (rig/diagnose/catalogue/<name>.py, an
`EFFECT = Effect(...)`; the parts: effect.py). Every module of this package that defines EFFECT is in the
catalogue: a new effect is its definition here plus its term in the simulators it names (docs/ARCHITECTURE.md,
"An effect").

One registry serves the plants (which effects apply), the engine (bounds, starts, how each is fitted), the
evidence and the report (plots, signatures, units) and the blind proofs (draws, the simulators' arguments)."""
from __future__ import annotations

import importlib
import pkgutil

from rig.diagnose.catalogue.effect import SIMULATORS, Draw, Effect, Evidence, Param, Scale
from rig.plant.model import INPUT_UNITS
from sim_backend.actuator import Effects

__all__ = ["Draw", "Effect", "Evidence", "Param", "Scale", "EFFECTS", "get", "for_plant", "for_proof",
           "simulated", "projected", "slow_in", "state_nonlinear_in", "fast", "line_frequency", "terms", "display_units", "short",
           "stand_effects"]


def _discover() -> dict[str, Effect]:
    found = []
    for m in pkgutil.iter_modules(__path__):
        effect = getattr(importlib.import_module(f"{__name__}.{m.name}"), "EFFECT", None)
        if isinstance(effect, Effect):
            found.append(effect)
    names = [e.name for e in found]
    if len(set(names)) != len(names):
        raise RuntimeError(f"rig/diagnose/catalogue: an effect defined twice ({sorted(names)})")
    return {e.name: e for e in sorted(found, key=lambda e: (e.order, e.name))}


EFFECTS: dict[str, Effect] = _discover()       # name -> definition, in the search's order


def get(name: str) -> Effect:
    try:
        return EFFECTS[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r} (known: {', '.join(EFFECTS)})") from None


def for_plant(family: str, has_load: bool, output: str = "position") -> dict[str, Effect]:
    """The effects that apply to a plant family (with a load or not, its sensor reading `output`), in the search's
    order."""
    return {n: e for n, e in EFFECTS.items() if e.applies_to(family, has_load, output)}


def for_proof(proof: str) -> tuple[str, ...]:
    """The names a blind proof draws from ("stand": rig prove; "axis": rig prove --plant), in its order."""
    return tuple(sorted((n for n, e in EFFECTS.items() if proof in e.draws), key=lambda n: EFFECTS[n].draws[proof].rank))


def simulated(fx: dict) -> dict:
    """The effects a simulator runs (a projected line is fitted on the residual instead)."""
    return {k: v for k, v in fx.items() if not get(k).projected}


def projected(fx: dict) -> str | None:
    """The name of the projected line effect in fx, if any."""
    return next((k for k in fx if get(k).projected), None)


def slow_in(fx) -> bool:
    """A slow (reduced nonlinear) effect among fx's names."""
    return any(get(k).slow for k in fx)


def state_nonlinear_in(fx) -> bool:
    """An effect among fx's names whose response is not linear in a segment's initial state."""
    return any(get(k).has_state_nonlinearity for k in fx)


def terms(simulator: str, fx: dict, u: str = "V") -> dict:
    """A simulator's keyword arguments for the effects fx ({name: {key: value}}); an effect without a term in
    it is refused."""
    if simulator not in SIMULATORS:
        raise ValueError(f"unknown simulator {simulator!r} (known: {', '.join(SIMULATORS)})")
    kw = {}
    for name, prm in fx.items():
        term = get(name).terms.get(simulator)
        if term is None:
            raise ValueError(f"effect {name!r} has no term in the {simulator} simulator")
        kw.update(term(prm, u))
    return kw


def display_units() -> dict[str, tuple[float, str]]:
    """Parameter key -> (scale, unit) the report shows it in, from every effect's parameters."""
    out = {}
    for e in EFFECTS.values():
        for p in e.params + e.reported:
            for u in INPUT_UNITS:
                out[p.key_for(u)] = (p.scale, p.unit_for(u))
    return out


def short(name: str) -> str:
    """The short name of an effect (proof tables); an unknown name as it is."""
    e = EFFECTS.get(name)
    return e.short if e is not None else name


def fast(fx: dict) -> dict:
    """The effects the exact linear-time simulators run (neither slow nor projected)."""
    return {k: v for k, v in fx.items() if not get(k).slow and not get(k).projected}


def line_frequency(fx: dict) -> float | None:
    """The frequency of the projected line in fx (a projected effect's first parameter is its frequency_hz)."""
    name = projected(fx)
    return None if name is None else fx[name]["frequency_hz"]


def stand_effects(effects: dict, **extra) -> Effects:
    """The recordings' simulator's effects (sim_backend.actuator Effects) from answers.json style
    {"transport_delay": {"delay_s": ...}, ...}; extra: its other fields (noise, seed)."""
    return Effects(**{**extra, **terms("stand", effects)})

"""base_resonance: what the plant stands on is a lightly damped mode (the test stand under the actuator's
housing; a compliant base under an axis's frame), loaded by the plant's reaction: a resonance/antiresonance pair."""
from rig.config import STAND_BASE_MASS_KG
from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import StandMode

AXIS_BASE_MASS_KG = 100.0          # an axis's base when a caller gives no mass (the fits always do)


def _finding(prm: dict, band) -> str:
    return (f"the measured response over the model without the stand mode shows a resonance/antiresonance pair "
            f"at {prm.get('frequency_hz', 0.0):.1f} Hz")


def _base(p: dict, mass_kg: float) -> tuple[float, float, float]:
    return (p["frequency_hz"], p["damping_ratio"], p.get("mass_kg", mass_kg))


def _stand(p: dict, u: str) -> dict:
    out = {"base_frequency_hz": p["frequency_hz"], "base_damping_ratio": p.get("damping_ratio", 0.03)}
    if "mass_kg" in p:
        out["base_mass_kg"] = p["mass_kg"]
    return out


def _draw(rng, c) -> tuple[dict, dict]:
    return ({"frequency_hz": round(float(rng.uniform(30.0, 90.0)), 2),
             "damping_ratio": round(float(rng.uniform(0.02, 0.05)), 4)},
            {"mass_kg": round(float(rng.uniform(150.0, 300.0)), 1)})


EFFECT = Effect(
    name="base_resonance", short="base", order=20,
    families=("eha", "mechanical_axis", "transfer_function"), needs_load=True,
    params=(Param("frequency_hz", "Hz"), Param("damping_ratio"), Param("mass_kg", "kg")),
    meaning=lambda family, load: ("stand mode under the housing (resonance/antiresonance pair)" if family == "eha"
                                  else "the axis's frame on a compliant base (resonance/antiresonance pair)"),
    bounds=lambda s: [(5.0, 0.45 * s.fs), (0.003, 0.4), (s.mass_kg / 3.0, 100.0 * s.mass_kg)],
    start=StandMode(), in_band=True, edge_test=True,
    evidence=Evidence("frf", "local resonance/antiresonance pair in the FRF", _finding),
    terms={"eha_model": lambda p, u: {"base": _base(p, STAND_BASE_MASS_KG)},
           "axis_model": lambda p, u: {"base": _base(p, AXIS_BASE_MASS_KG)},
           "stand": _stand},
    draws={"stand": Draw(2, _draw)},
)

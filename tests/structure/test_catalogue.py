"""The diagnosis's effects live in one catalogue (rig/diagnose/catalogue/, one definition per effect; issue 25): what
an effect is and does is asked of its definition, never decided by comparing its name. Checked by parsing every
module (ast): outside the catalogue no comparison (==, !=, in, not in, a match case) and no lookup (d["name"],
d.get("name")) has an effect's name as a literal. And the diagnosis stays in modules a reader can see whole."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from rig.diagnose import catalogue
from tests.paths import REPO

PACKAGES = ("rig", "controllers", "drivers", "sim_backend")
CATALOGUE = REPO / "rig" / "diagnose" / "catalogue"
MAX_DIAGNOSE_LINES = 600


def _names_in(node: ast.AST) -> list[str]:
    """Effect names written as literals in a node (a string, or a tuple/list/set of them)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value] if node.value in catalogue.EFFECTS else []
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [n for e in node.elts for n in _names_in(e)]
    return []


def name_decisions(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, effect name) of every comparison, match case or lookup on an effect's name."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            for part in [node.left] + node.comparators:
                found += [(node.lineno, n) for n in _names_in(part)]
        elif isinstance(node, ast.MatchValue):
            found += [(node.lineno, n) for n in _names_in(node.value)]
        elif isinstance(node, ast.Subscript):
            found += [(node.lineno, n) for n in _names_in(node.slice)]
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in ("get", "pop"):
            found += [(node.lineno, n) for a in node.args[:1] for n in _names_in(a)]
    return found


def _modules():
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            if CATALOGUE not in path.parents:
                yield path


def test_the_check_finds_a_decision_on_a_name():
    """The check can fail: each form of deciding by an effect's name is caught."""
    code = ('if name == "coulomb_friction": pass\nx = "base_resonance" in fx\ny = fx["transport_delay"]\n'
            'z = fx.get("valve_deadband")\nw = n in ("input_saturation", "other")\n'
            'match name:\n    case "constant_force": pass\n')
    assert sorted(n for _, n in name_decisions(ast.parse(code))) == sorted(
        ["coulomb_friction", "base_resonance", "transport_delay", "valve_deadband", "input_saturation",
         "constant_force"])
    assert name_decisions(ast.parse('if kind == "frf": pass\nlabel = "coulomb_friction"\n')) == []


def test_no_code_outside_the_catalogue_decides_by_an_effect_name():
    bad = [f"{p.relative_to(REPO)}:{line} {name!r}" for p in _modules()
           for line, name in name_decisions(ast.parse(p.read_text(), str(p)))]
    assert not bad, ("code outside rig/diagnose/catalogue/ decides by an effect's name (ask the effect's definition "
                     "instead: a flag, its start, its evidence kind, its terms): " + ", ".join(bad))


def test_every_effect_is_one_definition_with_what_the_diagnosis_needs():
    assert catalogue.EFFECTS, "the catalogue is empty"
    for name, e in catalogue.EFFECTS.items():
        assert (CATALOGUE / f"{name}.py").is_file(), f"{name}: its definition is not rig/diagnose/catalogue/{name}.py"
        assert e.params and e.families and callable(e.bounds) and hasattr(e.start, "initial"), name
        assert e.evidence.kind in ("amplitude", "velocity", "frf", "line"), (name, e.evidence.kind)
        assert e.evidence.kind != "frf" or e.evidence.finding is not None, f"{name}: an frf plot needs its finding"
        model = "eha_model" if "eha" in e.families else "axis_model"
        assert model in e.terms, f"{name}: no term in the diagnosis's model ({model})"
        for proof, draw in e.draws.items():
            sim = "stand" if proof == "stand" else "axis"
            assert sim in e.terms, f"{name}: drawn by the {proof} proof but no term in its simulator ({sim})"


@pytest.mark.parametrize("path", sorted((REPO / "rig" / "diagnose").rglob("*.py")), ids=lambda p: p.name)
def test_no_diagnosis_module_over_600_lines(path: Path):
    n = len(path.read_text().splitlines())
    assert n <= MAX_DIAGNOSE_LINES, f"{path.relative_to(REPO)} has {n} lines: split it by what its parts do"

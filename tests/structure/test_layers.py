"""The packages import downwards only (docs/ARCHITECTURE.md), checked by parsing every module's imports (ast).

Layers, lowest first; a module may import its own layer and those below, never one above:
  0 base          rig.errors, rig.textfile, rig.config, rig.port, rig.runtime.clock, rig.runtime.rt (+ idle_poll,
                  libc), rig.runtime.lifecycle
  1 models, maps  sim_backend physics (linear, actuator, machine, rig_plant, bench, data), drivers.protocol
  2 controllers   controllers.*  (laws, builders, design tools; may use the physics models)
  3 runtime       rig.runtime (kernel, safety, loop and its parts, recorder), recordings and their analysis;
                  ports beside it: drivers.*, sim_backend.backend, sim_backend.emulators.*
  4 registry      rig.backends, rig.runtime.session (builds runs from the registry), rig.chirp (the chirp run),
                  rig.compare (isolation off / feedback / feedforward over the same floor)
  5 commands      rig.commands.*, rig.cli, rig.console.* (the operator console: drives sessions as a command does;
                  it imports no command: commands use the console, never the other way); the Python API (rig.api,
                  and the package `rig` itself, which offers it lazily)
Within layer 3 the runtime knows no backend, the drivers know no simulator or emulator, and the simulated
ports know no driver (only the shared protocol maps of layer 1).
Function-local imports of the project's own modules are kept for the registry and the command line (they load
only what a command or a backend needs) and where a line says `# lazy:` why (a hardware library loaded only
when a device is built); elsewhere they would only hide the structure.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.paths import REPO

PACKAGES = ("rig", "controllers", "drivers", "sim_backend")
LAYER_PREFIXES = [                      # most specific first
    ("rig.commands", 5), ("rig.cli", 5), ("rig.console", 5), ("rig.api", 5),
    ("rig.backends", 4), ("rig.runtime.session", 4), ("rig.chirp", 4), ("rig.compare", 4),
    ("rig.errors", 0), ("rig.textfile", 0), ("rig.config", 0), ("rig.port", 0),
    ("rig.runtime.clock", 0), ("rig.runtime.rt", 0), ("rig.runtime.idle_poll", 0), ("rig.runtime.libc", 0),
    ("rig.runtime.lifecycle", 0),
    ("drivers.protocol", 1), ("sim_backend.backend", 3), ("sim_backend.emulators", 3), ("sim_backend", 1),
    ("controllers", 2), ("drivers", 3), ("rig", 3),
]
NAMES = {0: "base", 1: "models and maps", 2: "controllers", 3: "runtime and ports", 4: "registry", 5: "commands"}
# within layer 3: (importer prefix, imported prefix) that must not occur
SIDEWAYS = [("rig", "drivers"), ("rig", "sim_backend.backend"), ("rig", "sim_backend.emulators"),
            ("drivers", "sim_backend"), ("sim_backend", "drivers.port"), ("sim_backend", "drivers.modbus_io"),
            ("sim_backend", "drivers.canopen_valves"), ("sim_backend", "drivers.serial_dta"),
            ("sim_backend", "drivers.process"), ("sim_backend", "drivers.conversion")]
LOCAL_IMPORTS_ALLOWED = ("rig.cli", "rig.backends", "rig.commands", "rig.api")
EXACT = {"rig": 5}                      # the package's __init__: the API, loaded lazily (`import rig` stays light)
# modules another branch is reworking now (controller design): their local imports are left to it
LOCAL_IMPORTS_LATER = ("controllers.tune", "controllers.analysis")


def _layer(mod: str) -> int:
    if mod in EXACT:
        return EXACT[mod]
    for prefix, layer in LAYER_PREFIXES:
        if mod == prefix or mod.startswith(prefix + "."):
            return layer
    raise AssertionError(f"{mod}: no layer (add it to LAYER_PREFIXES and docs/ARCHITECTURE.md)")


def _modules():
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            yield ".".join(parts), path


def _imports(mod: str, path: Path):
    """(imported module, line, inside a function and not marked `# lazy:`) for every import of the project."""
    text = path.read_text()
    lines = text.splitlines()
    tree = ast.parse(text, str(path))
    funcs = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
             for n in ast.walk(f)}
    pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(pkg.split(".")[:len(pkg.split(".")) - node.level + 1] + ([base] if base else []))
            names = [n for n in (f"{base}.{a.name}" for a in node.names) if _is_module(n)] or [base]
        else:
            continue
        for name in names:
            if name.split(".")[0] in PACKAGES:
                yield name, node.lineno, id(node) in funcs and "# lazy:" not in lines[node.lineno - 1]


def _is_module(name: str) -> bool:
    p = REPO.joinpath(*name.split("."))
    return p.with_suffix(".py").exists() or (p / "__init__.py").exists()


EDGES = [(mod, path, name, line, local) for mod, path in _modules() for name, line, local in _imports(mod, path)]


def test_every_module_has_a_layer():
    for mod, _ in _modules():
        _layer(mod)


def test_no_import_of_a_higher_layer():
    bad = [f"{path.relative_to(REPO)}:{line}: {mod} ({NAMES[_layer(mod)]}) imports {name} ({NAMES[_layer(name)]})"
           for mod, path, name, line, _ in EDGES if _layer(name) > _layer(mod)]
    assert not bad, "\n".join(bad)


def test_no_sideways_import_in_the_runtime_layer():
    def under(m, p):
        return m == p or m.startswith(p + ".")
    bad = [f"{path.relative_to(REPO)}:{line}: {mod} imports {name}" for mod, path, name, line, _ in EDGES
           for a, b in SIDEWAYS if under(mod, a) and under(name, b) and not under(mod, "rig.commands")
           and _layer(mod) == 3]
    assert not bad, "\n".join(bad)


def test_the_console_imports_no_command():
    """Commands and the console are one layer; they import in one direction: a command uses the console
    (`rig run --console`, `rig bench --console`), the console never a command (what both need lives below)."""
    bad = [f"{path.relative_to(REPO)}:{line}: {mod} imports {name}" for mod, path, name, line, _ in EDGES
           if mod.startswith("rig.console") and (name == "rig.commands" or name.startswith("rig.commands."))]
    assert not bad, "\n".join(bad)


def test_no_function_local_import_of_the_project():
    def under(m, prefixes):
        return any(m == p or m.startswith(p + ".") for p in prefixes)
    bad = [f"{path.relative_to(REPO)}:{line}: {mod} imports {name} inside a function"
           for mod, path, name, line, local in EDGES
           if local and not under(mod, LOCAL_IMPORTS_ALLOWED + LOCAL_IMPORTS_LATER)]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("src", ["drivers/__init__.py", "rig/runtime/loop.py", "rig/runtime/kernel.py"])
def test_the_check_sees_imports(src):
    """The parser finds the imports it is meant to judge (a check that sees nothing passes everything)."""
    mod = src[:-3].replace("/", ".").removesuffix(".__init__")
    assert any(m == mod for m, *_ in EDGES)

"""No function over 80 lines in rig/, controllers/ and drivers/ (issue 16): a function that long does more than
one thing, and its reader cannot see it whole. Counted by parsing every module (ast): from the `def` line to the
function's last line, docstring and nested functions included.

A function that should stay long goes into ALLOWED with the reason; an entry that is no longer long must leave
the list (so the list says only what is true).
"""
from __future__ import annotations

import ast

from tests.paths import REPO

PACKAGES = ("rig", "controllers", "drivers")
MAX_LINES = 80
# "path:qualified name" -> why it may be longer; empty today
ALLOWED: dict[str, str] = {}


def _functions(tree: ast.AST, prefix: str = ""):
    """(qualified name, node) of every function and method, nested ones included."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = f"{prefix}{node.name}"
            if not isinstance(node, ast.ClassDef):
                yield name, node
            yield from _functions(node, name + ".")
        else:
            yield from _functions(node, prefix)


def function_lengths() -> dict[str, int]:
    """"path:qualified name" -> lines, for every function in PACKAGES."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            for name, node in _functions(ast.parse(path.read_text(), str(path))):
                out[f"{rel}:{name}"] = node.end_lineno - node.lineno + 1
    return out


def test_no_function_over_80_lines():
    long = {k: n for k, n in function_lengths().items() if n > MAX_LINES and k not in ALLOWED}
    assert not long, ("functions over 80 lines (split them into functions that do one thing each, or add them "
                      "to ALLOWED saying why they should stay long): "
                      + ", ".join(f"{k} ({n} lines)" for k, n in sorted(long.items(), key=lambda kv: -kv[1])))


def test_allowed_list_is_current():
    lengths = function_lengths()
    stale = [k for k in ALLOWED if lengths.get(k, 0) <= MAX_LINES]
    assert not stale, f"in ALLOWED but no longer over {MAX_LINES} lines (or gone): remove {', '.join(stale)}"


def test_counter_sees_nested_and_async_functions():
    src = "class A:\n    def f(self):\n        def g():\n            pass\n        return g\n\nasync def h():\n    pass\n"
    got = {name: node.end_lineno - node.lineno + 1 for name, node in _functions(ast.parse(src))}
    assert got == {"A.f": 4, "A.f.g": 2, "h": 2}

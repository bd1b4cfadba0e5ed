"""Every command follows docs/CLI.md (issue 29): --out is an optional folder, --record the run's HDF5 file,
--plot one PNG, --json only JSON, every output refused when it exists unless --overwrite; `rig --help` imports
no command and nothing heavy."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from rig.cli import COMMANDS, build_parser
from rig.cliargs import _Output
from tests.paths import REPO


def _parsers():
    """(name, parser) of every command and every sub-command (rig bench loop, ...)."""
    for name in COMMANDS:
        root = build_parser(name)
        sub = next(a for a in root._actions if isinstance(a, argparse._SubParsersAction))
        p = sub.choices[name]
        yield name, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sname, sp in a.choices.items():
                    yield f"{name} {sname}", sp


PARSERS = list(_parsers())


def _option(p, flag):
    return next((a for a in p._actions if flag in a.option_strings), None)


@pytest.mark.parametrize("name,parser", PARSERS, ids=[n for n, _ in PARSERS])
def test_the_output_options_mean_the_same_everywhere(name, parser):
    out, record, plot = (_option(parser, f) for f in ("--out", "--record", "--plot"))
    if out is not None and out.help != argparse.SUPPRESS:
        assert isinstance(out, _Output) and out.kind == "folder" and out.metavar == "DIR", name
        assert not out.required, f"rig {name}: --out DIR is optional everywhere"
    if record is not None:
        assert isinstance(record, _Output) and record.kind == "file" and record.metavar == "FILE", name
    if plot is not None:
        assert isinstance(plot, _Output) and plot.kind == "file" and plot.metavar == "FILE", name
        assert plot.suffix == ".png", name
    outputs = [a for a in parser._actions if isinstance(a, _Output)]
    if outputs:
        assert _option(parser, "--overwrite") is not None, f"rig {name}: outputs without --overwrite"
    js = _option(parser, "--json")
    if js is not None:
        assert js.help.startswith("print only"), f"rig {name}: --json help: {js.help!r}"


def test_the_commands_that_draw_offer_plot():
    names = {n for n, p in PARSERS if _option(p, "--plot") is not None}
    assert {"model", "run", "identify", "report"} <= names, names


def test_chirp_out_of_earlier_versions_says_what_it_is_now(capsys):
    from rig.cli import main
    assert main(["chirp", "--out", "x.h5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--record FILE" in err[0], err


def test_rig_help_imports_no_command_and_nothing_heavy():
    code = ("import sys, runpy; sys.argv = ['rig', '--help']\n"
            "try:\n    runpy.run_module('rig.cli', run_name='__main__')\nexcept SystemExit:\n    pass\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'scipy', 'numba', 'h5py', "
            "'control', 'matplotlib') or m.startswith('rig.commands.'))\n"
            "print('HEAVY', heavy, file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert "HEAVY []" in out.stderr, out.stderr[-2000:]
    for name in COMMANDS:
        assert name in out.stdout


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_a_refusal_comes_before_the_heavy_imports(name, tmp_path):
    """A command's options are checked before its work's libraries load: a missing input file, an existing
    output folder or a misspelt option is refused at once, not after seconds of imports (numba, scipy, ...)."""
    code = ("import sys\nfrom rig.cli import build_parser\n"
            f"build_parser({name!r})\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'numba', 'control', 'matplotlib'))\n"
            "print('HEAVY', heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert "HEAVY []" in out.stdout, (name, out.stdout[-2000:], out.stderr[-2000:])


def test_a_missing_recording_is_refused_before_any_work(tmp_path):
    """`rig identify` of a file that is not there: one line naming it, and the identification's compiled code
    (numba) never loaded: the refusal is immediate."""
    code = ("import sys\nfrom rig.cli import main\n"
            f"code = main(['identify', {str(tmp_path / 'nothere.h5')!r}])\n"
            "print('CODE', code, sorted(m for m in sys.modules if m.split('.')[0] == 'numba'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert "CODE 2 []" in out.stdout, (out.stdout, out.stderr)
    assert out.stderr.strip() == f"rig identify: error: {tmp_path / 'nothere.h5'}: no such file", out.stderr


def test_json_prints_only_json_on_stdout():
    out = subprocess.run([sys.executable, "-m", "rig.cli", "model", "--json"], capture_output=True, text=True,
                         timeout=300, cwd=REPO)
    assert out.returncode == 0, out.stderr
    json.loads(out.stdout)


def test_a_warning_on_stderr_names_its_command():
    """docs/CLI.md: a warning is one line `rig COMMAND: warning: ...` on stderr. No command prints a bare
    `WARNING: ...` to stderr (readers of the README could not grep one form: rig identify's and rig chirp's did)."""
    import ast
    bare = []
    for path in sorted((REPO / "rig").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print" and node.args):
                continue
            to_stderr = any(k.arg == "file" and ast.unparse(k.value) == "sys.stderr" for k in node.keywords)
            first = node.args[0]
            head = (first.value if isinstance(first, ast.Constant) else
                    first.values[0].value if isinstance(first, ast.JoinedStr) and first.values
                    and isinstance(first.values[0], ast.Constant) else "")
            if to_stderr and isinstance(head, str) and head.lower().startswith("warning"):
                bare.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not bare, bare

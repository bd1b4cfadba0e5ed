"""Bad-input campaign over the command line (issue 17): for every command, hypothesis draws arguments from bad
values (nan, inf, negative, zero, huge, not a number, empty) and short valid ones, output paths that exist or
not, flags on or off; each draw runs in-process through rig.cli.main. Whatever the input: an exit status of 0,
1 (a FAULT, valves nulled) or 2 (a user error whose last line says what was wrong), never an exception and
never a hang (valid values are short by construction; pytest-timeout guards the rest). The hardware backend
is never drawn (its defaults name real device addresses); `rig hil` always gets one refused value."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, settings, strategies as st

from rig.cli import main

pytestmark = pytest.mark.slow          # about a minute in all

BAD = ["nan", "NaN", "inf", "-inf", "-1", "0", "-0", "1e9", "1e300", "-1e300", "abc", "", "1e", "0x10",
       "5e-324", "--", "１"]
def _settings(n: int):
    """n draws (times RIG_CAMPAIGN_SCALE from the environment, for a longer campaign by hand)."""
    return settings(max_examples=n * int(os.environ.get("RIG_CAMPAIGN_SCALE", "1")), deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


SHORT_S = 0.5                            # valid durations drawn stay below this: no draw runs for long
DURATIONS = ("--seconds", "--duration", "--settle")


def _not_long(text: str) -> bool:
    try:
        v = float(text)
    except ValueError:
        return True
    return not (SHORT_S < v < 1e7)        # a valid but long duration would be a slow test, not a finding


def _value(opt, valid):
    """Three times in four a short valid value (edges included), else a bad one or any number (durations:
    never a valid long one), so that whole valid combinations run often too."""
    anything = st.one_of(st.sampled_from(BAD), st.floats().map(repr),
                         st.integers(min_value=-10 ** 12, max_value=10 ** 12).map(str))
    if opt in DURATIONS:
        anything = anything.filter(_not_long)
    return st.one_of(st.sampled_from(valid), st.sampled_from(valid), st.sampled_from(valid), anything)


class Workspace:
    """A fresh folder per draw: an existing file, a folder with a file in it, a garbage recording."""

    def __init__(self) -> None:
        self.d = Path(tempfile.mkdtemp(prefix="rig-campaign-"))
        (self.d / "old.h5").write_bytes(b"keep me")
        (self.d / "full").mkdir()
        (self.d / "full" / "notes.md").write_text("keep me")
        (self.d / "empty").mkdir()
        (self.d / "garbage.csv").write_text("time_s,valve_cmd_V\n1,2,3\nx\n")
        (self.d / "bad.toml").write_text("[actuator]\nM = -1\n")

    def path(self, kind: str) -> str:
        return {"new": str(self.d / "new.h5"), "new_png": str(self.d / "plot"), "old": str(self.d / "old.h5"),
                "folder": str(self.d / "full"), "empty": str(self.d / "empty"), "missing_dir": str(self.d / "no" / "x.h5"),
                "fresh_dir": str(self.d / "fresh"), "garbage": str(self.d / "garbage.csv"),
                "missing": str(self.d / "missing.h5"), "bad_config": str(self.d / "bad.toml")}[kind]

    def unchanged(self) -> bool:
        return (self.d / "old.h5").read_bytes() == b"keep me" and \
            (self.d / "full" / "notes.md").read_text() == "keep me"


@st.composite
def argv_for(draw, command: str, prefix: list, options: dict, paths: dict, flags: list, force_bad=()):
    """argv: the prefix, then each option absent or drawn, each path option from its kinds, each flag on or off;
    options in force_bad always get a value from BAD (so that command is refused before it starts)."""
    ws = Workspace()
    argv = [command, *prefix]
    for opt, valid in options.items():
        if opt in force_bad:
            argv += [opt, draw(st.sampled_from(["nan", "0", "-1", "1e9", "abc"]))]
        elif draw(st.booleans()):
            argv += [opt, draw(_value(opt, valid))]
    for opt, kinds in paths.items():
        if opt.startswith("--") and not draw(st.booleans()) and opt not in ("--out",) + tuple(force_bad):
            continue
        k = draw(st.sampled_from(kinds))
        argv += ([opt] if opt.startswith("--") else []) + [ws.path(k)]
    for flag in flags:
        if draw(st.booleans()):
            argv.append(flag)
    if draw(st.integers(0, 9)) == 0:
        argv += ["--config", ws.path(draw(st.sampled_from(["bad_config", "missing", "garbage"])))]
    return ws, argv


def _check(capsys, ws, argv):
    cwd = os.getcwd()
    os.chdir(ws.d)                         # defaults (e.g. rig hil's recording name) land in the workspace
    try:
        rc = main(argv)
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err
    event(f"exit {rc}")                    # the spread of outcomes: --hypothesis-show-statistics
    assert rc in (0, 1, 2), (argv, rc, err[-2000:])
    assert "Traceback" not in err, (argv, err[-2000:])
    if rc == 2:
        last = err.strip().splitlines()[-1] if err.strip() else ""
        assert "error:" in last, (argv, err[-2000:])
    if "--overwrite" not in argv:
        assert ws.unchanged(), argv
    shutil.rmtree(ws.d, ignore_errors=True)
    return rc


FILE_KINDS = ["new", "old", "folder", "missing_dir"]
DIR_KINDS = ["fresh_dir", "empty", "folder", "old"]


@_settings(120)
@given(argv_for("model", [], {}, {"--plot": ["new_png", "old", "folder", "missing_dir", "garbage"]},
                ["--json", "--overwrite"]))
def test_model(capsys, case):
    _check(capsys, *case)


# fault rehearsal specs: valid ones for the sim backend (acting within the short runs drawn), a hil-only kind,
# and malformed ones (the bad values drawn beside them too)
INJECTIONS = ["nan:front_left:accel@0.02", "stuck:1:stroke@0", "device:3:-@0.01", "drop:rear_right:stroke@0.04",
              "recorder:*:-@0.02", "overrun:*:-@0.01", "silence:*:accel@0.01", "nan:front_left:accel",
              "nan:9:accel@0.1", "frob:*:-@1", "nan:front_left:accel@-1", "nan:front_left:accel@nan"]


@_settings(100)
@given(argv_for("run", ["--sim-time", "--no-realtime", "--quiet"],
                {"--seconds": ["0.05", "0.1", "0.5"], "--settle": ["0", "0.02", "0.05", "0.5"], "--isolation": ["on", "off"],
                 "--policy": ["skip", "catch_up"], "--inject": INJECTIONS}, {"--record": FILE_KINDS},
                ["--overwrite", "--force"]))
def test_run(capsys, case):
    ws, argv = case
    if "--seconds" not in argv:
        argv += ["--seconds", "0.05"]       # no draw runs until Ctrl-C
    _check(capsys, ws, argv)


@_settings(100)
@given(argv_for("chirp", [], {"--amplitude": ["0.5", "2", "10", "50"], "--f0": ["0", "0.5", "150"],
                              "--f1": ["20", "100", "0.5"], "--duration": ["0.2", "0.4"],
                              "--rate": ["1000", "2000", "10", "100000"],
                              "--mount": ["front_left", "rear_right"], "--settle": ["0", "0.05"],
                              "--seed": ["0", "7"]},
                {"--record": FILE_KINDS}, ["--csv", "--overwrite", "--json"]))
def test_chirp(capsys, case):
    ws, argv = case
    if "--duration" not in argv:
        argv += ["--duration", "0.2"]       # the default is the paper's 100 s
    _check(capsys, ws, argv)


@_settings(60)
@given(argv_for("bench", ["loop", "--no-realtime"], {"--rate": ["1000", "5000", "10", "100000"],
                                                     "--seconds": ["0.05"], "--policy": ["skip", "catch_up"],
                                                     "--spin-us": ["0", "60", "1000"]},
                {"--record": FILE_KINDS}, ["--empty", "--json", "--overwrite"]))
def test_bench_loop(capsys, case):
    ws, argv = case
    if "--seconds" not in argv:
        argv += ["--seconds", "0.05"]
    _check(capsys, ws, argv)


@_settings(60)
@given(argv_for("bench", ["sim", "--repeats", "1"], {"--seconds": ["0.05", "0.2"], "--rate": ["1000", "5000"]},
                {}, ["--json"], force_bad=("--seconds",)))
def test_bench_sim(capsys, case):
    assert _check(capsys, *case) == 2


@_settings(25)
@given(argv_for("demo", [], {"--seconds": ["0.5"], "--settle": ["0", "0.1", "0.5"],
                                         "--rms-um": ["1", "3", "1000"], "--model-error": ["0", "10", "50"]},
                {"--out": DIR_KINDS}, ["--overwrite", "--json"]))
def test_demo(capsys, case):
    ws, argv = case
    if "--seconds" not in argv:
        argv += ["--seconds", "0.5"]
    if "--model-error" not in argv:
        argv += ["--model-error", "0"]      # the default searches 64 plants first (a few seconds)
    if "--settle" not in argv:
        argv += ["--settle", "0.1"]         # the default (1 s) is longer than the short phases drawn
    _check(capsys, ws, argv)


@_settings(60)
@given(argv_for("identify", [], {"--starts": ["1", "3"], "--seed": ["0", "5"], "--repeat": ["1", "2"]},
                {"REC": ["garbage", "missing", "empty"], "--out": DIR_KINDS}, ["--json", "--no-refine", "--overwrite"]))
def test_identify(capsys, case):
    assert _check(capsys, *case) == 2        # no readable recording among the draws


@_settings(60)
@given(argv_for("diagnose", [], {"--seed": ["0", "5"]}, {"REC": ["garbage", "missing", "empty"], "--out": DIR_KINDS},
                ["--json", "--overwrite"]))
def test_diagnose(capsys, case):
    assert _check(capsys, *case) == 2


@_settings(60)
@given(argv_for("prove", [], {"--seed": ["0", "3"], "--n": ["1", "2"], "--duration": ["1", "10"],
                              "--workers": ["1", "2"]},
                {"--cases": ["empty", "missing", "garbage"], "--out": DIR_KINDS}, ["--json", "--overwrite"],
                force_bad=("--cases",)))
def test_prove(capsys, case):
    assert _check(capsys, *case) == 2        # --cases is never a folder of recordings with answers


@_settings(60)
@given(argv_for("hil", ["--no-realtime"], {"--seconds": ["1"], "--rate": ["500"]}, {"--record": FILE_KINDS},
                ["--json", "--bench", "--overwrite"], force_bad=("--rate",)))
def test_hil(capsys, case):
    assert _check(capsys, *case) == 2        # a refused --rate: the emulated rig is never started


@_settings(60)
@given(argv_for("report", [], {"--settle": ["0", "1", "3"]}, {"REC": ["garbage", "missing", "empty", "old"],
                                                              "--out": DIR_KINDS}, ["--json", "--overwrite"]))
def test_report(capsys, case):
    assert _check(capsys, *case) == 2        # no loop recording among the draws


@_settings(40)
@given(argv_for("design", [], {}, {"--out": ["old", "folder"]}, ["--json"]))
def test_design_outputs(capsys, case):
    assert _check(capsys, *case) == 2        # an existing file or a folder with files: refused before analysis


def _matches_a_drill_case(word: str) -> bool:
    from rig.commands.drill import HIL_CASES, SIM_CASES
    return bool(word.strip()) and any(word.lower() in c.name.lower() for c in SIM_CASES + HIL_CASES)


@_settings(60)
@given(st.lists(st.one_of(st.sampled_from(BAD), st.text(max_size=8)).filter(lambda w: not _matches_a_drill_case(w)),
                min_size=1, max_size=3),
       st.sampled_from(["sim", "hil", "both", "frob", ""]), st.booleans())
def test_drill_refuses_words_of_no_case(capsys, words, backend, as_json):
    """`rig drill --only` with words of no case (or an empty one, which would match every case) is refused
    before any case runs: never a drill nobody asked for."""
    argv = ["drill", "--no-realtime", "--backend", backend, *(["--json"] if as_json else []), "--only", *words]
    assert _check(capsys, Workspace(), argv) == 2


@pytest.mark.parametrize("argv", [[], ["--help"], ["frob"], ["run", "--frob"], ["bench"], ["bench", "frob"]])
def test_no_command_or_unknown_ones(capsys, argv):
    assert main(argv) in (0, 2)
    assert "Traceback" not in capsys.readouterr().err


def test_rig_run_prints_its_vc_figure_on_stdout_and_the_lifecycle_on_stderr(tmp_path):
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--sim-time", "--seconds", "6",
                          "--record", str(tmp_path / "r.h5")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().startswith("rig run: VC class, machine at its mounts") and "VC class" not in out.stderr
    assert "lifecycle: activate -> ACTIVE" in out.stderr

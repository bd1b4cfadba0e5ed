"""`rig run --quiet` is quiet (issue 29: it still printed seven lines): only warnings, errors and the result, the
result on stdout (docs/CLI.md); without it the lifecycle lines are there."""
from __future__ import annotations

import subprocess
import sys

from tests.paths import REPO

RIG = [sys.executable, "-m", "rig.cli", "run"]


def _run(*args, cwd):
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=600, cwd=cwd)


def test_quiet_prints_the_result_alone_and_its_help_says_so(tmp_path):
    """The README's run: isolation off, then on (so the do-no-harm supervisor has its reference: no warning)."""
    script = REPO / "docs" / "examples" / "isolation_off_then_on.txt"
    out = _run("--sim-time", "--seconds", "12", "--quiet", "--script", script, "--record", "r.h5", cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stderr == ""
    (line,) = out.stdout.splitlines()
    assert line.startswith("rig run: VC class, machine at its mounts")
    loud = _run("--sim-time", "--seconds", "12", "--script", script, "--record", "r2.h5", cwd=tmp_path)
    assert loud.returncode == 0 and "lifecycle: activate -> ACTIVE" in loud.stderr and "stopped (time)" in loud.stderr
    assert f"isolation on, then as {script} says" in loud.stderr     # the start line does not contradict the script
    assert loud.stdout.splitlines()[0].split(":")[:2] == line.split(":")[:2]           # the same result
    helped = subprocess.run(RIG + ["--help"], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert "only warnings, errors and the result" in " ".join(helped.stdout.split())


def test_quiet_still_says_a_fault(tmp_path):
    cfg = tmp_path / "relaxed.toml"
    cfg.write_text("[safety]\nwatchdog_s = 1.0\nlag_limit_s = 10\nmissed_limit = 1.0\n")
    out = _run("--config", cfg, "--sim-time", "--seconds", "1", "--quiet", "--inject", "nan:front_left:accel@0.4",
               cwd=tmp_path)
    assert out.returncode == 1
    (line,) = out.stderr.splitlines()
    assert line.startswith("rig run: FAULT: front_left: accelerometer implausible: nan"), out.stderr

"""`rig demo` and `rig.simulate` under the do-no-harm supervisor (issue 27): the demo's runs keep loop time from
their first period, so the supervisor judges them against the floor accelerometers; the design as shipped runs
through untouched, and one mount's feedback of the wrong sign is switched off and said in the figures (res["harm"]),
never left in them silently."""
from __future__ import annotations

import dataclasses

from rig.compare import compare, demo_config


def test_the_demo_as_shipped_is_not_switched_off():
    cfg, _ = demo_config(None)
    res, _ = compare(cfg, seconds=4.0, settle_s=1.0)
    assert res["harm"] == {}
    assert res["reduction_db"]["table_1_100hz"]["feedback"] > 10.0


def test_a_mount_of_the_wrong_sign_is_switched_off_and_said():
    cfg, _ = demo_config(None)
    wrong = cfg.replace(controller=dataclasses.replace(cfg.controller, gain_trim=(-1.0, 1.0, 1.0, 1.0)))
    res, _ = compare(wrong, seconds=4.0, settle_s=1.0)
    assert set(res["harm"]) == {"feedback", "feedback_feedforward"}
    assert all("front_left +" in line and "isolation switched off" in line for line in res["harm"].values())


def test_rig_demo_exits_with_the_harm_status(tmp_path, capsys):
    """A wrong sign through `rig demo` (an accelerometer wired reversed): the warning lines, and EXIT_HARM, so a
    script or CI job running the demo fails on it rather than reading a zero."""
    from rig.cli import main
    from rig.errors import EXIT_HARM
    cfg = tmp_path / "wrong_sign.toml"
    cfg.write_text("[rig_error]\naccel_gain = [-1.0, 1.0, 1.0, 1.0]\n")   # front_left wired reversed
    assert main(["demo", "--config", str(cfg), "--seconds", "4", "--settle", "1"]) == EXIT_HARM
    err = capsys.readouterr().err
    assert "rig demo: warning: feedback:" in err and "isolation switched off" in err


def test_rig_run_says_the_harm_as_a_warning_and_exits_with_the_harm_status(tmp_path):
    """The README's scripted run (isolation off, then on) with an accelerometer wired reversed: the supervisor's
    line on stderr as every command says a warning, `rig run: warning: do-no-harm: ...` (docs/CLI.md), and EXIT_HARM."""
    import subprocess
    import sys
    from rig.errors import EXIT_HARM
    from tests.paths import REPO
    cfg = tmp_path / "wrong_sign.toml"
    cfg.write_text("[rig_error]\naccel_gain = [-1.0, 1.0, 1.0, 1.0]\n")
    out = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--config", str(cfg), "--sim-time", "--seconds", "12",
                          "--script", str(REPO / "docs" / "examples" / "isolation_off_then_on.txt")],
                         capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert out.returncode == EXIT_HARM, out.stderr[-2000:]
    said = [ln for ln in out.stderr.splitlines() if "do-no-harm" in ln]
    assert said and all(ln.startswith("rig run: warning: do-no-harm: isolation made the table worse than isolation off: "
                                      "front_left +") for ln in said), said

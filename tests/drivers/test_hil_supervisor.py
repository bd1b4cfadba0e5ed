"""`rig hil` at its defaults (500 Hz) with the front-left table accelerometer wired with its sign inverted
([hil] ai_factor, the emulated module's wiring fault): the isolation loop of that mount feeds back the wrong way
and the do-no-harm supervisor switches isolation off within 5 s of it going on, says so in one line, keeps it off
for the feedforward phase, records the event, and the command exits 3 with the line in its JSON. (The clean run
at the defaults, not flagged: tests/drivers/test_hil_isolation.py.)"""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rig.commands.hil import HIL_DEFAULT_CONFIG
from rig.runtime.recorder import read_recording
from rig.errors import EXIT_HARM

pytestmark = pytest.mark.hil

SECONDS = 10.5                   # off, feedback, feedback + feedforward: 3.5 s each


def test_an_inverted_accelerometer_is_caught_and_isolation_switched_off(tmp_path):
    text = HIL_DEFAULT_CONFIG.read_text().replace(
        "[hil]\n", "[hil]\nai_factor = [-1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]\n", 1)
    cfg = tmp_path / "inverted.toml"
    cfg.write_text(text)
    rec = tmp_path / "run.h5"
    argv = [sys.executable, "-m", "rig.cli", "hil", "--config", str(cfg), "--seconds", str(SECONDS),
            "--record", str(rec), "--json"]
    out = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert out.returncode == EXIT_HARM, out.stderr[-3000:]
    res = json.loads(out.stdout)
    harm = res["harm"]
    assert res["faults"] == 0 and harm.startswith("do-no-harm: isolation made the table worse")
    assert ": front_left +" in harm and res["supervisor"]["tripped"]
    t_trip = float(harm.rsplit("at t = ", 1)[1].split(" s")[0])
    assert 0 < t_trip - SECONDS / 3 < 5.0                         # isolation went on at a third of the run
    assert out.stderr.count(f"rig hil: warning: {harm}") >= 1      # said at once, on stderr, as a warning
    events = [t for _, t in read_recording(rec)["events"]]
    assert harm in events
    assert "isolation on refused: held off by the do-no-harm supervisor" in events     # the feedforward phase

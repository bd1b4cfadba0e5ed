"""A recording sampled far too slowly for the valve (a chirp's rows re-timed to 20 Hz: 1275 s of a 5 s sweep)
is diagnosed in seconds with the reason named, where `rig diagnose` looked hung: the fit pushed friction to
its bound (5000 N), and the full physics of the bias check at that friction takes 6e9 inner steps
(rig/diagnose/reduction.py MAX_INNER_STEPS). Run as a user runs it, in a process of its own."""
from __future__ import annotations

import json
import subprocess
import sys

from tests.paths import REPO


def _rig(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "rig.cli", *args], cwd=REPO, capture_output=True, text=True,
                           timeout=timeout)


def test_a_recording_sampled_at_20_hz_is_diagnosed_not_hung(tmp_path):
    chirp, exported = tmp_path / "c.h5", tmp_path / "ex"
    assert _rig("chirp", "--seconds", "5", "--record", str(chirp)).returncode == 0
    assert _rig("export", str(chirp), "--to", "csv", "--out", str(exported)).returncode == 0
    lines = (exported / "c.csv").read_text().splitlines()
    slow = tmp_path / "slow.csv"
    slow.write_text("\n".join([lines[0]] + [",".join([repr(i / 20)] + row.split(",")[1:])
                                            for i, row in enumerate(lines[1:])]) + "\n")
    out = _rig("diagnose", str(slow), "--out", str(tmp_path / "d"))     # was: still at work after 10 min
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr[-2000:]
    doc = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    text = json.dumps(doc)
    assert "sampled at 20 Hz" in text
    assert "bias was not checked against the full physics" in text

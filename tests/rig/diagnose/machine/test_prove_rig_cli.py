"""`rig prove --rig` as a user runs it, with --keep: one short blind case, its JSON result on stdout, and in the
--keep folder each case's recording and its graded row (what a proof stopped half-way keeps)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rig.recordings.runfile import is_run_recording

pytestmark = pytest.mark.slow


def test_prove_rig_keeps_each_cases_recording_and_graded_row(tmp_path):
    keep = tmp_path / "keep"
    res = subprocess.run([sys.executable, "-m", "rig.cli", "prove", "--rig", "--n", "1", "--duration", "5",
                          "--seed", "3", "--workers", "1", "--keep", str(keep), "--json"],
                         capture_output=True, text=True, timeout=1800)
    assert res.returncode == 0, res.stderr[-2000:]
    doc = json.loads(res.stdout)                                  # --json: only JSON on stdout
    (row,) = doc["rows"]
    name = doc["cases"][0]["name"]
    assert row["case"] == name and "right" in row and doc["score"]
    assert is_run_recording(keep / f"{name}.h5")
    assert json.loads((keep / f"{name}.json").read_text()) == json.loads(json.dumps(row))

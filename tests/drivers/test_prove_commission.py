"""`rig prove --commission` (issue 27): the draws of wiring faults, and one blind case end to end."""
from __future__ import annotations

import json
import random
import subprocess
import sys

import pytest
from hypothesis import given, settings, strategies as st

from rig.commands.prove_commission import FAULTS, Wiring, draw
from rig.config import MOUNTS
from tests.paths import REPO


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.sampled_from([2, 3]))
def test_a_draw_puts_each_fault_on_mounts_of_its_own(seed, n):
    """Two or three faults, on distinct mounts (a swap takes two), each named by one (channel, kind) per mount it
    takes; the wiring differs from a rig wired right exactly on those mounts."""
    w, said, expected = draw(random.Random(seed), n)
    assert len(said) == n
    mounts = [c.split(":")[1] for c, _ in expected]
    assert len(mounts) == len(set(mounts)) <= len(MOUNTS)
    right = Wiring()
    changed = set()
    for key, vals in vars(w).items():
        for i, (a, b) in enumerate(zip(vals, getattr(right, key))):
            if a != b:
                changed.add(MOUNTS[i % len(MOUNTS)] if key.startswith("ai_") else MOUNTS[i])
    assert changed == set(mounts), (said, vars(w))


def test_every_documented_fault_can_be_drawn():
    """Every fault kind of the table comes up in a few hundred draws, and its keys are in the wiring doc."""
    seen = set()
    rng = random.Random(1)
    for _ in range(400):
        seen |= {s.split("(")[0] for s in draw(rng, 3)[1]}
    assert seen == set(FAULTS)
    doc = (REPO / "drivers" / "devicemaps" / "hil_wiring_faults.md").read_text()
    assert all(f"`{k}`" in doc for k in vars(Wiring())), [k for k in vars(Wiring()) if f"`{k}`" not in doc]


@pytest.mark.hil
@pytest.mark.slow
def test_prove_commission_runs_as_a_user_runs_it(tmp_path):
    """`rig prove --commission --n 1 --clean 1`: two commissionings of the emulated rig, graded; the summary
    counts both, and the clean rig is not flagged."""
    out = tmp_path / "proof"
    r = subprocess.run([sys.executable, "-m", "rig.cli", "prove", "--commission", "--n", "1", "--clean", "1",
                        "--seed", "3", "--out", str(out), "--json"], capture_output=True, text=True, timeout=900,
                       cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads(r.stdout)
    assert s["combinations"] == 1 and s["clean"] == 1 and s["clean_flagged"] == 0, (s, r.stderr[-3000:])
    rows = json.loads((out / "proof.json").read_text())["rows"]
    assert [x["what"] for x in rows] == ["clean", "faults"] and rows[1]["expected"]
    assert s["peak_stroke_pct_of_limit_max"] < 50.0
    assert "| case | faults drawn |" in (out / "proof.md").read_text()

"""The diagnosis of the rig's own runs as a user runs it: `rig run --record X` on the simulated rig (a config
hiding a deviation), then `rig diagnose X --out D` with the model's config; its defaults, its files, its lines."""
from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

RIG = [sys.executable, "-m", "rig.cli"]
SECONDS = 15
DELAY_S = 3.5e-4


def _start(*args):
    return subprocess.Popen(RIG + [str(a) for a in args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _done(p, what):
    out, err = p.communicate(timeout=900)
    assert p.returncode == 0, f"{what}: {err[-2000:]}"
    return out, err


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("rigdiag")
    (d / "clean.toml").write_text("[sensors]\nfloor_accel = true\n")
    (d / "delay.toml").write_text(f"[rig_error]\nvalve_delay_s = [{DELAY_S}, 0.0, 0.0, 0.0]\n")
    (d / "model.toml").write_text("# the model: Table 1 and 2, no floor accelerometers\n")
    runs = [_start("run", "--config", d / f"{n}.toml", "--sim-time", "--seconds", SECONDS, "--record", d / f"{n}.h5",
                   "--quiet") for n in ("clean", "delay")]
    for p, n in zip(runs, ("clean", "delay")):
        _done(p, f"rig run {n}")
    diags = [_start("diagnose", d / "clean.h5", "--out", d / "out_clean", "--config", d / "clean.toml", "--json"),
             _start("diagnose", d / "delay.h5", "--out", d / "out_delay", "--config", d / "model.toml")]
    (clean_out, clean_err), (delay_out, delay_err) = (_done(p, "rig diagnose") for p in diags)
    return {"dir": d, "clean": (clean_out, clean_err), "delay": (delay_out, delay_err)}


def test_a_clean_run_names_nothing_and_writes_every_output(runs):
    d = runs["dir"] / "out_clean"
    out, err = runs["clean"]
    for name in ("diagnosis.json", "report.md", "replay.csv", "mismatch.png", "transmissibility.png"):
        assert (d / name).is_file() and (d / name).stat().st_size > 0, name
    doc = json.loads((d / "diagnosis.json").read_text())
    assert json.loads(out) == doc                                  # --json: only JSON on stdout, the file's
    assert doc["effects"] == [] and doc["verdict"] == "explained" and doc["floor_measured"]
    assert [m["mount"] for m in doc["margins"]] == ["front_left", "front_right", "rear_left", "rear_right"]
    assert all(m["diagnosed"]["stable"] for m in doc["margins"])
    report = (d / "report.md").read_text()
    for section in ("## Where the model and the recording differ", "## Physics named", "## Fit per mount",
                    "## The floor", "## The valves' null offsets", "## What this recording can and cannot tell",
                    "## Transmissibility per mount and band", "## rig design on the diagnosed rig"):
        assert section in report, section
    assert "Named: nothing" in doc["summary"]
    assert sum("margins hold on the diagnosed rig" in m["text"] for m in doc["margins"]) == 4
    assert "replay of" in err and "done in" in err                  # progress on stderr
    # the transmissibilities measured and predicted agree where the floor moves the machine (5-60 Hz)
    fb = doc["transmissibility"]["mounts"]["front_left"]["feedback"]
    for meas, pred in list(zip(fb["measured_db"], fb["diagnosed_db"]))[1:5]:
        assert abs(meas - pred) < 2.0
    with open(d / "replay.csv") as f:
        head = next(csv.reader(f))
    assert head[0] == "time_s" and "front_left_accel_mps2_measured" in head and "rear_right_stroke_m_diagnosed" in head


def test_a_valve_delay_is_named_at_its_mount_with_its_margins_line(runs):
    out, err = runs["delay"]
    doc = json.loads((runs["dir"] / "out_delay" / "diagnosis.json").read_text())
    named = [(e["name"], e["location"]) for e in doc["effects"]]
    assert named == [("transport_delay", "front_left")]
    e = doc["effects"][0]
    assert abs(e["parameters"]["delay_s"] - DELAY_S) < 0.15 * DELAY_S
    assert e["tests"]["passed"] and e["tests"]["holdout_gain"] > 0.3
    assert not doc["floor_measured"] and any("with floor accelerometers" in x["text"] for x in doc["detectability"])
    fl = next(m for m in doc["margins"] if m["mount"] == "front_left")
    assert "do NOT hold" in fl["text"] and fl["diagnosed"]["phase_margin_deg"] < fl["nominal"]["phase_margin_deg"] - 5
    assert len(e["margins"]) == 1 and e["margins"][0].startswith("front_left: margins do NOT hold")   # its loop only
    assert "(without it: " in e["margins"][0]
    fit = doc["fit"]
    assert fit["augmented"]["front_left"]["stroke"] < 0.5 * fit["nominal"]["front_left"]["stroke"]
    # what the user reads: the effect, its margins line, the fit per mount, what a run without floor
    # accelerometers cannot tell
    lines = out.splitlines()
    i = next(k for k, x in enumerate(lines) if x.startswith("named: front_left: valve delay"))
    assert lines[i + 1].startswith("  margins with it: front_left: margins do NOT hold")
    per_mount = [x for x in lines if x.startswith("  front_left: accelerometer")]
    assert len(per_mount) == 1 and "stroke" in per_mount[0]
    before, after = (float(v) for v in per_mount[0].split("stroke ")[1].split(" -> ")[::2])
    assert after < 0.5 * before
    assert "without floor accelerometers (the floor estimated from the mounts):" in lines
    assert any(x.startswith("  cannot be judged: a floor accelerometer's sensitivity") for x in lines)
    assert any(x.startswith("  smallest named: transport_delay at") for x in lines)

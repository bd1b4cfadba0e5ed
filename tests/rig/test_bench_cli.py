"""`rig bench loop --json` (and its `--empty` floor): only JSON on stdout, the issue's keys, consistent
distributions. No timing is asserted (the machine is shared); the figures are for the note and README."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

KEYS = {"rate_hz", "iterations", "wake_latency_us", "compute_us", "overruns", "missed_deadline_fraction"}


@pytest.mark.parametrize("extra", [[], ["--empty"]], ids=["loop", "empty"])
def test_bench_loop_json(extra):
    out = subprocess.run([sys.executable, "-m", "rig.cli", "bench", "loop", "--rate", "1000", "--seconds", "0.3",
                          "--no-realtime", "--json", *extra], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)                            # only JSON on stdout
    assert set(res) == KEYS
    assert res["rate_hz"] == 1000.0 and res["iterations"] >= 280
    for k in ("wake_latency_us", "compute_us"):
        d = res[k]
        assert set(d) == {"p50", "p99", "max"} and 0 <= d["p50"] <= d["p99"] <= d["max"]
    assert 0 <= res["missed_deadline_fraction"] <= 1 and res["overruns"] >= 0
    assert "rig bench loop" in out.stderr                   # the set-up line goes to stderr


def test_bench_loop_bad_rate_is_one_line():
    out = subprocess.run([sys.executable, "-m", "rig.cli", "bench", "loop", "--rate", "-5", "--json"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.strip().count("\n") == 0 and "--rate" in out.stderr


def test_bench_loop_feedforward_ab_json(tmp_path):
    """`rig bench loop --feedforward`: both paths run alternately (AB BA), each its own figures; the
    feedforward path really ran the feedforward (its mode on stderr). No timing is asserted."""
    out = subprocess.run([sys.executable, "-m", "rig.cli", "bench", "loop", "--feedforward", "--rounds", "2",
                          "--rate", "5000", "--seconds", "0.2", "--no-realtime", "--json"], capture_output=True,
                         text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    assert {"rate_hz", "rounds", "seconds", "feedback", "feedback_feedforward", "compute_p99_difference_us",
            "compute_p50_difference_us", "compute_p99_paired_difference_us"} == set(res)
    for path in ("feedback", "feedback_feedforward"):
        r = res[path]
        assert len(r["compute_p99_us_by_round"]) == 2 and r["iterations"] >= 1800
        assert 0 <= r["compute_us"]["p50"] <= r["compute_us"]["p99"] <= r["compute_us"]["max"]
    assert res["compute_p99_difference_us"] == pytest.approx(
        res["feedback_feedforward"]["compute_us"]["p99"] - res["feedback"]["compute_us"]["p99"], abs=0.011)
    order = [line.split()[6] for line in out.stderr.splitlines() if "round" in line and "compute p99" in line]
    assert order == ["feedback:", "feedback_feedforward:", "feedback_feedforward:", "feedback:"]
    assert "(mode feedback_feedforward)" in out.stderr and "(mode feedback)" in out.stderr

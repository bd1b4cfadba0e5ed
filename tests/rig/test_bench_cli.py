"""`rig bench loop --json` (and its `--empty` floor): only JSON on stdout, the issue's keys, consistent
distributions. No timing is asserted (the machine is shared); the figures are for the note and README."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.hosttiming import skip_unless_on_time

KEYS = {"rate_hz", "iterations", "wake_latency_us", "compute_us", "overruns", "missed_deadline_fraction"}


@pytest.mark.parametrize("extra", [[], ["--empty"]], ids=["loop", "empty"])
def test_bench_loop_json(extra):
    # 2000 Hz: the default (Table 1) controllers are unstable at 1000 Hz (`rig design`), so a loop run there
    # faults on its own oscillation (exit 1)
    out = subprocess.run([sys.executable, "-m", "rig.cli", "bench", "loop", "--rate", "2000", "--seconds", "0.3",
                          "--no-realtime", "--json", *extra], capture_output=True, text=True, timeout=120)
    skip_unless_on_time(out)                                # a stall of the shared host faults the loop (exit 1)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)                            # only JSON on stdout
    assert set(res) == KEYS
    assert res["rate_hz"] == 2000.0 and res["iterations"] >= 560
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
    skip_unless_on_time(out)
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


@pytest.mark.parametrize("extra", [[], ["--feedforward", "--rounds", "1"]], ids=["loop", "feedforward"])
def test_bench_loop_whose_rig_faulted_exits_as_a_fault(tmp_path, extra):
    """Was: a benchmark whose simulated rig faulted (its loop at FAULT, valves at null, for the rest of the run)
    said so as a `note:` and exited 0, as if its figures were the loop's. Now a warning line naming the fault,
    and exit 1 (a fault, rig/errors.py EXIT_FAULT); the figures are still printed, and --json stays JSON."""
    cfg = tmp_path / "trip.toml"
    cfg.write_text("[safety]\nstroke_limit_m = 1e-9\n")     # the first period's stroke trips the limit
    out = subprocess.run([sys.executable, "-m", "rig.cli", "bench", "loop", "--config", str(cfg), "--rate", "1000",
                          "--seconds", "0.2", "--no-realtime", "--json", *extra], capture_output=True, text=True,
                         timeout=180)
    assert out.returncode == 1, out.stderr[-2000:]
    json.loads(out.stdout)                                  # still only JSON on stdout
    warned = [ln for ln in out.stderr.splitlines() if ln.startswith("rig bench: warning: ")]
    assert warned and all("faulted (" in ln and "stroke limit" in ln for ln in warned), out.stderr[-2000:]
    assert "note:" not in out.stderr


@pytest.mark.parametrize("extra", [[], ["--layout", "prototype"]], ids=["machine", "prototype"])
def test_bench_loop_interrupted_by_ctrl_c_says_so_and_exits_130(extra):
    """Found by the abuse trial: Ctrl-C during `rig bench loop` printed the figures of the part that ran as if
    the run were whole, exit 0. Now the figures, a line saying it was interrupted, and exit 130 (rig/errors.py)."""
    import os
    import signal
    import time
    from tests.rig.support import Command
    cmd = Command("bench", "loop", "--rate", "2000", "--seconds", "120", "--no-realtime", "--json", *extra,
                  own_group=True)                          # SIGINT at its default, as at a terminal
    try:
        assert cmd.wait_for("rig bench loop: ", timeout=120), cmd.text     # the set-up line: the run starts
        time.sleep(1.0)                                    # into the run (it would go on for 120 s)
        os.killpg(cmd.proc.pid, signal.SIGINT)             # Ctrl-C at a terminal reaches the whole group
        out = cmd.proc.stdout.read()
        code = cmd.finish(timeout=120)
    finally:
        cmd.finish()
        cmd.drain()
    assert code == 130, cmd.text
    res = json.loads(out)                                  # the figures measured, still only JSON on stdout
    assert KEYS <= set(res) and 0 < res["iterations"] < 120 * 2000
    said = [ln for ln in cmd.text.splitlines() if "interrupted" in ln]
    assert len(said) == 1 and said[0].startswith("rig bench loop: interrupted (SIGINT) at t = "), cmd.text


def test_bench_loop_of_several_runs_ends_at_ctrl_c(tmp_path):
    """Was: Ctrl-C during `rig bench loop --feedforward` cut one run short and the next ran on, pooled into
    figures printed as whole, exit 0. Now the benchmark ends there: `rig bench: interrupted`, exit 130."""
    import os
    import signal
    import time
    from tests.rig.support import Command
    cmd = Command("bench", "loop", "--feedforward", "--rounds", "1", "--rate", "2000", "--seconds", "30",
                  "--no-realtime", "--json", env=dict(os.environ, TMPDIR=str(tmp_path)), own_group=True)
    try:
        while not list(tmp_path.glob("rig-bench-*.h5")) and cmd.proc.poll() is None:
            time.sleep(0.1)                                # the first run's recording: its session is set up
        time.sleep(1.0)                                    # into that run (it would go on for 30 s)
        os.killpg(cmd.proc.pid, signal.SIGINT)
        out = cmd.proc.stdout.read()
        code = cmd.finish(timeout=120)
    finally:
        cmd.finish()
        cmd.drain()
    assert code == 130 and out == "", cmd.text
    assert cmd.text.strip().splitlines()[-1] == "rig bench: interrupted", cmd.text

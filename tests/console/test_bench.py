"""`rig bench loop --console` when its run goes wrong: a fault that comes straight back after a reset, and
Ctrl-C. Each must end (the subprocess timeouts only end the old hangs), with the exit status every other
benchmark of blocks gives (rig/commands/bench.py faulted_exit, stop_if_interrupted). No timing is asserted."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from tests.rig.support import Command

pytestmark = pytest.mark.browser
CONSOLE = ["bench", "loop", "--console", "--serve", "process", "--block-s", "1", "--no-realtime"]


def test_a_fault_back_at_once_after_each_reset_leaves_the_blocks_out_and_exits_1(tmp_path):
    """Found by a helper: with a fault that returns in the period of its reset ([safety] accel_range_mps2 =
    1e-9: any accelerometer sample trips it), each block's wait for ACTIVE never ended. Now a few
    resets, then the block is not run and counted as faulted: a warning per condition (faulted_exit), exit 1,
    and the figures (--json: only JSON) say no block was measured."""
    cfg = tmp_path / "trip.toml"
    cfg.write_text("[safety]\naccel_range_mps2 = 1e-9\n")
    out = subprocess.run([sys.executable, "-m", "rig.cli", *CONSOLE, "--rounds", "1", "--rate", "1000", "--config",
                          str(cfg), "--json"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stderr[-3000:]
    res = json.loads(out.stdout)
    assert {c: (d["blocks"], d["faults"]) for c, d in res["conditions"].items()} == {"none": (0, 1),
                                                                                    "process": (0, 1)}
    warned = [ln for ln in out.stderr.splitlines() if ln.startswith("rig bench: warning: ")]
    assert [ln.split(" (")[0] for ln in warned] == ["rig bench: warning: none", "rig bench: warning: process"]
    assert all("accelerometer implausible" in ln and ln.endswith("those blocks are left out of the figures")
               for ln in warned), out.stderr[-3000:]


def test_ctrl_c_ends_the_console_benchmark_with_130():
    """Found with the above: Ctrl-C stopped the loop, and the benchmark then waited for ACTIVE for ever. Now it
    ends as the other benchmarks of blocks do: `rig bench: interrupted`, no figures, exit 130."""
    cmd = Command(*CONSOLE, "--rounds", "3", "--rate", "2000", own_group=True)    # SIGINT as at a terminal
    try:
        assert cmd.wait_for("none done", timeout=120), cmd.text     # into the console block: the browser's
        time.sleep(2.0)                                    # process runs too (it is left to the bench to end)
        os.killpg(cmd.proc.pid, signal.SIGINT)             # Ctrl-C reaches the terminal's whole group
        code = cmd.finish(timeout=120)
    finally:
        cmd.finish()
        cmd.drain()
    assert code == 130 and cmd.proc.stdout.read() == "", cmd.text
    assert cmd.text.strip().splitlines()[-1] == "rig bench: interrupted", cmd.text

"""Issue 17 (reliability) in HIL: the real drivers against the emulated devices on loopback. `rig run --backend
hil` without --config runs the HIL design; `rig hil` stopped by Ctrl-C says so (exit 130, no summary); fault
rehearsal on the emulated devices; the lag and oscillation rules within their targets through the drivers
(lag fault within 100 ms of the limit being crossed, a limit cycle caught within 0.2 s)."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from rig.commands.drill import HIL_CASES, drill_case
from rig.commands.hil import HIL_DEFAULT_CONFIG
from tests.rig.support import Command

pytestmark = pytest.mark.hil
PY = sys.executable


@pytest.fixture(autouse=True)
def own_lock_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_LOCK_DIR", str(tmp_path / "locks"))


def test_rig_run_hil_without_config_runs_the_hil_design():
    """Issue: without --config it took the 5 kHz Table 1 controller at 500 Hz and never activated within
    --seconds 8. Now the HIL design (hil.toml): warmed up 2 / blend_hz, then isolating, no fault."""
    out = subprocess.run([PY, "-m", "rig.cli", "run", "--backend", "hil", "--seconds", "7.5"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "devicemaps/hil.toml" in out.stderr and "at 500 Hz" in out.stderr
    assert "activate -> ACTIVE" in out.stderr and "FAULT" not in out.stderr


def test_rig_hil_stopped_by_ctrl_c_says_so_and_exits_130(tmp_path):
    """Issue: `rig hil` stopped by Ctrl-C exited 0 with a normal-looking summary."""
    hil = Command("hil", "--seconds", "20", "--record", str(tmp_path / "int.h5"))
    assert hil.wait_for("ACTIVE isolation"), hil.text
    time.sleep(1.0)
    hil.proc.send_signal(signal.SIGINT)
    rc = hil.finish()
    out = hil.proc.stdout.read()
    text = hil.text
    assert rc == 130, text
    assert "interrupted (SIGINT)" in text and "no isolation figure" in text and "Traceback" not in text
    assert "isolation reduction" not in out and out.strip() == ""


def test_ctrl_c_at_a_terminal_reaches_every_process_of_rig_hil_and_says_one_line(tmp_path):
    """Was: a Ctrl-C to the whole process group (as a terminal sends it) also ended the emulated devices, each
    printing "Fatal Python error: _enter_buffered_busy" (their stdin watcher at interpreter shutdown)."""
    hil = Command("hil", "--seconds", "20", "--record", str(tmp_path / "int.h5"), own_group=True)
    assert hil.wait_for("ACTIVE isolation"), hil.text
    time.sleep(1.0)
    os.killpg(hil.proc.pid, signal.SIGINT)
    rc = hil.finish()
    hil.drain()
    text = hil.text
    assert rc == 130, text
    assert "interrupted (SIGINT)" in text and "Fatal Python error" not in text and "Traceback" not in text


def test_hil_inject_a_silent_valve_node_faults_naming_it(tmp_path):
    out = subprocess.run([PY, "-m", "rig.cli", "hil", "--seconds", "3", "--record", str(tmp_path / "v.h5"), "--json",
                          "--inject", "silence:front_left:valve@1.5"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 1, out.stderr[-3000:]
    assert json.loads(out.stdout)["faults"] == 1
    assert "valve front_left (node 1): no new TPDO" in out.stderr and "Traceback" not in out.stderr


def _case(name):
    return next(c for c in HIL_CASES if c.name.startswith(name))


def _design_with_room(tmp: Path) -> str:
    """The HIL design with the devices' staleness limits at 0.3 s: the loaded shared machine stalls a device
    process for 100 ms at times, and these tests are about the loop's own rules."""
    text = HIL_DEFAULT_CONFIG.read_text()
    for key in ("stale_s", "serial_stale_s"):
        text = re.sub(rf"^{key} = 0\.1$", f"{key} = 0.3", text, flags=re.M)
    p = tmp / "hil_room.toml"
    p.write_text(text)
    return str(p)


def test_hil_lag_fault_within_100_ms_of_the_limit_being_crossed():
    with tempfile.TemporaryDirectory() as tmp:
        r = drill_case(_case("loop falls behind"), "hil", folder=Path(tmp), config=_design_with_room(Path(tmp)))
    assert r["faulted"] and r["line"].startswith("loop lag:") and r["valves_null"], r
    assert r["after_limit_crossed_ms"] <= 100, r


def test_hil_limit_cycle_caught_within_0_2_s():
    with tempfile.TemporaryDirectory() as tmp:
        r = drill_case(_case("limit cycle"), "hil", folder=Path(tmp), config=_design_with_room(Path(tmp)))
    assert r["faulted"] and "valve command oscillating" in r["line"] and r["valves_null"], r
    assert r["to_fault_ms"] <= 200 and r["measured_from"].startswith("the first command"), r

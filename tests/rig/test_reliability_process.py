"""Issue 17 (reliability) through the command line: `rig run` as an operator starts it (real processes, real
HDF5 files, real signals, the real lock files), the fault rehearsal (`--inject`, `rig drill`), and the
messages. Each test is one of the issue's cases and failed on the code before the issue."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rig.runtime.recorder import read_recording
from tests.rig.support import Command

PY = sys.executable
# timing rules relaxed above the shared machine's stalls (45-51 ms), its missed deadlines without real-time
# priority and its lag (a starved 5 kHz loop fell 200 ms behind in 2 s): these tests are about the control path;
# the timing rules have their own (test_reliability.py)
RELAXED = "[safety]\nwatchdog_s = 0.2\nlag_limit_s = 10\nmissed_limit = 1.0\n[vibration]\nrms_m = 1e-6\n"


@pytest.fixture(autouse=True)
def own_lock_dir(tmp_path, monkeypatch):
    """Lock files of these tests in their own folder (other runs on the machine keep theirs)."""
    monkeypatch.setenv("RIG_LOCK_DIR", str(tmp_path / "locks"))


def rig(*args, timeout=180, cwd=None):
    return subprocess.run([PY, "-m", "rig.cli", *args], capture_output=True, text=True, timeout=timeout, cwd=cwd)


def relaxed(tmp_path, extra: str = "") -> str:
    p = tmp_path / "rig.toml"
    p.write_text(RELAXED + extra)
    return str(p)


def one_error_line(out, rc=2) -> str:
    assert out.returncode == rc, out.stderr[-3000:]
    assert "Traceback" not in out.stderr, out.stderr
    errs = [ln for ln in out.stderr.splitlines() if ": error: " in ln]
    assert len(errs) == 1, out.stderr
    return errs[0]


# ---- start-up refusals --------------------------------------------------------------------------------------
def test_rig_run_refuses_a_rate_the_loop_cannot_hold(tmp_path):
    """Issue: `[loop] rate_hz = 50000` was accepted (23 % of deadlines missed, 45 ms behind). At 100 kHz no
    Python loop holds the 10 us period: refused from the first periods' measurement, valves never driven."""
    line = one_error_line(rig("run", "--config", relaxed(tmp_path, "[loop]\nrate_hz = 100000\n"), "--seconds", "2",
                              "--quiet", "--no-realtime"))
    assert "loop rate 100000 Hz: the loop cannot hold this rate here" in line and "us period" in line


def test_rig_run_refuses_an_unstable_controller_unless_forced(tmp_path):
    """Issue: a controller `rig design` calls unstable was run. Refused with the poles (exit 2); with --force it
    runs and the oscillation rule faults its limit cycle (exit 1), the FAULT row recorded with null commands."""
    cfg = relaxed(tmp_path, "[controller]\nkp_V_per_m = 3450000\n")
    line = one_error_line(rig("run", "--config", cfg, "--seconds", "2", "--quiet", "--no-realtime"))
    assert "`rig design` calls this loop unstable" in line and "--force" in line
    rec = tmp_path / "forced.h5"
    out = rig("run", "--config", cfg, "--seconds", "3", "--quiet", "--no-realtime", "--force", "--record", str(rec))
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    faults = [ln for ln in out.stderr.splitlines() if "FAULT:" in ln]
    assert len(faults) == 1 and "valve command oscillating" in faults[0]
    d = read_recording(rec)
    k = np.flatnonzero(d["fault"] > 0.5)[0]
    assert np.all(d["valve_cmd_V"][k:] == 0.0) and d["attrs"]["fault_reason"].endswith("valves to null")


# ---- the control path ---------------------------------------------------------------------------------------
def _usr1_caught(pid: int) -> bool:
    try:
        caught = next(ln for ln in Path(f"/proc/{pid}/status").read_text().splitlines() if ln.startswith("SigCgt"))
    except (OSError, StopIteration):
        return False
    return bool(int(caught.split()[1], 16) & (1 << (signal.SIGUSR1 - 1)))


def test_sigusr1_during_the_start_up_is_held_not_fatal(tmp_path):
    """Issue: SIGUSR1 in the first ~1.5 s killed `rig run` (exit 138). The handler is installed before the
    slow imports and set-up; a toggle sent then is applied at the first period (isolation off)."""
    rec = tmp_path / "usr1.h5"
    run = Command("run", "--config", relaxed(tmp_path), "--seconds", "1.0", "--no-realtime",
                  "--record", str(rec))
    end = time.monotonic() + 30
    while not _usr1_caught(run.proc.pid) and time.monotonic() < end and run.proc.poll() is None:
        time.sleep(0.002)
    assert not any("backend sim" in ln for ln in run.lines)       # still setting up
    run.proc.send_signal(signal.SIGUSR1)
    rc = run.finish()
    assert rc == 0, run.text
    assert "isolation toggle (SIGUSR1) received during start-up: applied at the first period" in run.text
    d = read_recording(rec)
    assert np.all(d["isolation_on"] == 0.0)                       # toggled off before the run began


def test_a_control_file_left_saying_stop_or_off_does_not_count(tmp_path):
    """Issue: a control file left saying `stop` ended the next run after 0.1 s; one saying `off` overrode
    --isolation on. Only changes after the start count; a change then is applied, logged and recorded."""
    ctl = tmp_path / "ctl"
    ctl.write_text("stop\n")
    rec = tmp_path / "ctl.h5"
    run = Command("run", "--config", relaxed(tmp_path), "--seconds", "3", "--no-realtime", "--control",
                  str(ctl), "--isolation", "on", "--record", str(rec))
    assert run.wait_for("activate -> ACTIVE"), run.text
    time.sleep(0.3)
    ctl.write_text("off\n")                                      # a change: applied
    assert run.wait_for("isolation off", timeout=30), run.text
    assert run.finish() == 0, run.text
    assert "stopped (time)" in run.text and "says 'stop' from before the start: ignored" in run.text
    d = read_recording(rec)
    assert "isolation off" in [e[1] for e in d["events"]]
    on = d["isolation_on"]
    assert on[0] == 1.0 and on[-1] == 0.0 and np.count_nonzero(np.diff(on)) == 1


def test_a_control_file_that_is_not_text_is_ignored_with_a_warning_and_still_polled(tmp_path):
    """Was: a byte that is not UTF-8 in the control file killed its polling thread (a traceback on stderr); the
    run went on to its end and a later `stop` was never read."""
    ctl = tmp_path / "ctl"
    run = Command("run", "--config", relaxed(tmp_path), "--seconds", "30", "--no-realtime", "--control", str(ctl))
    assert run.wait_for("activate -> ACTIVE"), run.text
    ctl.write_bytes(b"\xff\n")
    assert run.wait_for("is not UTF-8 text", timeout=30), run.text
    ctl.write_text("stop\n")
    assert run.finish() == 0, run.text
    assert "Traceback" not in run.text and f"stopped (control file {ctl}: stop)" in run.text


@pytest.mark.parametrize("option", ["--config", "--control", "--script", "--reference"])
def test_a_named_file_that_is_a_pipe_is_refused_not_waited_on(tmp_path, option):
    """Was: a FIFO given as --config, --control, --script or a csv: reference hung `rig run` on its open (no
    writer ever comes), and Ctrl-C did not end it."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    value = f"csv:{fifo}" if option == "--reference" else str(fifo)
    extra = ["--layout", "prototype", "--mode", "track"] if option == "--reference" else []
    line = one_error_line(rig("run", "--sim-time", "--seconds", "1", *extra, option, value, timeout=60))
    assert str(fifo) in line and "a pipe or device" in line


def test_a_control_file_in_a_missing_folder_is_refused(tmp_path):
    line = one_error_line(rig("run", "--seconds", "1", "--quiet", "--control", str(tmp_path / "nope" / "ctl")))
    assert f"folder {tmp_path / 'nope'} does not exist" in line


def test_a_second_process_driving_the_same_rig_is_refused_naming_the_holder(tmp_path):
    """Issue: two `rig run` could drive the same rig. The hardware backend's devices are locked per process:
    a second one is refused before it touches a device, naming the holder's pid and command line; when the
    holder dies (kill -9 here) its lock goes with it."""
    cfg = tmp_path / "hw.toml"
    cfg.write_text('[drivers]\ncan_interface = "virtual"\ncan_channel = "rig-lock-test"\nmodbus_host = "127.0.0.1"\n'
                   f'modbus_port = 1\nserial_port = "{tmp_path / "no-tty"}"\n')
    holder = subprocess.Popen([PY, "-c", "import sys, time\nfrom rig.backends import devices\n"
                               "from rig.config import load_config\nfrom rig.runtime.lock import RigLock\n"
                               f"with RigLock(devices(load_config({str(cfg)!r}), 'hardware'), 'rig run (holder)'):\n"
                               "    print('held', flush=True)\n    time.sleep(120)\n"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        line = one_error_line(rig("run", "--backend", "hardware", "--config", str(cfg), "--seconds", "1",
                                  "--quiet", "--no-realtime", "--uncommissioned"))
        assert "is in use by another process" in line and f"pid {holder.pid}" in line and "rig run (holder)" in line
    finally:
        holder.kill()
        holder.wait()
    out = rig("run", "--backend", "hardware", "--config", str(cfg), "--seconds", "1", "--quiet", "--no-realtime",
              "--uncommissioned")
    assert "in use" not in out.stderr and "Traceback" not in out.stderr      # past the lock: the devices' own error
    assert out.returncode != 0


# ---- fault rehearsal ---------------------------------------------------------------------------------------
def test_inject_drives_a_sim_knob_and_the_run_faults_naming_it(tmp_path):
    """Issue: the fault knobs could not be reached from the command line."""
    rec = tmp_path / "inj.h5"
    out = rig("run", "--config", relaxed(tmp_path), "--seconds", "2", "--no-realtime", "--record", str(rec),
              "--inject", "nan:front_left:accel@0.4")
    assert out.returncode == 1, out.stderr
    faults = [ln for ln in out.stderr.splitlines() if "FAULT:" in ln]
    assert len(faults) == 1 and "front_left: accelerometer implausible: nan" in faults[0]
    assert "injected nan:front_left:accel@0.4 at t = 0.400 s" in out.stderr
    d = read_recording(rec)
    k = np.flatnonzero(d["fault"] > 0.5)[0]
    assert d["time_s"][k] == pytest.approx(0.4, abs=2e-4) and np.all(d["valve_cmd_V"][k:] == 0.0)


@pytest.mark.parametrize("spec, words", [
    ("nan:front_left:accel", "expected KIND:MOUNT:SIGNAL@T"),
    ("melt:front_left:accel@1", "KIND: expected one of"),
    ("nan:middle:accel@1", "MOUNT: expected one of"),
    ("nan:front_left:valve@1", "needs SIGNAL accel or stroke"),
    ("silence:*:accel@1", "the sim backend has no 'silence' knob"),
    ("nan:0:accel@nan", "T: expected 0 <= T <= 86400 s"),
    ("recorder:*:-@0.5", "needs a recording (--record FILE)"),     # T within the --seconds 1 run
])
def test_a_bad_injection_is_one_line(tmp_path, spec, words):
    line = one_error_line(rig("run", "--config", relaxed(tmp_path), "--seconds", "1", "--quiet", "--no-realtime",
                              "--inject", spec))
    assert words in line


def test_rig_drill_rehearses_a_fault_and_reports_the_time_to_fault(tmp_path):
    out = rig("drill", "--config", relaxed(tmp_path), "--only", "NaN", "stalls", "--json", "--no-realtime")
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout)
    assert [r["case"] for r in res] == ["accelerometer NaN", "loop stalls (three watchdog limits in one period)"]
    for r in res:
        assert r["faulted"] and r["valves_null"] and r["rows_lost"] == 0, r
    assert res[0]["to_fault_ms"] == 0.0 and "front_left: accelerometer implausible" in res[0]["line"]
    assert "watchdog" in res[1]["line"] and res[1]["to_fault_ms"] >= 200          # watchdog_s = 0.2 here


# ---- messages ------------------------------------------------------------------------------------------------
def test_the_status_line_shows_suspended_isolation():
    """Issue: with the valves at the clamp and isolation suspended, the status line said `iso=on`."""
    from rig.runtime.clock import SimClock
    from rig.config import Config
    from rig.runtime.session import Session, _StatusLine
    from controllers.isolation import SCALAR_STATES
    with Session(Config(), "sim", clock=SimClock()) as s:
        s.run(iterations=100, activate_after_s=0.005)
        line = _StatusLine(s.loop).line()
        assert "iso=on " in line
        c = s.loop.ctrls[0]
        s.loop.states[0][len(c.state_names) - len(SCALAR_STATES) + SCALAR_STATES.index("suspended")] = 1.0
        s.loop._watch_suspension()
        assert "iso=SUSPENDED(front_left)" in _StatusLine(s.loop).line()


def test_hil_help_names_the_config_it_runs():
    """Issue: `rig hil` silently used another config while its help said Table 1."""
    out = rig("hil", "--help")
    assert out.returncode == 0 and "hil.toml" in out.stdout and "Table 1 values)" not in out.stdout
    out = rig("run", "--help")
    assert "with --backend hil the HIL design" in out.stdout.replace("\n", " ").replace("  ", " ") or \
        "hil.toml" in out.stdout


def test_uncommissioned_hardware_is_refused_in_one_line(tmp_path):
    """Issue 27: `rig run --backend hardware` without a calibration newer than the configuration is refused
    before it touches a device (the config points at 127.0.0.1 only); a newer one passes this rule."""
    cfg = tmp_path / "hw.toml"
    body = ('[drivers]\ncan_interface = "virtual"\ncan_channel = "rig-cal-test"\nmodbus_host = "127.0.0.1"\n'
            f'modbus_port = 1\nserial_port = "{tmp_path / "no-tty"}"\n')
    cfg.write_text(body)
    args = ("run", "--backend", "hardware", "--config", str(cfg), "--seconds", "1", "--quiet", "--no-realtime")
    line = one_error_line(rig(*args))
    assert "the rig is not commissioned: no calibration ([drivers] calibration is not set)" in line
    cal = tmp_path / "commissioning.toml"
    cal.write_text('[accel.front_left]\nmount = "front_left"\nsign = 1\n')
    cfg.write_text(body + 'calibration = "commissioning.toml"\n')        # the configuration changed after it
    os.utime(cal, (time.time() - 60, time.time() - 60))
    assert f"its calibration {cal} is older than {cfg}" in one_error_line(rig(*args))
    os.utime(cal, None)
    out = rig(*args)                                                  # past the rule: the devices' own error
    assert "not commissioned" not in out.stderr and "Traceback" not in out.stderr and out.returncode != 0
    # a chirp drives the hardware's valve too: the same rule (and its own --uncommissioned)
    os.utime(cal, (time.time() - 60, time.time() - 60))
    chirp = ("chirp", "--backend", "hardware", "--config", str(cfg), "--seconds", "1", "--record",
             str(tmp_path / "c.h5"))
    assert f"its calibration {cal} is older than {cfg}" in one_error_line(rig(*chirp))
    out = rig(*chirp, "--uncommissioned")                             # past the rule: the devices' own error
    assert "not commissioned" not in out.stderr and "Traceback" not in out.stderr and out.returncode != 0

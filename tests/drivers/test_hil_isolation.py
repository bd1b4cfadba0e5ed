"""A HIL run through the real drivers with the runtime's loop (`rig hil --json`, its defaults): no faults, every
period recorded, and the isolation through the drivers (feedback; feedback + floor feedforward, the floor
accelerometers on the module's further channels) held against the same design under the same floor in lockstep
simulated time, which the same command runs beside (the table's rms in 1-100 Hz, each mode over the same loop
periods). If the drivers lost conversions, added periods of latency, swapped channels or scaled wrongly, the two
would part (a lost accelerometer conversion per second is enough to put the valves at the clamp). The figures
are judged against each other, from one run: no retry, no skip for a loaded machine."""
from __future__ import annotations

import json
import re
import subprocess
import sys

import h5py
import pytest

from rig.commands.hil import HIL_DEFAULT_CONFIG, JSON_KEYS, LATE_WARN, hil_config
from rig.config import load_config
from rig.errors import EXIT_SUSPECT
from tests.hosttiming import LATE_BOUND, ran_to_the_end, skip_unless_on_time

pytestmark = pytest.mark.hil           # the real drivers against the emulated devices, on loopback

SECONDS = 15.0                           # off, feedback, feedback + feedforward: 5 s each (as `rig hil`)
AGREE_DB = 1.5                           # through the drivers within this of the lockstep run (issue 24)
# The floor feedforward is held to the same bound: its gap of 0.4-3.6 dB was the metering (the emulated plant's trace
# band-limited with what it did after the loop stopped, the last window at the trace's end: drivers/README.md);
# swapped or misscaled floor channels lose far more, and test_feedforward_adds_to_feedback_through_the_drivers
# holds its gain over feedback.


@pytest.fixture(scope="module")
def hil_run(tmp_path_factory):
    rec = tmp_path_factory.mktemp("hil") / "run.h5"
    argv = [sys.executable, "-m", "rig.cli", "hil", "--seconds", str(SECONDS), "--record", str(rec), "--json"]
    out = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    return out, rec


@pytest.fixture
def on_time(hil_run):
    """The run, judged only if the host kept its time (tests/hosttiming.py)."""
    skip_unless_on_time(hil_run[0])
    return hil_run


def test_json_schema_and_clean_run(on_time):
    out, rec = on_time
    res = json.loads(out.stdout)                       # only JSON on stdout
    late = max(res["late_periods"].values())           # beyond LATE_WARN: said, and the exit status says so too
    assert out.returncode == (EXIT_SUSPECT if late > LATE_WARN else 0), out.stderr[-2000:]
    assert set(res) == set(JSON_KEYS)
    modes = {"off", "feedback", "feedback_feedforward"}
    assert set(res["transmissibility_db"]) == set(res["late_periods"]) == modes
    assert set(res["lockstep_reduction_db"]) == modes - {"off"}
    assert all(0.0 <= v <= 1.0 for v in res["late_periods"].values())
    assert res["transports"] == ["canopen", "modbus_tcp", "serial"]
    assert res["faults"] == 0
    sup = res["supervisor"]                            # the do-no-harm supervisor judged the run and let it be
    assert res["harm"] is None and not sup["tripped"] and sup["reference"] == "isolation off (table/floor)"
    assert sup["table_vs_reference_db"] < -sup["margin_db"]
    cfg = hil_config(load_config(HIL_DEFAULT_CONFIG))
    assert res["iterations"] >= 0.9 * SECONDS * cfg.loop.rate_hz
    assert res["samples_recorded"] == res["iterations"]      # every period's sample recorded
    assert res["recording"] == str(rec)
    with h5py.File(rec, "r") as f:
        assert f["time_s"].shape[0] == res["iterations"]
        on, floor = f["feedforward_on"][()], f["floor_accel_mps2"][()]
    # the last third, switched on live; the run ends through one INACTIVE period (valves null, feedforward off)
    assert 0 < on.mean() < 0.5 and on[-2] == 1.0 and on[-1] == 0.0
    assert floor.shape[1] == 4 and 1e-3 < floor.std() < 1.0  # the floor accelerometers came over Modbus


@pytest.mark.parametrize("mode", ["feedback", "feedback_feedforward"])
def test_isolation_through_the_drivers_matches_lockstep(on_time, mode):
    """Each isolation mode through the drivers within AGREE_DB of the same design and floor in lockstep (the
    same run's), and isolating (the lockstep run's design meets hil.toml's prediction)."""
    out, _ = on_time
    res = json.loads(out.stdout)
    got = res["isolation_reduction_db" if mode == "feedback" else "feedforward_reduction_db"]
    sim = res["lockstep_reduction_db"][mode]
    why = f"{mode}: through the drivers {got} dB, lockstep {sim} dB, late {res['late_periods']}; {out.stderr[-1500:]}"
    assert sim > (5.0 if mode == "feedback" else 10.0), why
    assert got == pytest.approx(sim, abs=AGREE_DB), why


def test_feedforward_adds_to_feedback_through_the_drivers(on_time):
    """Swapped or misscaled floor channels would undo the feedforward's gain over feedback alone."""
    out, _ = on_time
    res = json.loads(out.stdout)
    assert res["feedforward_reduction_db"] > res["isolation_reduction_db"] + 1.0, out.stderr[-1500:]


@pytest.fixture(scope="module")
def hil_2khz_run(tmp_path_factory):
    """The design at 2 kHz as a user runs it: `rig hil --config drivers/devicemaps/hil_2khz.toml`."""
    rec = tmp_path_factory.mktemp("hil2k") / "run.h5"
    argv = [sys.executable, "-m", "rig.cli", "hil", "--config", str(HIL_DEFAULT_CONFIG.parent / "hil_2khz.toml"),
            "--seconds", str(SECONDS), "--record", str(rec), "--json"]
    return subprocess.run(argv, capture_output=True, text=True, timeout=600)


def test_the_2khz_design_isolates_through_the_drivers_as_in_lockstep(hil_2khz_run):
    """Issue 24's targets at 2 kHz, from one run: no fault; feedback >= 11 dB and feedback + feedforward >= 20 dB
    through the drivers, each within AGREE_DB of its lockstep twin. (The feedforward's figure fell 1.3-2.2 dB
    short of its twin in one run of three while the trace metered began before the loop and ran into its null
    tail: tests/drivers/test_hil_metering.py.) More than 1 % of a mode's periods late is said (EXIT_SUSPECT) and
    still judged here."""
    out = hil_2khz_run
    skip_unless_on_time(out)
    assert ran_to_the_end(out), out.stderr[-2000:]
    res = json.loads(out.stdout)
    fb, ff = res["isolation_reduction_db"], res["feedforward_reduction_db"]
    twin = res["lockstep_reduction_db"]
    why = f"drivers {fb} / {ff} dB, lockstep {twin}, late {res['late_periods']}; {out.stderr[-1500:]}"
    assert res["faults"] == 0, why
    assert fb >= 11.0 and ff >= 20.0, why
    assert fb == pytest.approx(twin["feedback"], abs=AGREE_DB), why
    assert ff == pytest.approx(twin["feedback_feedforward"], abs=AGREE_DB), why


def test_bad_rate_is_one_line_user_error():
    out = subprocess.run([sys.executable, "-m", "rig.cli", "hil", "--rate", "0", "--json"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.strip() == "rig hil: error: --rate: expected > 0 Hz and <= 5000 Hz, got '0'"


def test_rig_run_with_the_hil_backend():
    """`rig run --backend hil` goes through the same make_port and drivers (the runtime's command): it warms the
    controllers up INACTIVE (2 / blend_hz, about 5 s) and then isolates without reaching the clamp."""
    out = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--backend", "hil", "--config",
                          str(HIL_DEFAULT_CONFIG), "--seconds", "7.5"], capture_output=True, text=True,
                         timeout=300)
    skip_unless_on_time(out)
    missed = re.search(r"missed deadlines ([0-9.]+) %", out.stderr)
    if missed and float(missed.group(1)) > 100 * LATE_BOUND / 10:     # a few % late: the valves fall behind
        pytest.skip(f"host timing, not judged: missed deadlines {missed.group(1)} %")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "warming up the controllers for 5.1 s" in out.stderr
    assert "activate -> ACTIVE" in out.stderr
    assert "FAULT" not in out.stderr and "suspended" not in out.stderr

"""A short HIL run through the real drivers with the runtime's loop (`rig hil --json`): no faults, every period
recorded, and the reductions through the drivers (feedback; feedback + floor feedforward, the floor
accelerometers on the module's further channels) agree with the same controllers in lockstep simulated time
with the delay the drivers are designed to give (ZOH + one period). If the drivers lost samples or
conversions, added periods of latency, swapped channels or scaled wrongly, the two would disagree (a lost
accelerometer conversion per second is enough to put the valves at the clamp)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from rig.config import load_config
from rig.commands.hil import HIL_DEFAULT_CONFIG, hil_config

pytestmark = pytest.mark.hil           # the real drivers against the emulated devices, on loopback

SECONDS = 15.0                           # off, feedback, feedback + feedforward: 5 s each (as `rig hil`)


LATE_BOUND = 0.10            # the targets are judged on runs with at most this share of late metered periods


def _faulted(out) -> bool:
    try:
        res = json.loads(out.stdout)
        return res["faults"] > 0 or max(res["late_periods"].values()) > LATE_BOUND
    except (ValueError, KeyError, TypeError, AttributeError):
        return False


def _skip_if_late(res, mode: str) -> None:
    """The reductions are judged on runs the host let the loop keep on time; beyond LATE_BOUND named, not judged."""
    late = res["late_periods"][mode]
    if late > LATE_BOUND:
        pytest.skip(f"{100 * late:.1f} % of the metered {mode} periods late (judged for <= {100 * LATE_BOUND:g} %): "
                    f"the machine is too loaded to judge it")


@pytest.fixture(scope="module")
def hil_run(tmp_path_factory):
    """One `rig hil` run. A run that faulted, or had more than LATE_BOUND of a mode's periods late, is run once more, and said so on stderr: on this shared 2-core
    host a stall of 100 ms (the emulated serial amplifier past its staleness limit under load, or one
    100.8 ms gap between periods seen at load 1.2 in 1 of 3 clean-clone runs) faults a run now and then, and
    the safety rules are right to fault it. Two faulted runs in a row fail the tests."""
    rec = tmp_path_factory.mktemp("hil") / "run.h5"
    argv = [sys.executable, "-m", "rig.cli", "hil", "--seconds", str(SECONDS), "--record", str(rec), "--json"]
    out = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    load = os.getloadavg()[0]
    if _faulted(out):
        print(f"rig hil faulted at load average {load:.1f} on {os.cpu_count()} cores "
              f"({out.stderr.strip().splitlines()[-4:]}); run once more", file=sys.stderr)
        rec.unlink(missing_ok=True)
        out = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    return out, rec


def test_json_schema_and_clean_run(hil_run):
    out, rec = hil_run
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)                       # only JSON on stdout
    assert set(res) == {"transports", "faults", "overruns", "iterations", "samples_recorded",
                        "isolation_reduction_db", "feedforward_reduction_db", "transmissibility_db", "late_periods",
                        "recording"}
    assert set(res["transmissibility_db"]) == set(res["late_periods"]) == {"off", "feedback", "feedback_feedforward"}
    assert all(0.0 <= v <= 1.0 for v in res["late_periods"].values())
    assert res["transports"] == ["canopen", "modbus_tcp", "serial"]
    assert res["faults"] == 0
    cfg = hil_config(load_config(HIL_DEFAULT_CONFIG))
    assert res["iterations"] >= 0.9 * SECONDS * cfg.loop.rate_hz
    assert res["samples_recorded"] == res["iterations"]      # every period's sample recorded
    assert res["recording"] == str(rec)
    with h5py.File(rec, "r") as f:
        n = f["time_s"].shape[0] if "time_s" in f else None
        assert n is None or n == res["iterations"]
        on, floor = f["feedforward_on"][()], f["floor_accel_mps2"][()]
    # the last third, switched on live; the run ends through one INACTIVE period (valves null, feedforward off)
    assert 0 < on.mean() < 0.5 and on[-2] == 1.0 and on[-1] == 0.0
    assert floor.shape[1] == 4 and 1e-3 < floor.std() < 1.0  # the floor accelerometers came over Modbus


def test_reduction_through_drivers_matches_lockstep_simulation(hil_run):
    from controllers.isolation import params_from_config
    from controllers.tune_hil import table_rms
    out, _ = hil_run
    res = json.loads(out.stdout)
    _skip_if_late(res, "feedback")
    cfg = hil_config(load_config(HIL_DEFAULT_CONFIG))
    dt = 1.0 / cfg.loop.rate_hz
    p = params_from_config(cfg)
    third = SECONDS / 3 - min(cfg.hil.settle_s, SECONDS / 6)
    off = table_rms(cfg, p, dt, third, 1, False, seed=cfg.vibration.seed)
    on = table_rms(cfg, p, dt, third, 1, True, seed=cfg.vibration.seed)
    sil_db = 20 * math.log10(off / on)
    print(f"reduction through the drivers {res['isolation_reduction_db']} dB, lockstep simulation {sil_db:.2f} dB")
    assert sil_db > 6.0                                  # the HIL design itself (hil.toml) meets the target
    # the loop through the real drivers does what the same controller does in lockstep simulation (4 s of
    # floor motion per half: the two halves differ by ~1 dB on their own)
    why = f"through the drivers {res['isolation_reduction_db']} dB, lockstep {sil_db:.2f} dB; {out.stderr[-1500:]}"
    assert res["isolation_reduction_db"] == pytest.approx(sil_db, abs=2.5), why
    assert res["isolation_reduction_db"] > 4.5, why


def _lockstep_table_rms(cfg, mode: str, seconds: float) -> float:
    """The table's rms in lockstep simulated time (sim backend: one period of delay), after 1 s settling."""
    from rig.runtime.clock import SimClock
    from rig.runtime.session import Session
    with Session(cfg, "sim", clock=SimClock(), isolation=mode != "off",
                 feedforward=mode == "feedback_feedforward") as s:
        s.loop.activate()
        n0, n = int(cfg.loop.rate_hz), int((1.0 + seconds) * cfg.loop.rate_hz)
        xs = []
        for k in range(n):
            s.loop.cycle(k * s.loop.period_ns)
            if k >= n0:
                xs.append(s.port.plant.table_m)
    return float(np.std(xs))


def test_feedforward_through_drivers_matches_lockstep_simulation(hil_run):
    """Feedback + floor feedforward through the drivers (floor accelerometers over Modbus, switched on live)
    reduces the table motion as the same loop does in lockstep (within 3.5 dB: other stretches of the floor,
    and a loaded machine's late periods), and beyond feedback alone (swapped or misscaled floor channels would
    undo that)."""
    out, _ = hil_run
    res = json.loads(out.stdout)
    _skip_if_late(res, "feedback_feedforward")
    cfg = hil_config(load_config(HIL_DEFAULT_CONFIG))
    third = SECONDS / 3 - min(cfg.hil.settle_s, SECONDS / 6)
    sil_db = 20 * math.log10(_lockstep_table_rms(cfg, "off", third)
                             / _lockstep_table_rms(cfg, "feedback_feedforward", third))
    got = res["feedforward_reduction_db"]
    why = f"through the drivers {got} dB, lockstep {sil_db:.2f} dB; {out.stderr[-1500:]}"
    assert sil_db > 10.0                                 # the HIL design (hil.toml) meets the target
    assert got == pytest.approx(sil_db, abs=3.5), why
    assert got > res["isolation_reduction_db"] + 1.0, why




def test_feedforward_meets_the_target_through_the_drivers(hil_run):
    """Issue 14's HIL target: feedback + floor feedforward through the drivers >= 10 dB, 0 faults. Stated for
    runs in which at most LATE_BOUND of the metered periods were late (the loop woke a period late, or the
    Modbus reply with the new conversion came late); a machine loaded beyond that (other processes at real-time
    priority on its 2 cores) is named in the skip, not judged."""
    out, _ = hil_run
    res = json.loads(out.stdout)
    assert res["faults"] == 0, out.stderr[-1500:]
    _skip_if_late(res, "feedback_feedforward")
    assert res["feedforward_reduction_db"] >= 10.0, (res["late_periods"], out.stderr[-1500:])


def test_bad_rate_is_one_line_user_error():
    out = subprocess.run([sys.executable, "-m", "rig.cli", "hil", "--rate", "0", "--json"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.strip() == "rig hil: error: --rate: expected > 0 Hz and <= 5000 Hz, got '0'"


def test_rig_run_with_the_hil_backend():
    """`rig run --backend hil` goes through the same make_port and drivers (the runtime's command): it warms the
    controllers up INACTIVE (2 / blend_hz, about 5 s) and then isolates without reaching the clamp."""
    out = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--backend", "hil", "--config",
                          str(HIL_DEFAULT_CONFIG), "--seconds", "7.5", "--quiet"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "warming up the controllers for 5.1 s" in out.stderr
    assert "activate -> ACTIVE" in out.stderr
    assert "FAULT" not in out.stderr and "suspended" not in out.stderr

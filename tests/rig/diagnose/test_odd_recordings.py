"""Odd recordings get a clear answer, not a wrong diagnosis or a traceback (issue 12): too short, absurd values,
gaps, a clipped transducer, a plant the model does not describe, closed-loop data (diagnose and identify)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.signal import lfilter

from rig.diagnose import locate, prove
from rig.errors import EXIT_SUSPECT
from rig.recordings.recording import Recording
from rig.recordings.rigformat import save_recording_csv
from sim_backend.actuator import Effects, StandPlant
from sim_backend.linear import ActuatorParams

RIG = [sys.executable, "-m", "rig.cli"]


def _rig(*args):
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=600)


def _chirp(duration_s, effects=None, fs=1000.0):
    return prove.simulate_case(prove.Case(name="odd", effects=effects or {}, linear={}, duration_s=duration_s,
                                          fs_hz=fs, seed=9))


def _save(tmp_path, name, cmd, pos, acc, fs):
    return save_recording_csv(Recording.from_signals(cmd, pos, acc, fs_hz=fs), tmp_path / name)


def _no_traceback(res):
    assert "Traceback" not in res.stderr and "Traceback" not in res.stdout


def test_one_second_recording_says_no_claim(tmp_path):
    path = save_recording_csv(_chirp(1.0), tmp_path / "short.csv")
    res = _rig("diagnose", path, "--out", tmp_path / "o")
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    doc = json.loads((tmp_path / "o" / "diagnosis.json").read_text())
    assert doc["effects"] == [] and doc["verdict"]["status"] == "no_claim"
    assert "too short" in doc["summary"] and "No claim" in res.stdout


def test_absurd_value_is_one_line(tmp_path):
    rec = _chirp(3.0)
    pos = rec.position_m.copy()
    pos[1234] = 1e300
    path = _save(tmp_path, "huge.csv", rec.valve_cmd_V, pos, rec.accel_mps2, rec.fs_hz)
    for cmd in ("diagnose", "identify"):
        res = _rig(cmd, path, *(("--out", tmp_path / "o") if cmd == "diagnose" else ()))
        _no_traceback(res)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1
        assert "position_m" in lines[0] and "sample 1234" in lines[0] and str(path) in lines[0]


def test_rows_missing_everywhere_is_one_line_saying_what_to_do(tmp_path):
    """Gaps too many to leave a usable stretch (a long gap every 60 samples): refused in one line. Fewer gaps
    are mended (tests/rig/test_recording_loader.py, tests/test_uses.py)."""
    rec = _chirp(3.0)
    keep = np.arange(rec.n) % 60 < 50
    path = tmp_path / "gap.csv"
    with open(path, "w") as fh:
        fh.write("time_s,valve_cmd_V,position_m,accel_mps2\n")
        np.savetxt(fh, np.c_[rec.t_s, rec.valve_cmd_V, rec.position_m, rec.accel_mps2][keep], delimiter=",",
                   fmt="%.9g")
    res = _rig("diagnose", path, "--out", tmp_path / "o")
    _no_traceback(res)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1
    assert "rows missing" in lines[0] and "holds 50 samples, need at least 100" in lines[0]
    assert "record again" in lines[0]


def test_clipped_transducer_is_reported_and_left_out(tmp_path):
    rec = _chirp(20.0, {"transport_delay": {"delay_s": 1.2e-3}})
    lim = 0.8 * np.max(rec.position_m)
    path = _save(tmp_path, "clip.csv", rec.valve_cmd_V, np.minimum(rec.position_m, lim), rec.accel_mps2, rec.fs_hz)
    res = _rig("diagnose", path, "--out", tmp_path / "o")
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    doc = json.loads((tmp_path / "o" / "diagnosis.json").read_text())
    assert [e["name"] for e in doc["effects"]] == ["transport_delay"]
    (clip,) = doc["sensor"]["clipped"]
    assert clip["channel"] == "position_m" and clip["high"] == pytest.approx(lim, rel=1e-6)
    data = np.loadtxt(tmp_path / "o" / "fit.csv", delimiter=",", skiprows=1)
    at_top = data[:, 1] >= lim * (1 - 1e-9)
    assert at_top.sum() - 3 <= clip["samples"] <= at_top.sum()     # flat tops (a lone peak sample may touch it)
    assert data[at_top, 6].sum() <= 3                              # left out of the fit
    assert doc["fit"]["augmented"]["residual_over_noise"] < 1.3
    assert "clipped" in (tmp_path / "o" / "report.md").read_text()


def test_a_geared_motor_at_100_hz_is_not_described(tmp_path):
    """Another plant (an integrating DC motor), sampled at 100 Hz, no accelerometer: no traceback, no claim of
    'explained', no effect named, and the reasons."""
    rng = np.random.default_rng(0)
    fs, n = 100.0, 6000
    u = np.repeat(rng.uniform(-6, 6, n // 100), 100)
    a = np.exp(-1 / (fs * 0.2))
    x = np.cumsum(lfilter([0, 1 - a], [1, -a], 10 * u)) / fs + rng.normal(0, 1e-3, n)   # sampled before u acts
    path = _save(tmp_path, "motor.csv", u, x, np.zeros(n), fs)
    res = _rig("diagnose", path, "--out", tmp_path / "o")
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    doc = json.loads((tmp_path / "o" / "diagnosis.json").read_text())
    assert doc["effects"] == [] and doc["verdict"]["status"] == "not_described"
    assert "does not describe" in doc["summary"] and "explains" not in doc["summary"]
    assert any("100 Hz" in s for s in doc["verdict"]["suggestions"])
    assert any("no accelerometer" in s for s in doc["verdict"]["suggestions"])


def test_mismatch_bands_without_bands():
    """Too few frequency bins for any band (the 100 Hz motor's traceback): no bands, not an IndexError."""
    x = np.random.default_rng(0).standard_normal(50)
    frf = locate.frf_bands(x, x, {"nominal": x}, 100.0, 1.0, 0.5)
    assert len(frf["freqs_hz"]) == 0
    assert locate.mismatch_bands(frf, "nominal") == []


def _closed_loop(tmp_path, plant: str):
    """A position loop (PI on the transducer) tracking a chirp: the command reacts to the measured position."""
    fs, n = 1000.0, 30000
    t = np.arange(n) / fs
    ref = 3e-6 * np.sin(2 * np.pi * (0.1 * t + 0.5 * 20 / 30 * t ** 2))
    u, y = np.zeros(n), np.zeros(n)
    rng = np.random.default_rng(1)
    stand = StandPlant(ActuatorParams(), Effects(position_noise_m=2e-8, accel_noise_mps2=2e-4, seed=3), fs)
    v = pos = integ = 0.0
    for k in range(n):
        y[k] = stand.position_m if plant == "stand" else pos + 2e-8 * rng.standard_normal()
        err = ref[k] - y[k]
        integ += err / fs
        u[k] = np.clip(4e5 * err + 2e6 * integ, -10, 10)
        if plant == "stand":
            stand.step(u[k])
        else:                       # a motor: velocity lags the command, the position integrates it
            v += (2e-5 * u[k] - v) / (0.05 * fs)
            pos += v / fs
    return _save(tmp_path, f"closed_{plant}.csv", u, y, np.zeros(n), fs)


def test_identify_says_closed_loop(tmp_path):
    path = _closed_loop(tmp_path, "stand")
    res = _rig("identify", path, "--json")
    _no_traceback(res)
    assert res.returncode == EXIT_SUSPECT, res.stderr       # identified, with the warning that qualifies it
    doc = json.loads(res.stdout)
    assert doc["fit"]["closed_loop"]["closed_loop"] is True
    assert "closed-loop" in doc["fit"]["warning"] and "rig identify: warning: closed-loop" in res.stderr
    # an open-loop chirp is not flagged
    open_path = save_recording_csv(_chirp(20.0), tmp_path / "open.csv")
    doc2 = json.loads(_rig("identify", open_path, "--json").stdout)
    assert doc2["fit"]["closed_loop"]["closed_loop"] is False


def test_diagnose_of_closed_loop_other_plant_says_why(tmp_path):
    path = _closed_loop(tmp_path, "motor")
    res = _rig("diagnose", path, "--out", tmp_path / "o", "--json")
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert doc["verdict"]["status"] == "not_described" and doc["effects"] == []
    assert "explains the recording" not in doc["summary"]
    assert any("Closed-loop data" in s for s in doc["verdict"]["suggestions"])


# A `rig run` recording of the four-mount rig now goes to the machine diagnosis (issue 28), which replays its
# closed loop's inputs: tests/rig/diagnose/machine/test_diagnose_cli.py runs it as a user does.


@pytest.mark.slow
def test_position_logged_a_sample_early_gets_a_time_alignment_hint(tmp_path):
    rec = _chirp(12.0)
    early = np.r_[rec.position_m[1:], rec.position_m[-1]]           # each position stamped one sample early
    paths = {"early": _save(tmp_path, "early.csv", rec.valve_cmd_V, early, rec.accel_mps2, rec.fs_hz),
             "aligned": _save(tmp_path, "aligned.csv", rec.valve_cmd_V, rec.position_m, rec.accel_mps2, rec.fs_hz)}
    hints = {}
    for name, path in paths.items():
        res = _rig("diagnose", path, "--out", tmp_path / name)
        _no_traceback(res)
        assert res.returncode == 0, res.stderr
        doc = json.loads((tmp_path / name / "diagnosis.json").read_text())
        hints[name] = [s for s in doc["verdict"]["suggestions"] if "time alignment" in s]
    assert len(hints["early"]) == 1 and "shifted by 1 sample (1 ms)" in hints["early"][0]
    assert "leads the command" in hints["early"][0]
    assert hints["aligned"] == []

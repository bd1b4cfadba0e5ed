"""docs/RUN_RECORDING.md is the whole of what the diagnosis reads: a file written from it is read, units are
converted, rows missing are mended, and a bad file is refused in one line naming the file and the dataset --
through the command line too (exit 2, no traceback)."""
from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest

from rig.recordings.runfile import is_run_recording, read_run
from rig.errors import RecordingError
from tests.rig.diagnose.machine.support import DT, open_loop_run, rig_cfg, write_run


@pytest.fixture(scope="module")
def rows():
    return open_loop_run(rig_cfg(True), 6.0, seed=3)


def test_a_file_written_from_the_page_is_read(tmp_path, rows):
    p = tmp_path / "run.h5"
    write_run(p, rows)
    assert is_run_recording(p)
    r = read_run(p)
    assert r.fs_hz == pytest.approx(1 / DT) and r.n == len(rows["time_s"]) and r.floor_measured
    assert np.array_equal(r.stroke_m, rows["stroke_m"]) and r.mode_seconds() == {"off": pytest.approx(6.0)}


def test_units_are_converted_and_flags_are_optional(tmp_path, rows):
    p = tmp_path / "run_um.h5"
    scaled = dict(rows, stroke_m=rows["stroke_m"] * 1e6, accel_mps2=rows["accel_mps2"] / 9.80665)
    write_run(p, scaled, flags=False, units={"accel_mps2": "g", "stroke_m": "um", "valve_cmd_V": "V",
                                             "floor_accel_mps2": "m/s^2"})
    r = read_run(p)
    assert np.allclose(r.stroke_m, rows["stroke_m"]) and np.allclose(r.accel_mps2, rows["accel_mps2"])
    assert r.mode is None


def test_rows_missing_are_mended_as_every_reader_does(tmp_path, rows):
    p = tmp_path / "gaps.h5"
    keep = np.ones(len(rows["time_s"]), bool)
    keep[1000:1002] = False
    write_run(p, {k: v[keep] for k, v in rows.items()})
    r = read_run(p)
    assert r.n == len(rows["time_s"]) and "bridged" in r.gaps


@pytest.mark.parametrize("change, match", [
    (lambda f: f.__delitem__("stroke_m"), "no dataset stroke_m"),
    (lambda f: f.attrs.__delitem__("rate_hz"), "rate_hz"),
    (lambda f: f["valve_cmd_V"].attrs.__setitem__("unit", "furlong"), "valve_cmd_V: unit 'furlong'"),
    (lambda f: f["accel_mps2"].attrs.__setitem__("labels", ["rear_left", "front_right", "front_left", "rear_right"]),
     "accel_mps2: columns labelled"),
    (lambda f: f.attrs.__setitem__("rate_hz", 1000.0), "rate_hz = 1000 Hz, but time_s steps by"),   # were believed
    (lambda f: f["time_s"].__setitem__(slice(3000, None), f["time_s"][3000:] - 0.5),
     "time_s: not increasing at row 3000"),
    (lambda f: f["time_s"].__setitem__(3000, f["time_s"][2990]), "time_s: not increasing at row 3000"),
    (lambda f: f["stroke_m"].__setitem__((100, 0), 1e300), "dataset stroke_m: 1e\\+300 at row 100: not a plausible"),
])
def test_a_bad_file_is_refused_in_one_line(tmp_path, rows, change, match):
    p = tmp_path / "bad.h5"
    write_run(p, rows)
    with h5py.File(p, "a") as f:
        change(f)
    with pytest.raises(RecordingError, match=match) as e:
        read_run(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_nan_short_and_wrong_shape(tmp_path, rows):
    bad = dict(rows, accel_mps2=rows["accel_mps2"].copy())
    bad["accel_mps2"][777, 2] = np.nan
    write_run(tmp_path / "nan.h5", bad)
    with pytest.raises(RecordingError, match="accel_mps2: not a finite number at row 777"):
        read_run(tmp_path / "nan.h5")
    write_run(tmp_path / "short.h5", {k: v[:5000] for k, v in rows.items()})
    with pytest.raises(RecordingError, match="at least 5 s"):
        read_run(tmp_path / "short.h5")
    with h5py.File(tmp_path / "three.h5", "w") as f:
        f.attrs["rate_hz"] = 5000.0
        for k in ("time_s", "accel_mps2", "stroke_m", "valve_cmd_V"):
            f[k] = rows[k] if k == "time_s" else rows[k][:, :3]
    assert not is_run_recording(tmp_path / "three.h5")
    with pytest.raises(RecordingError, match=r"expected shape \(rows, 4\)"):
        read_run(tmp_path / "three.h5")


def test_the_command_line_says_it_in_one_line(tmp_path, rows):
    bad = dict(rows, stroke_m=rows["stroke_m"].copy())
    bad["stroke_m"][100, 0] = np.inf
    write_run(tmp_path / "inf.h5", bad)
    res = subprocess.run([sys.executable, "-m", "rig.cli", "diagnose", str(tmp_path / "inf.h5"), "--out",
                          str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "stroke_m: not a finite number at row 100" in res.stderr

"""Recording loader: the shared CSV(.gz), our HDF5 (also as rig.runtime.recorder writes it), MATLAB .mat, and every kind
of bad input ending in one RecordingError line that names the file and the problem."""
from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from rig.errors import RecordingError
from tests.paths import RECORDINGS
from rig.recordings.recording import COLUMNS, MIN_SAMPLES, Recording
from rig.recordings.rigformat import load_recording, save_recording_csv, save_recording_h5, save_recording_mat

SHARED = RECORDINGS / "p01_nominal.csv.gz"
HEADER = ",".join(COLUMNS)


def _rec(n=500, fs=1000.0) -> Recording:
    t = np.arange(n) / fs
    u = np.sin(2 * np.pi * 5 * t)
    return Recording.from_arrays(t, u, 2.7e-6 * u + 1e-9 * np.cos(t), -1e-3 * u, source="synthetic")


def _csv_text(rows: list[str], header: str = HEADER) -> str:
    return header + "\n" + "\n".join(rows) + "\n"


def _good_rows(n=200, fs=1000.0):
    return [f"{k / fs:.6f},{math.sin(k / 10):.6g},{1e-6 * math.sin(k / 10):.6g},{1e-3 * k:.6g}" for k in range(n)]


@pytest.mark.shared
def test_shared_recording_loads_as_published():
    rec = load_recording(SHARED)
    assert rec.n == 100_000
    assert rec.fs_hz == pytest.approx(1000.0, rel=1e-9)
    assert rec.t_s[0] == 0.0 and rec.valve_cmd_V[0] == 0.0
    assert rec.position_m[0] == pytest.approx(3.42079e-08)        # first data row of the file
    assert np.max(np.abs(rec.valve_cmd_V)) == pytest.approx(2.0, abs=1e-3)   # answers.json amplitude_V


@pytest.mark.parametrize("name", ["r.csv", "r.csv.gz", "r.h5", "r.mat"])
def test_round_trip_each_format(tmp_path, name):
    rec = _rec()
    path = tmp_path / name
    if name.endswith(".h5"):
        save_recording_h5(rec, path)
    elif name.endswith(".mat"):
        save_recording_mat(rec, path)
    else:
        save_recording_csv(rec, path)
    back = load_recording(path)
    assert back.n == rec.n and back.fs_hz == pytest.approx(1000.0, rel=1e-9)
    for c in ("t_s", "valve_cmd_V", "position_m", "accel_mps2"):
        np.testing.assert_allclose(getattr(back, c), getattr(rec, c), rtol=1e-8, atol=1e-15)
    assert back.source == str(path)


def _recorded_chirp(path, position_unit: str = "m", per_metre: float = 1.0):
    """400 rows at 2 kHz as rig.runtime.recorder writes them, the position in `position_unit`."""
    from rig.runtime.recorder import Channel, Recorder
    r = Recorder(path, [Channel("time_s", "s"), Channel("valve_cmd_V", "V"), Channel("position_m", position_unit),
                        Channel("accel_mps2", "m/s^2")], rate_hz=2000.0).start()
    for k in range(400):
        r.push(k / 2000.0, math.sin(k / 7), per_metre * 1e-6 * math.sin(k / 7 - 0.3), 0.01 * k)
    r.close()
    return path


def test_reads_what_rig_recorder_writes(tmp_path):
    rec = load_recording(_recorded_chirp(tmp_path / "chirp.h5"))
    assert rec.n == 400 and rec.fs_hz == pytest.approx(2000.0)
    assert rec.position_m[7] == pytest.approx(1e-6 * math.sin(1 - 0.3))


def test_a_unit_attribute_is_read_not_ignored(tmp_path):
    """Was: a chirp whose position_m says unit = "mm" (or "furlong") identified as if in metres."""
    import h5py
    path = _recorded_chirp(tmp_path / "chirp.h5", "mm", 1e3)
    assert load_recording(path).position_m[7] == pytest.approx(1e-6 * math.sin(1 - 0.3))
    with h5py.File(path, "r+") as f:
        f["position_m"].attrs["unit"] = "furlong"
    with pytest.raises(RecordingError, match="dataset position_m: unit 'furlong' \\(expected one of m, mm, um\\)"):
        load_recording(path)


def test_per_mount_hdf5_picks_the_mount_by_label(tmp_path):
    import h5py
    path = tmp_path / "rig.h5"
    n = 300
    with h5py.File(path, "w") as f:
        f["time_s"] = np.arange(n) / 1000.0
        for c in COLUMNS[1:]:
            d = f.create_dataset(c, data=np.arange(n)[:, None] * np.array([1.0, 2.0, 3.0, 4.0]))
            d.attrs["labels"] = ["front_left", "front_right", "rear_left", "rear_right"]
    assert load_recording(path, mount="rear_left").position_m[10] == 30.0
    assert load_recording(path, mount=1).valve_cmd_V[10] == 20.0
    with pytest.raises(RecordingError, match="mount 'middle' not recorded"):
        load_recording(path, mount="middle")


def test_crlf_bom_column_order_and_extra_columns(tmp_path):
    rows = [f"{1e-6 * k:.6g},{k / 1000:.6f},{0.5:.3f},{0.1:.3f},{k}" for k in range(150)]
    text = "\ufeffposition_m,time_s,accel_mps2,valve_cmd_V,spool_mA\r\n" + "\r\n".join(rows) + "\r\n"
    p = tmp_path / "odd.csv"
    p.write_text(text, encoding="utf-8", newline="")
    rec = load_recording(p)
    assert rec.n == 150 and rec.position_m[3] == pytest.approx(3e-6) and rec.valve_cmd_V[0] == 0.1


# ---- bad input: one line naming the file and the problem ----------------------------------------------

BAD_CASES = {
    "empty": (b"", "empty file"),
    "blank": (b"\n\n  \n", "empty file"),
    "header_only": (HEADER.encode() + b"\n", "no data rows"),
    "wrong_columns": (_csv_text(_good_rows(), "t,u,y,a").encode(), "wrong columns"),
    # found by the abuse trial: refused as "wrong columns" without naming the separator the file has
    "semicolon_separated": (_csv_text([r.replace(",", ";") for r in _good_rows()], HEADER.replace(",", ";")).encode(),
                            f"one field on ',' but 4 on ';': the file looks ';'-separated; expected ','-separated "
                            f"columns {HEADER} "),
    "tab_separated": (_csv_text([r.replace(",", "\t") for r in _good_rows()], HEADER.replace(",", "\t")).encode(),
                      "the file looks tab-separated; expected ','-separated"),
    "missing_column": (_csv_text([r.rsplit(",", 1)[0] for r in _good_rows()],
                                 "time_s,valve_cmd_V,position_m").encode(), "missing accel_mps2"),
    "nan": (_csv_text(_good_rows()[:50] + ["0.050000,nan,0,0"] + _good_rows(200)[51:]).encode(),
            "valve_cmd_V is nan"),
    "inf": (_csv_text(_good_rows()[:60] + ["0.060000,0,inf,0"] + _good_rows(200)[61:]).encode(),
            "position_m is inf"),
    "non_numeric": (_csv_text(_good_rows()[:70] + ["0.070000,abc,0,0"] + _good_rows(200)[71:]).encode(),
                    "line 72 is not numeric"),
    "short_row": (_csv_text(_good_rows()[:80] + ["0.080000,1,2"] + _good_rows(200)[81:]).encode(),
                  "line 82 has 3 fields, expected 4"),
    "time_backwards": (_csv_text(_good_rows()[:90] + [_good_rows()[88]] + _good_rows()[91:]).encode(),
                       "time_s not increasing at sample 90 (0.089 s then 0.088 s)"),   # (not np.float64(...))
    "time_jump": (_csv_text(_good_rows()[:100] + [f"{0.1004:.6f},0,0,0"] + _good_rows()[101:]).encode(),
                  "time_s not uniform at sample 100"),
    "rows_missing_everywhere": (_csv_text([r for i, r in enumerate(_good_rows(2000)) if i % 20 >= 8]).encode(),
                                "the longest stretch without a gap over 3 samples holds 12 samples"),
    "too_short": (_csv_text(_good_rows(MIN_SAMPLES - 1)).encode(), f"too short: {MIN_SAMPLES - 1} samples"),
    "binary": (bytes(range(256)) * 20, "binary data"),
    "latin1": (_csv_text(_good_rows()).encode() + "\xe9\xff".encode("latin-1"), "binary data"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_csv_is_one_line_naming_file_and_problem(tmp_path, case):
    data, expect = BAD_CASES[case]
    path = tmp_path / f"{case}.csv"
    path.write_bytes(data)
    with pytest.raises(RecordingError) as ei:
        load_recording(path)
    msg = str(ei.value)
    assert "\n" not in msg and str(path) in msg and expect in msg, msg


def test_truncated_gzip(tmp_path):
    good = tmp_path / "good.csv.gz"
    save_recording_csv(_rec(2000), good)
    raw = good.read_bytes()
    cut = tmp_path / "cut.csv.gz"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(RecordingError, match=r"cut\.csv\.gz: truncated gzip"):
        load_recording(cut)


def test_not_gzip_with_gz_name_and_not_hdf5_with_h5_name(tmp_path):
    a = tmp_path / "a.csv.gz"
    a.write_bytes(b"\x1f\x8bgarbage that is not deflate")
    with pytest.raises(RecordingError, match="a.csv.gz: (corrupt|truncated) gzip"):
        load_recording(a)
    b = tmp_path / "b.h5"
    b.write_text(_csv_text(_good_rows()))
    with pytest.raises(RecordingError, match="b.h5: not an HDF5 file"):
        load_recording(b)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(RecordingError, match="no such file"):
        load_recording(tmp_path / "nope.csv")
    with pytest.raises(RecordingError, match="is a directory"):
        load_recording(tmp_path)


@pytest.mark.parametrize("command", [["identify"], ["diagnose"], ["report"], ["export", "--to", "csv"]])
def test_a_named_pipe_is_refused_in_one_line_not_waited_on(tmp_path, command):
    """Found by the abuse trial: a FIFO given as the recording hung the command for ever (reading waits for a
    writer); report and export then called it "no such recording". Now one line saying what it is, exit 2 (the
    timeout only ends the old hang)."""
    import os
    import subprocess
    import sys
    fifo = tmp_path / "pipe.h5"    # not .csv: export --to csv would write pipe.csv beside it
    os.mkfifo(fifo)
    r = subprocess.run([sys.executable, "-m", "rig.cli", command[0], str(fifo), *command[1:]], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.splitlines() == [f"rig {command[0]}: error: {fifo}: a named pipe, expected a regular file "
                                     "(a recording)"]


def test_hdf5_and_mat_with_wrong_variables(tmp_path):
    import h5py
    import scipy.io
    h = tmp_path / "w.h5"
    with h5py.File(h, "w") as f:
        f["time_s"] = np.arange(200) / 1e3
        f["cmd"] = np.zeros(200)
    with pytest.raises(RecordingError, match="w.h5: wrong datasets: missing valve_cmd_V, position_m, accel_mps2"):
        load_recording(h)
    m = tmp_path / "w.mat"
    scipy.io.savemat(m, {"time_s": np.arange(200) / 1e3, "x": np.zeros(200)})
    with pytest.raises(RecordingError, match="w.mat: wrong variables: missing valve_cmd_V"):
        load_recording(m)


def test_rows_missing_are_bridged_or_the_longest_stretch_kept(tmp_path):
    """Rows a real-clock run dropped: short gaps bridged (the recorded samples untouched), a long one splits the
    recording and its longest stretch is kept; either way one line says what was done."""
    rows = _good_rows(2000)
    p = tmp_path / "bridged.csv"
    p.write_text(_csv_text([r for i, r in enumerate(rows) if i not in (100, 700, 1200, 1201, 1202)]))
    rec = load_recording(p)
    assert rec.n == 2000 and rec.fs_hz == pytest.approx(1000.0)
    assert "3 gaps of at most 3 samples bridged by linear interpolation (5 of 2000 samples, first at t = 0.099 s)" \
        in rec.gaps and str(p) in rec.gaps
    assert rec.valve_cmd_V[99] == pytest.approx(math.sin(9.9), abs=1e-6)            # recorded: as it was
    assert rec.valve_cmd_V[100] == pytest.approx((math.sin(9.9) + math.sin(10.1)) / 2, abs=1e-6)   # bridged
    assert rec.t_s[1201] == pytest.approx(1.201)
    p = tmp_path / "split.csv"
    p.write_text(_csv_text(rows[:500] + rows[800:]))
    rec = load_recording(p)
    assert rec.n == 1200 and rec.t_s[0] == pytest.approx(0.8) and rec.valve_cmd_V[0] == pytest.approx(math.sin(80))
    assert "used the longest stretch without a gap over 3 samples: t = 0.8 to 1.999 s (1200 of 2000 samples; " \
           "1 longer gap (300 samples) left out)" in rec.gaps
    p = tmp_path / "whole.csv"
    p.write_text(_csv_text(rows))
    assert load_recording(p).gaps == ""


def test_unequal_lengths_and_non_uniform_time_in_hdf5(tmp_path):
    import h5py
    t = np.arange(300) / 1e3
    t[150:] += 0.0004                         # the clock jumps by 40 % of a period once
    for name, n_pos, time_s, expect in (("u.h5", 299, np.arange(300) / 1e3, "position_m has 299 samples, time_s has 300"),
                                        ("j.h5", 300, t, "time_s not uniform at sample 150")):
        h = tmp_path / name
        with h5py.File(h, "w") as f:
            f["time_s"] = time_s
            f["valve_cmd_V"] = np.zeros(300)
            f["position_m"] = np.zeros(n_pos)
            f["accel_mps2"] = np.zeros(300)
        with pytest.raises(RecordingError, match=expect):
            load_recording(h)


# ---- property tests: arbitrary input never escapes as anything but RecordingError ----------------------

SUFFIXES = [".csv", ".csv.gz", ".h5", ".mat", ".dat"]
_fs_settings = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@_fs_settings
@given(data=st.binary(max_size=3000), suffix=st.sampled_from(SUFFIXES),
       magic=st.sampled_from([b"", b"\x1f\x8b\x08\x00", b"\x89HDF\r\n\x1a\n", b"MATLAB 5.0 MAT-file", HEADER.encode()]))
def test_arbitrary_bytes_only_raise_recording_error(tmp_path, data, suffix, magic):
    p = tmp_path / f"x{suffix}"
    p.write_bytes(magic + data)
    try:
        rec = load_recording(p)
    except RecordingError as e:
        assert "\n" not in str(e) and str(p) in str(e)
    else:
        assert isinstance(rec, Recording) and rec.n >= MIN_SAMPLES


_cell = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(max_size=6),
                  st.integers(-10**30, 10**30).map(str), st.just(""))


@_fs_settings
@given(rows=st.lists(st.lists(_cell, min_size=0, max_size=6), max_size=40), gz=st.booleans(),
       cut=st.integers(0, 10_000))
def test_csv_like_text_only_raises_recording_error(tmp_path, rows, gz, cut):
    text = _csv_text([",".join(r) for r in rows]) + "\n".join(_good_rows(120))
    raw = text.encode("utf-8", "replace")
    if gz:
        raw = gzip.compress(raw)
        raw = raw[: max(1, len(raw) - cut % 64)] if cut % 3 == 0 else raw   # sometimes truncated
    p = tmp_path / ("y.csv.gz" if gz else "y.csv")
    p.write_bytes(raw)
    try:
        rec = load_recording(p)
    except RecordingError as e:
        assert "\n" not in str(e)
    else:
        assert np.all(np.isfinite(rec.position_m)) and np.all(np.diff(rec.t_s) > 0)


def test_matlab_v73_is_read_as_hdf5(tmp_path):
    # MATLAB -v7.3 writes HDF5 after a 512-byte user block starting "MATLAB 7.3 MAT-file", vectors as (1, n)
    import h5py
    path = tmp_path / "v73.mat"
    rec = _rec(300)
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, a in zip(COLUMNS, (rec.t_s, rec.valve_cmd_V, rec.position_m, rec.accel_mps2)):
            f[name] = a[None, :]
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Sat Nov 21 2026 HDF5 schema 1.00 .")
    back = load_recording(path)
    np.testing.assert_array_equal(back.position_m, rec.position_m)
    assert back.fs_hz == pytest.approx(1000.0)


def test_a_recording_its_writer_did_not_close_is_used_and_said_once(tmp_path, caplog):
    """Found by the abuse trial: a file rig.runtime.recorder left with complete = False (a crash, a kill) was read
    with no word. The one reader of files says it in one warning line naming the file, why and the rows it
    holds; the rows every channel has are used; a second read of the same file says nothing more."""
    import logging

    import h5py
    rec = _rec(500)
    path = save_recording_h5(rec, tmp_path / "cut.h5", attrs={"complete": False})
    with h5py.File(path, "r+") as f:                  # the writer died between two datasets' appends
        data = f["valve_cmd_V"][:420]
        del f["valve_cmd_V"]
        f["valve_cmd_V"] = data
    with caplog.at_level(logging.WARNING, logger="rig.recordings"):
        back = load_recording(path)
        load_recording(path)
    assert back.n == 420
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert said == [f"{path}: the run ended before the recording was closed (attribute complete = false): it may be "
                    f"cut short; it holds 420 rows (t = 0 to 0.419 s), used as they are"]
    caplog.clear()
    closed = save_recording_h5(rec, tmp_path / "closed.h5", attrs={"complete": True})
    with caplog.at_level(logging.WARNING, logger="rig.recordings"):
        load_recording(closed)
    assert not caplog.records

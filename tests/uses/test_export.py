"""`rig export REC --to mat|csv` as a MATLAB or spreadsheet user runs it (issue 29), on real recordings: one of
`rig run --record` in simulated time and one of `rig chirp`; every dataset, its unit, its labels, the file's
attributes and the events come back (scipy.io.loadmat, the csv module); a chirp's .mat is read by rig's own
loader; bad input is one line naming the file or option."""
from __future__ import annotations

import csv
import json
import subprocess
import sys

import h5py
import numpy as np
import pytest
import scipy.io

from rig.recordings.rigformat import load_recording

RIG = [sys.executable, "-m", "rig.cli"]


def _rig(*args, cwd=None):
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=600, cwd=cwd)


def _ok(res):
    assert "Traceback" not in res.stderr + res.stdout, res.stderr[-3000:]
    assert res.returncode == 0, res.stderr[-3000:]
    return res


@pytest.fixture(scope="module")
def run_rec(tmp_path_factory):
    """A recording as `rig run --record` makes it (the machine, four mounts), 2 s in simulated time."""
    d = tmp_path_factory.mktemp("export")
    _ok(_rig("run", "--record", d / "run.h5", "--sim-time", "--seconds", 2, "--quiet"))
    return d / "run.h5"


def _h5(path):
    """Every dataset of the file with its attributes, the file's attributes, the events."""
    out = {}
    with h5py.File(path, "r") as f:
        for k, obj in f.items():
            if isinstance(obj, h5py.Dataset):
                labels = [x.decode() if isinstance(x, bytes) else str(x) for x in obj.attrs.get("labels", [])]
                out[k] = (obj[()], str(obj.attrs.get("unit", "")), labels)
        events = [(float(t), x.decode() if isinstance(x, bytes) else x)
                  for t, x in zip(f["events/time_s"][()], f["events/text"][()])]
        attrs = dict(f.attrs)
    return out, attrs, events


def _text(x) -> str:
    """A MATLAB char array as loadmat gives it ('' comes back as an empty array)."""
    return "" if isinstance(x, np.ndarray) and x.size == 0 else str(x)


def test_mat_round_trip(run_rec):
    res = _ok(_rig("export", run_rec, "--to", "mat"))
    mat_path = run_rec.with_suffix(".mat")                          # the default: beside the recording
    assert f"wrote {mat_path}" in res.stdout and res.stderr == ""
    datasets, attrs, events = _h5(run_rec)
    m = scipy.io.loadmat(mat_path, simplify_cells=True)
    meta = m["meta"]
    assert set(datasets) <= set(m) and meta["rows"] == len(datasets["time_s"][0])
    for name, (a, unit, labels) in datasets.items():
        got = np.asarray(m[name], dtype=float).reshape(a.shape)
        assert np.array_equal(got, a, equal_nan=True), name
        assert _text(meta["units"][name]) == unit, name
        if labels:
            assert list(np.atleast_1d(meta["labels"][name])) == labels, name
    assert datasets["accel_mps2"][1] == "m/s^2"
    assert list(meta["labels"]["accel_mps2"]) == ["front_left", "front_right", "rear_left", "rear_right"]
    assert meta["attrs"]["rate_hz"] == attrs["rate_hz"] and meta["attrs"]["command"] == "rig run"
    assert [str(x) for x in np.atleast_1d(meta["events"]["text"])] == [x for _, x in events]
    assert np.allclose(np.atleast_1d(meta["events"]["time_s"]), [t for t, _ in events])


def test_csv_round_trip_with_units_and_sidecars(run_rec, tmp_path):
    out = tmp_path / (run_rec.stem + ".csv")
    res = _ok(_rig("export", run_rec, "--to", "csv", "--out", tmp_path, "--json"))
    result = json.loads(res.stdout)                                  # only JSON on stdout
    assert result["files"] == [str(out), str(out.with_suffix(".meta.json")), str(out.with_suffix(".events.csv"))]
    datasets, attrs, events = _h5(run_rec)
    with open(out, newline="") as f:
        header = next(csv.reader(f))
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    meta = json.loads(out.with_suffix(".meta.json").read_text())
    cols = meta["columns"]
    assert [c["name"] for c in cols] == header and header[0] == "time_s"
    assert table.shape == (result["rows"], len(header)) == (len(datasets["time_s"][0]), result["columns"])
    for name, (a, unit, labels) in datasets.items():
        idx = [i for i, c in enumerate(cols) if c["dataset"] == name]
        assert all(cols[i]["unit"] == unit for i in idx), name
        got = table[:, idx].reshape(a.shape) if a.ndim > 1 else table[:, idx[0]]
        assert np.allclose(got, a, rtol=1e-11, atol=0, equal_nan=True), name
        if a.ndim > 1 and labels:
            assert [cols[i]["label"] for i in idx] == labels
    assert "accel_mps2.rear_right" in header and "controller_state.front_left.v" in header
    assert meta["attrs"]["rate_hz"] == attrs["rate_hz"]
    with open(out.with_suffix(".events.csv"), newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["time_s", "text"] and [(float(t), x) for t, x in rows[1:]] == events


def test_a_chirp_exported_to_mat_is_read_by_rigs_loader(tmp_path):
    rec = tmp_path / "chirp.h5"
    _ok(_rig("chirp", "--record", rec, "--duration", 2, "--f0", 1, "--f1", 50))
    _ok(_rig("export", rec, "--to", "mat", "--out", tmp_path / "for_matlab"))
    mat = tmp_path / "for_matlab" / "chirp.mat"                      # REC's name, in the folder --out
    a, b = load_recording(rec), load_recording(mat)
    assert b.fs_hz == a.fs_hz and np.array_equal(a.position_m, b.position_m)
    assert np.array_equal(a.valve_cmd_V, b.valve_cmd_V) and np.array_equal(a.accel_mps2, b.accel_mps2)
    assert scipy.io.loadmat(mat, simplify_cells=True)["meta"]["units"]["position_m"] == "m"


def test_a_refused_recording_leaves_no_output_folder(tmp_path):
    """Found by the abuse trial: `rig export bad.h5 --to csv --out DIR` refused bad.h5 and left DIR made, empty."""
    (tmp_path / "bad.h5").write_bytes(b"\x89HDF\r\n\x1a\n truncated")
    res = _rig("export", tmp_path / "bad.h5", "--to", "csv", "--out", tmp_path / "exported")
    assert res.returncode == 2 and "bad.h5: cannot open recording" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.h5"]


def test_bad_input_is_one_line(run_rec, tmp_path):
    (tmp_path / "text.h5").write_text("not HDF5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = [1.0, 2.0]
    cases = [
        ((tmp_path / "missing.h5", "--to", "mat"), "missing.h5: no such recording"),
        ((tmp_path / "text.h5", "--to", "csv"), "text.h5: cannot open recording"),
        ((tmp_path / "other.h5", "--to", "csv"), "other.h5: no time_s dataset (expected a recording of rig run"),
        ((run_rec, "--to", "csv", "--out", tmp_path / "text.h5"), "text.h5: exists and is not a folder"),
        ((run_rec, "--to", "mat", "--gzip"), "--gzip: for --to csv only"),
        ((run_rec, "--to", "xls"), "--to: invalid choice: 'xls'"),
    ]
    for args, want in cases:
        res = _rig("export", *args)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and want in lines[0], (args, res.stderr)
        assert lines[0].startswith("rig export: error: ") and res.stdout == ""
    _ok(_rig("export", run_rec, "--to", "csv", "--out", tmp_path / "twice"))
    res = _rig("export", run_rec, "--to", "csv", "--out", tmp_path / "twice")
    assert res.returncode == 2 and "(add --overwrite to" in res.stderr
    _ok(_rig("export", run_rec, "--to", "csv", "--out", tmp_path / "twice", "--overwrite"))
    csv_rec = tmp_path / "twice" / "run.csv"         # a CSV to CSV is itself: said so, with or without --overwrite
    for extra in ((), ("--overwrite",)):
        res = _rig("export", csv_rec, "--to", "csv", *extra)
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [
            f"rig export: error: {csv_rec}: the export would write over the recording itself (it is already a .csv "
            "file)"], res.stderr

"""The plant file's signal map (rig/recordings/signalmap.py): other labs' CSV, whitespace text, MATLAB v5 / v7.3 and HDF5
files written here for real, read as they are into SI units; every bad map or file is one line naming the file
and the key; the shipped examples load."""
from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings, strategies as st

from rig.cli import main
from rig.errors import ConfigError, RecordingError
from rig.plant.file import load_subject, read_plant_file
from rig.recordings.rigformat import load_recording
from rig.recordings.signalmap import (KEYS, UNITS, SignalMap, load_mapped, load_recording_for)
from tests.paths import RECORDINGS, REPO

PLANT_FILES = sorted((REPO / "docs" / "examples").glob("*.toml"))
EXAMPLES = [p for p in PLANT_FILES if "[signals]" in p.read_text()]     # those that map a foreign file
FS = 1000.0
N = 1500


def _axis(n=N, fs=FS):
    """SI ground truth of an axis: time, force command, position, acceleration, reference."""
    t = np.arange(n) / fs
    u = 40.0 * np.sin(2 * np.pi * 2.0 * t) + 5.0 * np.sin(2 * np.pi * 11.0 * t)
    x = 0.05 * np.sin(2 * np.pi * 2.0 * t - 0.4)
    a = -(2 * np.pi * 2.0) ** 2 * x
    return t, u, x, a, 0.05 * np.sin(2 * np.pi * 2.0 * t)


def _plant(tmp_path: Path, signals: str, plant: str = "") -> Path:
    p = tmp_path / "plant.toml"
    p.write_text((f"[plant]\n{plant}\n\n" if plant else "") + "[signals]\n" + signals)
    return p


def _map(signals: str, source="p.toml") -> SignalMap:
    import tomllib
    return SignalMap.from_table(tomllib.loads(signals), source)


# ---- formats -------------------------------------------------------------------------------------------------

def test_csv_with_foreign_names_preamble_and_units(tmp_path):
    t, u, x, a, _ = _axis()
    rows = [f"{1e3 * ti:.4f};{ui / 1e3:.9g};{xi * 1e3:.9g};{ai / 9.80665:.9g};OK" for ti, ui, xi, ai in
            zip(t, u, x, a)]
    text = "Logger XY export\nchannels: 4\nZeit [ms];F_soll [kN];x_ist [mm];a [g];Status\n" + "\n".join(rows) + "\n"
    path = tmp_path / "log.csv.gz"                 # compressed, and a text column the map does not name
    path.write_bytes(gzip.compress(text.encode()))
    smap = _map('csv = { delimiter = ";", skip_rows = 2 }\ntime = { name = "Zeit [ms]", unit = "ms" }\n'
                'command = { name = "F_soll [kN]", unit = "kN" }\nposition = { name = "x_ist [mm]", unit = "mm" }\n'
                'acceleration = { name = "a [g]", unit = "g" }\n')
    rec = load_mapped(path, smap)
    assert rec.fs_hz == pytest.approx(FS, rel=1e-6) and rec.n == N
    np.testing.assert_allclose(rec.command, u, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(rec.position_m, x, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(rec.accel_mps2, a, rtol=1e-7, atol=1e-9)
    assert rec.command_unit == "N" and rec.accel_present and rec.closed_loop == "" and rec.reference_m is None
    sm = rec.meta["signal_map"]
    assert sm["format"] == "csv" and sm["command"]["unit"] == "kN" and sm["position"]["si_unit"] == "m"


def test_whitespace_dat_without_header_at_a_sample_rate(tmp_path):
    _, u, x, _, _ = _axis()
    path = tmp_path / "motor.dat"
    path.write_text("% logged by the bench\n" + "\n".join(f"  {1e3 * ui:.6f}\t {math.degrees(xi):.9g}"
                                                           for ui, xi in zip(u / 40, x)) + "\n")
    smap = _map('csv = { comment = "%" }\nsample_rate_hz = 2000.0\ncommand = { column = 0, unit = "mA" }\n'
                'position = { column = 1, unit = "deg" }\n')
    rec = load_mapped(path, smap)
    assert rec.fs_hz == pytest.approx(2000.0) and rec.t_s[0] == 0.0 and rec.n == N
    np.testing.assert_allclose(rec.command, u / 40, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rec.position_m, x, rtol=1e-8, atol=1e-12)        # radians
    assert rec.command_unit == "A" and not rec.accel_present and not rec.accel_mps2.any()
    assert rec.meta["signal_map"]["position"]["si_unit"] == "rad"



def test_a_delimiter_ending_every_line_keeps_the_first_row(tmp_path):
    """MATLAB's `save -ascii -tabs` (the DaISy files) pads each number and ends every line with a tab and CRLF:
    the empty last cell must not make the first data row a header (it was silently dropped)."""
    _, u, x, _, _ = _axis()
    path = tmp_path / "daisy.dat"
    path.write_bytes("".join(f"{ui:16.7e}\t{xi:16.7e}\t\r\n" for ui, xi in zip(u, x)).encode())
    rec = load_mapped(path, _map('sample_rate_hz = 1000.0\ncommand = { column = 0, unit = "N" }\n'
                                 'position = { column = 1, unit = "m" }\n'))
    assert rec.n == N
    assert rec.command[0] == pytest.approx(float(f"{u[0]:.7e}"), abs=1e-12)
    np.testing.assert_allclose(rec.position_m, x, rtol=1e-6, atol=1e-12)

def test_mat_v5_row_vectors_matrix_columns_and_struct_fields(tmp_path):
    t, u, x, a, r = _axis()
    path = tmp_path / "emps.mat"
    scipy.io.savemat(path, {"t": t[None, :], "vir": (u / 35.15)[None, :], "data": np.column_stack([r, t, x]),
                            "meas": {"acc": a[:, None]}})
    smap = _map('time = "t"\ncommand = { name = "vir", scale = 35.15, unit = "N" }\nposition = "data[:, 2]"\n'
                'reference = { name = "data", column = 0 }\nacceleration = "meas.acc"\n')
    rec = load_mapped(path, smap)
    np.testing.assert_allclose(rec.command, u, rtol=1e-12)
    np.testing.assert_array_equal(rec.position_m, x)
    np.testing.assert_array_equal(rec.reference_m, r)
    np.testing.assert_array_equal(rec.accel_mps2, a)
    assert "reference 'data'[:, 0]" in rec.closed_loop and rec.command_unit == "N"


def test_hdf5_nested_dataset_paths_and_window(tmp_path):
    t, u, x, _, _ = _axis()
    path = tmp_path / "cyl.h5"
    with h5py.File(path, "w") as f:
        f["run1/daq/time"] = t + 100.0                 # a logger's clock, not starting at zero
        f["run1/drive/valve_cmd"] = u / 40
        f["run1/daq/stroke"] = -x * 1e6
    smap = _map('time = "/run1/daq/time"\ncommand = "run1/drive/valve_cmd"\n'
                'position = { name = "/run1/daq/stroke", scale = -1.0, unit = "um" }\nstart_s = 100.25\n'
                'stop_s = 101.0\n')
    rec = load_mapped(path, smap)
    sel = (t + 100.0 >= 100.25) & (t + 100.0 <= 101.0)
    assert rec.n == sel.sum() and rec.t_s[0] == pytest.approx(100.25)
    np.testing.assert_allclose(rec.position_m, x[sel], rtol=1e-12, atol=1e-15)
    assert rec.command_unit == "V" and rec.meta["signal_map"]["window_s"] == [100.25, 101.0]


def test_matlab_v73_matrix_is_column_major(tmp_path):
    # MATLAB -v7.3: HDF5 behind a 512-byte header; an n x k matrix is stored as a (k, n) dataset
    t, u, x, _, _ = _axis()
    path = tmp_path / "v73.mat"
    with h5py.File(path, "w", userblock_size=512) as f:
        f["t"] = t[None, :]
        f["sig"] = np.column_stack([u, x]).T
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Sat Nov 21 2026 HDF5 schema 1.00 .")
    rec = load_mapped(path, _map('format = "mat"\ntime = "t"\ncommand = { name = "sig[:, 0]", unit = "N" }\n'
                                 'position = "sig[:, 1]"\n'))
    np.testing.assert_array_equal(rec.command, u)
    np.testing.assert_array_equal(rec.position_m, x)
    assert rec.meta["signal_map"]["format"] == "mat73"


def test_no_signals_table_is_rigs_own_format(tmp_path):
    rec_path = tmp_path / "r.csv"
    t, u, x, a, _ = _axis()
    rec_path.write_text("time_s,valve_cmd_V,position_m,accel_mps2\n" +
                        "\n".join(f"{ti:.6f},{ui / 40:.9g},{xi:.9g},{ai:.9g}" for ti, ui, xi, ai in zip(t, u, x, a)))
    plant = tmp_path / "p.toml"
    plant.write_text('[plant]\nfamily = "eha"\n')
    assert read_plant_file(plant).signals is None
    np.testing.assert_array_equal(load_subject(rec_path, plant).rec.position_m, load_recording(rec_path).position_m)
    np.testing.assert_array_equal(load_recording_for(rec_path).position_m, load_recording(rec_path).position_m)


@pytest.mark.shared
def test_identify_through_a_plant_file_matches_the_shared_recording(tmp_path, capsys):
    """A shared recording re-saved another lab's way (.mat, mV and um, own names) identifies as the original."""
    ref = load_recording(RECORDINGS / "p01_nominal.csv.gz")
    k = slice(0, 20_000)
    mat = tmp_path / "lab.mat"
    scipy.io.savemat(mat, {"zeit": ref.t_s[k], "u_mV": 1e3 * ref.valve_cmd_V[k], "x_um": 1e6 * ref.position_m[k],
                           "acc": ref.accel_mps2[k]})
    plant = _plant(tmp_path, 'time = "zeit"\ncommand = { name = "u_mV", unit = "mV" }\n'
                             'position = { name = "x_um", unit = "um" }\nacceleration = "acc"\n', 'family = "eha"')
    rec = load_subject(mat, plant).rec
    np.testing.assert_allclose(rec.position_m, ref.position_m[k], rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(rec.valve_cmd_V, ref.valve_cmd_V[k], rtol=1e-12, atol=1e-15)
    assert main(["identify", str(mat), "--plant", str(plant), "--starts", "1", "--no-refine", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)["parameters"]
    assert 0.5 < got["w_nv"] / 570.0 < 1.5 and got["K_Q"] > 0


# ---- one line per error, through the command line ----------------------------------------------------------

def _write_mat(path, **vars_):
    scipy.io.savemat(path, vars_)


def _good(path):
    t, u, x, _, r = _axis()
    _write_mat(path, t=t, vir=u / 35.15, qm=x, qg=r)


def _short(path):
    t, u, x, _, _ = _axis(n=50)
    _write_mat(path, t=t, vir=u, qm=x)


def _lengths(path):
    t, u, x, _, _ = _axis()
    _write_mat(path, t=t, vir=u, qm=x[:-7])


def _nan(path):
    t, u, x, _, _ = _axis()
    x = x.copy()
    x[321] = np.nan
    _write_mat(path, t=t, vir=u, qm=x)


def _gap(path):
    t, u, x, _, _ = _axis()
    t = t.copy()
    t[700:] += 0.0004          # the clock jumps by 40 % of a step: not rows missing (those are mended)
    _write_mat(path, t=t, vir=u, qm=x)


MAP = 'time = "t"\ncommand = "vir"\nposition = "qm"\n'
ERRORS = [  # (id, [signals] body, data writer, [plant] body, words the one line must hold)
    ("unknown key", MAP + 'comand = "x"\n', _good, "", ["[signals]", "unknown key 'comand'", "valid: time"]),
    ("unknown signal key", 'time = "t"\ncommand = { name = "vir", gain = 2 }\nposition = "qm"\n', _good, "",
     ["command", "unknown key 'gain'", "valid: name, column, scale, unit"]),
    ("missing variable", 'time = "t"\ncommand = "vir"\nposition = "qx"\n', _good, "",
     ["data.mat", "no variable 'qx'", "[signals] position", "the file has:", "qm"]),
    ("unknown unit", 'time = "t"\ncommand = "vir"\nposition = { name = "qm", unit = "furlong" }\n', _good, "",
     ["position.unit = 'furlong'", "unknown unit", "mm", "deg"]),
    ("wrong kind", 'time = "t"\ncommand = "vir"\nposition = { name = "qm", unit = "N" }\n', _good, "",
     ["position.unit = 'N'", "a unit of force, not of the position"]),
    ("angle reference on a linear axis", MAP + 'reference = { name = "qg", unit = "deg" }\n', _good, "",
     ["reference.unit = 'deg'", "angle", "position is a length"]),
    ("no time", 'command = "vir"\nposition = "qm"\n', _good, "", ["neither time nor sample_rate_hz"]),
    ("inconsistent rate", MAP + "sample_rate_hz = 500.0\n", _good, "",
     ["data.mat", "'t' ([signals] time) gives 1000 Hz", "sample_rate_hz = 500", "inconsistent"]),
    ("lengths", MAP, _lengths, "", ["data.mat", "'qm' ([signals] position) has 1493 samples", "'t'", "1500"]),
    ("NaN row", MAP, _nan, "", ["data.mat", "'qm' ([signals] position) is nan", "sample 321"]),
    ("too short", MAP, _short, "", ["data.mat", "too short: 50 samples"]),
    ("gap in time", MAP, _gap, "", ["data.mat", "'t' ([signals] time) not uniform at sample 700", "expected"]),
    ("matrix without column", 'time = "t"\ncommand = "vir"\nposition = "data"\n',
     lambda p: _write_mat(p, t=_axis()[0], vir=_axis()[1], data=np.zeros((N, 3))), "",
     ["'data' ([signals] position)", "shape (1500, 3)", "data[:, 0]"]),
    ("column out of range", 'time = "t"\ncommand = "vir"\nposition = "data[:, 3]"\n',
     lambda p: _write_mat(p, t=_axis()[0], vir=_axis()[1], data=np.zeros((N, 3))), "",
     ["no column 3 in a 1500 x 3 matrix", "0-based: 0 to 2"]),
    ("window empty", MAP + "start_s = 50.0\n", _good, "",
     ["no samples within start_s = 50 s", "the time runs 0 to 1.499 s"]),
    ("bad format", MAP + 'format = "xlsx"\n', _good, "", ["format = 'xlsx'", "csv, mat, hdf5"]),
    ("wrong format", MAP + 'format = "hdf5"\n', _good, "", ["data.mat", "not a hdf5 file", "it is a MATLAB v5 file"]),
    ("unknown family", MAP, _good, 'family = "magic"', ["[plant] family: 'magic' is not a plant family"]),
    ("eha fed a force", 'time = "t"\ncommand = { name = "vir", scale = 35.15, unit = "N" }\nposition = "qm"\n',
     _good, 'family = "eha"', ["[signals] command is in N", "valve voltage"]),
]


@pytest.mark.parametrize("command", ["identify", "diagnose"])
@pytest.mark.parametrize("signals,writer,plant,words", [e[1:] for e in ERRORS], ids=[e[0] for e in ERRORS])
def test_each_error_is_one_line(tmp_path, capsys, command, signals, writer, plant, words):
    data = tmp_path / "data.mat"
    writer(data)
    plant_file = _plant(tmp_path, signals, plant)
    extra = ["--out", str(tmp_path / "out")] if command == "diagnose" else []
    assert main([command, str(data), "--plant", str(plant_file), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for w in words:
        assert w in err[0], (w, err[0])
    assert "data.mat" in err[0] or "plant.toml" in err[0]


def test_plant_file_problems_name_the_plant_file(tmp_path):
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match="nope.toml: plant file not found"):
        read_plant_file(missing)
    latin = tmp_path / "latin.toml"                  # was: a UnicodeDecodeError traceback
    latin.write_bytes(b"# d\xe9j\xe0\n[plant]\n")
    with pytest.raises(ConfigError, match="latin.toml: the plant file is not UTF-8 text"):
        read_plant_file(latin)
    bad = tmp_path / "bad.toml"
    bad.write_text("[signals\n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        read_plant_file(bad)


def test_csv_column_problems(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("a,b\n" + "\n".join(f"{k},{k * 2}" for k in range(200)) + "\n201,oops\n")
    with pytest.raises(RecordingError, match=r"no column 'c' \(\[signals\] position of p.toml\); the file has: a, b"):
        load_mapped(path, _map('sample_rate_hz = 10.0\ncommand = "a"\nposition = "c"\n'))
    with pytest.raises(RecordingError, match=r"x.csv: line 202, column 1: 'oops' is not a number"):
        load_mapped(path, _map('sample_rate_hz = 10.0\ncommand = "a"\nposition = "b"\n'))
    with pytest.raises(RecordingError, match=r"no header row names the columns .* give its column number"):
        load_mapped(path, _map('sample_rate_hz = 10.0\ncommand = "a"\nposition = 1\ncsv = { header = false }\n'))
    semi = tmp_path / "semi.csv"                   # the plant file says ',' and the file is ';'-separated
    semi.write_text("a;b\n" + "\n".join(f"{k};{k * 2}" for k in range(200)) + "\n")
    with pytest.raises(RecordingError, match=r"semi.csv: the header is one field on ',' but 2 on ';': the file "
                                             r"looks ';'-separated; expected ','-separated "
                                             r"\(\[signals\] csv.delimiter of p.toml\)"):
        load_mapped(semi, _map('sample_rate_hz = 10.0\ncommand = "a"\nposition = "b"\ncsv = { delimiter = "," }\n'))


# ---- property tests ---------------------------------------------------------------------------------------

_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 10**6) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12) | st.sampled_from(list(UNITS) + ["t", "x[:, 1]", "data[:, 0]", ",", "whitespace"]),
    lambda inner: st.dictionaries(st.sampled_from(["name", "column", "scale", "unit", "delimiter", "skip_rows",
                                                   "header", "comment", "bogus"]), inner, max_size=4),
    max_leaves=8)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(KEYS + ("extra",)) | st.text(max_size=6), _values, max_size=9))
def test_any_signals_table_is_a_map_or_one_config_line(table):
    table = {k: v for k, v in table.items() if v is not None}          # TOML has no null
    try:
        smap = SignalMap.from_table(table, "fuzz.toml")
    except ConfigError as e:
        msg = str(e)
        assert msg.startswith("fuzz.toml: [signals]") and "\n" not in msg, msg
        return
    assert smap.command.unit in UNITS and smap.position.unit in UNITS
    assert smap.time is not None or smap.sample_rate_hz


GARBAGE_MAP = _map('time = "t"\ncommand = { name = "u", unit = "N" }\nposition = "data[:, 1]"\n')


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                   HealthCheck.too_slow])
@given(raw=st.binary(max_size=2000), prefix=st.sampled_from([b"", b"MATLAB 5.0 MAT-file", b"\x89HDF\r\n\x1a\n",
                                                             b"\x1f\x8b", b"t,u,data\n"]),
       suffix=st.sampled_from([".csv", ".mat", ".h5", ".dat"]))
def test_any_garbage_file_is_a_recording_or_one_recording_line(tmp_path, raw, prefix, suffix):
    path = tmp_path / f"junk{suffix}"
    path.write_bytes(prefix + raw)
    try:
        load_mapped(path, GARBAGE_MAP)
    except RecordingError as e:
        assert str(e).startswith(str(path)) and "\n" not in str(e), str(e)


# ---- the shipped examples ------------------------------------------------------------------------------

def _sig(smap: SignalMap, key: str):
    """The map's signal of a [signals] key (`output`, any other measured quantity, is held as its position)."""
    return getattr(smap, "position" if key == "output" else key)


def _write_for(smap: SignalMap, path: Path, truth: dict[str, np.ndarray]) -> None:
    """A data file laid out as smap describes, holding truth (SI) in the file's own names and units."""
    cols = {s.key: truth[s.key] / s.factor for s in smap.signals}
    if smap.format == "csv":
        keys = sorted(cols, key=lambda k: _sig(smap, k).column if _sig(smap, k).column is not None else 0)
        d = {None: ",", "whitespace": " "}.get(smap.csv.delimiter, smap.csv.delimiter)
        head = [] if smap.csv.header is False else [d.join(_sig(smap, k).name for k in keys)]
        rows = [d.join(f"{cols[k][i]:.12g}" for k in keys) for i in range(N)]
        path.write_text("preamble\n" * smap.csv.skip_rows + "\n".join(head + rows) + "\n")
    elif smap.format == "mat":
        scipy.io.savemat(path, {_sig(smap, k).name: a for k, a in cols.items()})
    else:
        with h5py.File(path, "w") as f:
            for k, a in cols.items():
                f[_sig(smap, k).name] = a


@pytest.mark.parametrize("example", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_shipped_example_loads_a_file_laid_out_as_it_says(tmp_path, example):
    smap = SignalMap.from_table(read_plant_file(example).signals, str(example))
    assert smap is not None and smap.format in ("csv", "mat", "hdf5")
    t, u, x, a, r = _axis()
    t = t + 0.5 if smap.start_s is None else t + smap.start_s - 0.25        # the window cuts the first 0.25 s
    truth = {"time": t, "command": u, "position": x, "acceleration": a, "reference": r}
    if smap.position.kind == "angle":
        truth["position"] = x * 20
    truth["output"] = truth["position"]                 # another quantity (a voltage, a speed): any series
    data = tmp_path / f"data.{ {'csv': 'csv', 'mat': 'mat', 'hdf5': 'h5'}[smap.format] }"
    _write_for(smap, data, truth)
    rec = load_mapped(data, smap)
    sel = slice(0, N) if smap.start_s is None else slice(250, N)
    np.testing.assert_allclose(rec.command, u[sel], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(rec.position_m, truth["position"][sel], rtol=1e-9, atol=1e-12)
    expected_fs = smap.sample_rate_hz or FS
    assert rec.fs_hz == pytest.approx(expected_fs, rel=1e-6)
    assert rec.command_unit == smap.command.si_unit
    assert rec.accel_present == (smap.acceleration is not None)
    assert (rec.reference_m is not None) == (smap.reference is not None) and bool(rec.closed_loop) == bool(
        smap.reference or smap.closed_loop)


@pytest.mark.parametrize("example", PLANT_FILES, ids=[p.stem for p in PLANT_FILES])
def test_shipped_example_plant_table_loads(example):
    from rig.plant.file import load_plant
    plant = load_plant(example)
    assert plant.family in ("eha", "mechanical_axis", "transfer_function")

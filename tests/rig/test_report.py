"""`rig report REC`: the vibration-criterion report of a run recording, per isolation mode, from what the rig
measures (mount and floor accelerometers), and its one-line errors."""
from __future__ import annotations

import dataclasses
import json

import h5py
import pytest

from controllers.vibration_criteria import CRITERIA
from rig import report
from rig.runtime.clock import SimClock
from rig.config import Config
from rig.errors import RecordingError
from rig.runtime.session import Session

RANK = {name: i for i, (name, _, _) in enumerate(CRITERIA)}


@pytest.fixture(scope="module")
def three_modes(tmp_path_factory):
    """A recording of the simulated rig: 3.5 s in each mode, switched through the session's requests."""
    path = tmp_path_factory.mktemp("report") / "run.h5"
    cfg = Config()
    cfg = cfg.replace(sensors=dataclasses.replace(cfg.sensors, floor_accel=True))
    with Session(cfg, "sim", clock=SimClock(), isolation=False, record=path) as s:
        lp = s.loop
        lp.activate()
        p = 0
        for mode in report.MODES:
            s.request_isolation_mode(mode)
            for _ in range(17500):
                lp.cycle(p * lp.period_ns)
                p += 1
    return path


def test_report_classes_by_mode(three_modes):
    rep = report.vc_of_recording(three_modes)
    assert set(rep["segments"]) == set(report.MODES) and rep["skipped_modes"] == {}
    for mode, seg in rep["segments"].items():
        assert seg["seconds"] == pytest.approx(2.5, abs=0.01)          # 3.5 s less the settling second
    c = rep["vc_class"]
    assert RANK[c["off"]] < RANK[c["feedback"]] < RANK[c["feedback_feedforward"]]
    assert len(set(rep["vc_class_floor"].values())) == 1                # the floor is the floor in every mode
    tr = {m: [x for x in v if x is not None] for m, v in rep["transmissibility_db"].items()}   # (bands the
    tr = {m: sum(v) / len(v) for m, v in tr.items()}                                          # record resolves)
    assert abs(tr["off"]) < 1.0 and tr["feedback_feedforward"] < tr["feedback"] - 10.0 < -15.0
    assert set(rep["mounts"]["feedback"]["vc_class_per_mount"]) == {"front_left", "front_right", "rear_left",
                                                                   "rear_right"}
    line = report.summary(rep)                                          # each mode paired with its class
    assert f"feedback + feedforward = {c['feedback_feedforward']}" in line and f"off = {c['off']}, " in line
    assert f"; floor: off = {rep['vc_class_floor']['off']}" in line


def test_rig_report_cli_json_and_plot(three_modes, tmp_path, capsys):
    from rig.cli import main
    assert main(["report", str(three_modes), "--json", "--out", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)                           # only JSON on stdout
    assert out["vc_class"] == json.loads((tmp_path / "report.json").read_text())["vc_class"]
    assert (tmp_path / "report.png").stat().st_size > 10000
    assert main(["report", str(three_modes), "--settle", "3.0"]) == 2    # 0.5 s left of each: too short
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no mode lasted 5 s (a VC report needs seconds of one mode" in err[0]


def test_plot_into_a_missing_folder_makes_it(three_modes, tmp_path, capsys):
    """Found by the abuse trial: `rig report REC --plot new/vc.png` ended in a FileNotFoundError traceback from
    matplotlib (so did `rig identify --plot`, after the whole identification); the folder is made, as --out's."""
    from rig.cli import main
    plot = tmp_path / "new" / "sub" / "vc.png"
    assert main(["report", str(three_modes), "--plot", str(plot)]) == 0
    assert plot.stat().st_size > 10000
    assert "Traceback" not in capsys.readouterr().err


def test_not_a_loop_recording_is_one_line(tmp_path, capsys):
    from rig.cli import main
    bad = tmp_path / "chirp.h5"
    with h5py.File(bad, "w") as f:
        f["time_s"] = [0.0, 1.0]
    assert main(["report", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"rig report: error: {bad}: no accel_mps2 dataset (expected a recording of rig run or rig hil)"]
    with pytest.raises(RecordingError, match="no such recording"):
        report.vc_of_recording(tmp_path / "missing.h5")
    with pytest.raises(RecordingError, match="is a directory, expected a recording file"):
        report.vc_of_recording(tmp_path)          # it exists: not "no such recording"
    (tmp_path / "text.h5").write_text("not HDF5")
    with pytest.raises(RecordingError, match="cannot open recording") as e:
        report.vc_of_recording(tmp_path / "text.h5")
    assert "\n" not in str(e.value)


def test_a_run_that_never_switched_isolation_off_says_so_and_plots_every_band(tmp_path):
    """`rig run --record` with its defaults (isolation on), then `rig report`: the run has no isolation-off
    stretch, said plainly (not "too short"), and the short stretch's 1 Hz band is on the plot."""
    import subprocess
    import sys
    from tests.paths import REPO
    rec, out = tmp_path / "on.h5", tmp_path / "rep"
    r = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--record", str(rec), "--sim-time", "--seconds", "3.6",
                        "--quiet"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "(no isolation-off stretch to compare with)" in r.stdout          # the run's own VC line (stdout: the result)
    r = subprocess.run([sys.executable, "-m", "rig.cli", "report", str(rec), "--out", str(out)], cwd=REPO,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "too short" not in r.stdout + r.stderr
    assert "off: no isolation-off stretch: the run never switched isolation off (only the 0.05 s INACTIVE" \
        in r.stdout and "isolation on alone, not a comparison" in r.stdout
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["segments"]) == {"feedback"} and rep["skipped_modes"] == {}
    assert "no isolation-off stretch" in rep["absent_modes"]["off"]
    v = rep["mounts"]["feedback"]["velocity_um_s_worst_mount"]
    assert rep["band_hz"][0] == 1.0 and all(x > 0 for x in v), v          # 0 would fall off the log axis


def test_a_short_record_resolves_the_1_hz_band():
    """2.5 s of white acceleration: every one-third-octave band holds spectrum (none a zero that falls off a
    log axis), and over eight records its mean square is the exact band power of the noise's density."""
    import math
    import numpy as np
    from controllers.vibration_criteria import band_velocity_rms, third_octave_bands
    fs, sigma = 5000.0, 1e-3
    _, _, lo, hi = third_octave_bands()
    exact = 2 * sigma ** 2 / fs * (1 / lo - 1 / hi) / (2 * math.pi) ** 2         # S_a / w^2 over the band
    power = []
    for seed in range(8):
        x = np.random.default_rng(seed).normal(0.0, sigma, int(2.5 * fs))
        _, v = band_velocity_rms(x, fs, kind="acceleration")
        assert np.all(v > 0), v
        power.append(v ** 2 / exact)
    mean = np.mean(power, axis=0)
    assert np.all(mean > 0.4) and np.all(mean < 2.5), mean.round(2)


def test_a_mode_too_short_is_a_warning_in_the_house_form(tmp_path, capsys):
    """Found by the abuse trial: a mode too short for a VC report was said as `rig report: feedback: too short ...`,
    not in the `rig COMMAND: warning: ...` form every other warning takes (docs/CLI.md)."""
    from rig.cli import main
    path = tmp_path / "short.h5"
    with Session(Config(), "sim", clock=SimClock(), isolation=False, record=path) as s:
        lp = s.loop
        lp.activate()
        p = 0
        for mode, periods in (("off", 17500), ("feedback", 7500)):     # 3.5 s off, then 1.5 s of feedback
            s.request_isolation_mode(mode)
            for _ in range(periods):
                lp.cycle(p * lp.period_ns)
                p += 1
    assert main(["report", str(path), "--json"]) == 0
    r = capsys.readouterr()
    assert list(json.loads(r.out)["skipped_modes"]) == ["feedback"]     # --json: stdout stays pure JSON
    assert r.err.splitlines() == [f"rig report: warning: {path}: feedback: too short for a VC report (0.5 s after "
                                  "settling, at least 2 s)"]


def test_a_run_its_writer_did_not_close_is_reported_and_exported_with_a_warning(three_modes, tmp_path):
    """Found by the abuse trial: a run whose recording was left with complete = False (the loop killed) was
    reported and exported with no word. Each command says it in one warning line naming the file and the rows it
    holds, and does its work; --json keeps stdout pure JSON."""
    import shutil
    import subprocess
    import sys
    cut = tmp_path / "cut.h5"
    shutil.copy(three_modes, cut)
    with h5py.File(cut, "r+") as f:
        f.attrs["complete"] = False
        f.attrs["ended"] = "the recording process ended without closing (crash or kill)"
        rows = f["time_s"].shape[0]
        f["time_s"][...] = [k / 5000 for k in range(rows)]
    for command, extra in (("report", []), ("export", ["--to", "csv", "--out", str(tmp_path / "exported")])):
        r = subprocess.run([sys.executable, "-m", "rig.cli", command, str(cut), "--json", *extra],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        json.loads(r.stdout)
        assert r.stderr.splitlines() == [
            f"rig {command}: warning: {cut}: the run ended before the recording was closed (attribute complete = "
            f"false; the recording process ended without closing (crash or kill)): it may be cut short; it holds "
            f"{rows} rows (t = 0 to {(rows - 1) / 5000:.6g} s), used as they are"]


def _edited(src, dst, edit):
    import shutil
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        edit(f)
    return dst


def _replace(name, value):
    def edit(f):
        new = value(f) if callable(value) else value
        del f[name]
        f[name] = new
    return edit


def _set(name, row, col, value):
    def edit(f):
        a = f[name][()]
        a[row, col] = value
        f[name][...] = a
    return edit


@pytest.mark.parametrize("edit, needle", [
    (_set("accel_mps2", 4000, 1, float("nan")), "dataset accel_mps2: not a finite number at row 4000"),
    (_set("floor_accel_mps2", 10, 0, float("inf")), "dataset floor_accel_mps2: not a finite number at row 10"),
    (lambda f: f.attrs.__setitem__("rate_hz", float("inf")), "attribute rate_hz missing or not a positive number"),
    (_replace("isolation_on", lambda f: [b"on"] * f["time_s"].shape[0]), "dataset isolation_on: expected numbers"),
])
def test_a_damaged_run_recording_is_one_line_not_a_traceback(three_modes, tmp_path, capsys, edit, needle):
    """Were tracebacks of `rig report` (ValueError, OverflowError, a numpy ufunc error) on recordings changed by
    hand; `rig diagnose` named the same problems in one line."""
    from rig.cli import main
    bad = _edited(three_modes, tmp_path / "bad.h5", edit)
    assert main(["report", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and str(bad) in err[0], err


@pytest.mark.parametrize("edit, needle", [
    (_replace("valve_cmd_V", 1.0), "dataset valve_cmd_V: a single value, expected one value per row"),
    (_replace("accel_mps2", lambda f: f["accel_mps2"][:2000]), "dataset accel_mps2 has 2000 rows, time_s 52500"),
])
def test_export_of_a_recording_changed_since_it_was_written_is_one_line(three_modes, tmp_path, capsys, edit,
                                                                         needle):
    """Were: a TypeError traceback (a dataset of one value), and an export of every column cut to the shortest one's
    rows without a word (a dataset shortened in a file its writer had closed)."""
    from rig.cli import main
    bad = _edited(three_modes, tmp_path / "bad.h5", edit)
    assert main(["export", str(bad), "--to", "csv", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_an_accelerometer_recorded_in_g_is_rated_as_in_m_per_s2(three_modes, tmp_path, capsys):
    """Was: the unit attribute ignored: the same motion written in g rated three VC classes better, and an
    unknown unit accepted."""
    def in_g(unit):
        def edit(f):
            f["accel_mps2"][...] = f["accel_mps2"][()] / 9.80665
            f["accel_mps2"].attrs["unit"] = unit
        return edit
    same = report.vc_of_recording(three_modes)["vc_class"]
    assert report.vc_of_recording(_edited(three_modes, tmp_path / "g.h5", in_g("g")))["vc_class"] == same
    with pytest.raises(RecordingError, match="dataset accel_mps2: unit 'furlong/fortnight\\^2'"):
        report.vc_of_recording(_edited(three_modes, tmp_path / "f.h5", in_g("furlong/fortnight^2")))

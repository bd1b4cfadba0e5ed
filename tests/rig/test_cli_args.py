"""The command line's bad-input cases of issue 17 (item 8 and item 4), one named test each: a bad value ends in
one line naming the option and what was expected, exit 2, before anything runs; outputs are never overwritten
without --overwrite; `rig model --plot` writes what it says."""
from __future__ import annotations

import json
import logging
import subprocess
import sys
import time

import pytest

from rig.cli import main
from tests.paths import REPO



def _one_line_error(capsys, *needles) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "error:" in err[0] and "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


@pytest.mark.parametrize("argv, option", [
    (["run", "--seconds", "nan"], "--seconds"),
    (["run", "--seconds", "inf"], "--seconds"),
    (["demo", "--seconds", "nan"], "--seconds"),
    (["bench", "loop", "--seconds", "nan"], "--seconds"),
    (["bench", "sim", "--seconds", "nan"], "--seconds"),
    (["hil", "--seconds", "nan"], "--seconds"),
])
def test_seconds_nan(capsys, argv, option):
    """Was: ValueError: cannot convert float NaN to integer (a traceback)."""
    assert main(argv) == 2
    _one_line_error(capsys, option, "'nan'" if "nan" in argv else "'inf'")


@pytest.mark.parametrize("argv", [["chirp", "--duration", "nan", "--record", "x.h5"], ["prove", "--duration", "nan"]])
def test_duration_nan(tmp_path, monkeypatch, capsys, argv):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    _one_line_error(capsys, "--duration", "'nan'")
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("argv", [["chirp", "--record", "x.h5"], ["bench", "loop"], ["bench", "sim"], ["hil"]])
@pytest.mark.parametrize("value", ["nan", "0", "-5", "1e9"])
def test_rate_nan_zero_negative_and_huge(tmp_path, monkeypatch, capsys, argv, value):
    """--rate 0 silently meant 5000 Hz in `chirp` and `bench loop`; `chirp --rate 1e9` hung; nan was a
    traceback. Now all are refused at once, naming the option and the range."""
    monkeypatch.chdir(tmp_path)
    t0 = time.monotonic()
    assert main(argv + ["--rate", value]) == 2
    assert time.monotonic() - t0 < 10                       # refused, not run
    _one_line_error(capsys, "--rate", "Hz", repr(value))


def test_chirp_negative_settle_is_refused(tmp_path, capsys):
    """Was: accepted, and the chirp was cut by the negative settle time (half the chirp recorded)."""
    out = tmp_path / "c.h5"
    assert main(["chirp", "--settle", "-1", "--duration", "1", "--record", str(out)]) == 2
    _one_line_error(capsys, "--settle", ">= 0 s")
    assert not out.exists()


def test_settle_longer_than_seconds_is_refused(capsys):
    """Was: the run stayed INACTIVE to the end and exited 0."""
    assert main(["run", "--sim-time", "--seconds", "0.5", "--settle", "2", "--quiet"]) == 2
    _one_line_error(capsys, "--seconds 0.5", "--settle 2")


@pytest.mark.hil
def test_default_warm_up_longer_than_seconds_is_refused(tmp_path):
    """`rig run --backend hil` warms the controllers up for 2 / blend_hz (5.1 s with hil.toml): a run shorter
    than that would never activate. Refused with one line; the emulated rig it started is stopped again."""
    out = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--backend", "hil", "--config",
                          str(REPO / "drivers" / "devicemaps" / "hil.toml"), "--seconds", "2", "--no-realtime",
                          "--quiet"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("rig run: error: --seconds 2: expected longer than the settle time (the default --settle: 5.07 s)")


def test_hil_rate_above_the_controllers_nyquist_is_refused(capsys):
    """`rig hil --rate 150` with hil.toml (roll-off at 223 Hz): refused before the emulated rig starts."""
    assert main(["hil", "--rate", "150", "--seconds", "1"]) == 2
    _one_line_error(capsys, "controller.", "Nyquist", "150 Hz")


def test_model_plot_name_without_suffix_writes_what_it_says(tmp_path, capsys):
    """Was: `rig model --plot DIR` wrote DIR.png and said DIR."""
    target = tmp_path / "bode"
    assert main(["model", "--plot", str(target)]) == 0
    err = capsys.readouterr().err
    assert (tmp_path / "bode.png").stat().st_size > 10000 and not target.exists()
    assert f"Bode plot written to {target}.png" in err


def test_model_plot_pdf_and_bad_suffix(tmp_path, capsys):
    assert main(["model", "--plot", str(tmp_path / "bode.pdf")]) == 0
    assert (tmp_path / "bode.pdf").read_bytes()[:4] == b"%PDF"
    capsys.readouterr()
    assert main(["model", "--plot", str(tmp_path / "bode.txt")]) == 2
    _one_line_error(capsys, "--plot", ".png, .pdf, .svg")
    assert main(["model", "--plot", str(tmp_path)]) == 2            # a folder
    _one_line_error(capsys, "--plot", "(a folder)")


# ---- outputs are never overwritten without --overwrite ------------------------------------------------------
FILE_OUTPUTS = [
    (["run", "--sim-time", "--seconds", "0.1", "--quiet", "--record"], "--record"),
    (["bench", "loop", "--seconds", "0.1", "--no-realtime", "--record"], "--record"),
    (["hil", "--seconds", "1", "--record"], "--record"),
    (["chirp", "--duration", "0.5", "--record"], "--record"),
    (["model", "--plot"], "--plot"),
]
FOLDER_OUTPUTS = [
    (["demo", "--seconds", "1", "--out"], "--out"),
    (["design", "--out"], "--out"),
    (["identify", "missing.h5", "--out"], "--out"),
    (["diagnose", "missing.h5", "--out"], "--out"),
    (["prove", "--n", "1", "--out"], "--out"),
]


@pytest.mark.parametrize("argv, option", FILE_OUTPUTS)
def test_existing_output_file_is_not_overwritten(tmp_path, monkeypatch, capsys, argv, option):
    monkeypatch.chdir(tmp_path)
    f = tmp_path / ("old.png" if option == "--plot" else "old.h5")
    f.write_bytes(b"yesterday")
    t0 = time.monotonic()
    assert main(argv + [str(f)]) == 2
    assert time.monotonic() - t0 < 10                       # before anything started
    line = _one_line_error(capsys, f"{option} {f}", "exists", "--overwrite")
    assert line.startswith(f"rig {argv[0]}: error:")
    assert f.read_bytes() == b"yesterday"
    assert sorted(p.name for p in tmp_path.iterdir()) == [f.name]


@pytest.mark.parametrize("argv, option", FOLDER_OUTPUTS)
def test_output_folder_with_files_is_not_written_into(tmp_path, monkeypatch, capsys, argv, option):
    monkeypatch.chdir(tmp_path)
    d = tmp_path / "out"
    d.mkdir()
    (d / "notes.md").write_text("mine")
    assert main(argv + [str(d)]) == 2
    _one_line_error(capsys, f"{option} {d}", "not empty", "--overwrite")
    assert [p.name for p in d.iterdir()] == ["notes.md"]


@pytest.mark.parametrize("argv, option", FILE_OUTPUTS + FOLDER_OUTPUTS +
                         [(["export", "missing.h5", "--to", "csv", "--out"], "--out")])
def test_an_output_under_a_file_is_refused_before_anything_runs(tmp_path, monkeypatch, capsys, argv, option):
    """Found by the abuse trial: `rig chirp --record notes.txt/x.h5` and `rig export ... --out notes.txt/x` ended
    in a NotADirectoryError traceback, `rig identify --out notes.txt/x` only after the whole identification."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    out = tmp_path / "notes.txt" / ("x.png" if option == "--plot" else "x.h5")
    t0 = time.monotonic()
    assert main(argv + [str(out)]) == 2
    assert time.monotonic() - t0 < 10                       # before anything started
    _one_line_error(capsys, f"{option} {out}: {tmp_path / 'notes.txt'} is a file, not a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_overwrite_replaces_a_recording_after_a_run(tmp_path, capsys):
    rec = tmp_path / "run.h5"
    rec.write_bytes(b"old")
    assert main(["run", "--sim-time", "--seconds", "0.2", "--quiet", "--record", str(rec), "--overwrite"]) == 0
    from rig.runtime.recorder import read_recording
    d = read_recording(rec)
    assert d["attrs"]["complete"] and len(d["time_s"]) >= 900
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]       # no partial file left


def test_overwrite_into_a_folder_keeps_other_files(tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    (d / "notes.md").write_text("mine")
    assert main(["demo", "--seconds", "1", "--settle", "0.2", "--out", str(d), "--overwrite"]) == 0
    assert (d / "notes.md").read_text() == "mine"
    assert json.loads((d / "demo.json").read_text())["loop"]["periods"] > 0


def test_demo_rms_option_keeps_the_spectrum(capsys):
    """Found by the campaign: `rig demo --rms-um 1` rebuilt [vibration] positionally, the seed landed in the
    spectrum field, and the floor model raised a ValueError (a traceback)."""
    assert main(["demo", "--rms-um", "1", "--seconds", "0.5", "--settle", "0.1"]) == 0
    out = capsys.readouterr().out
    floor_um = float(out.split("rig demo: floor ")[1].split(" um")[0])
    assert 0.5 < floor_um < 1.5                                  # the level asked for, not the default 3 um


@pytest.mark.parametrize("argv", [["bench", "loop", "--no-realtime", "--seconds", "4.577290772920443e-59"],
                                  ["bench", "sim", "--repeats", "1", "--seconds", "1e-9"]])
def test_benchmark_shorter_than_ten_periods_is_refused(capsys, argv):
    """Found by the campaign: a benchmark of (next to) no periods ended in a ValueError or IndexError from an
    empty array's percentiles."""
    assert main(argv) == 2
    _one_line_error(capsys, "--seconds", "at least 10 periods")


@pytest.mark.parametrize("value", ["5", "-3", "0.000005", "5xx"])
def test_a_position_without_its_unit_is_refused(capsys, value):
    """`--position 5` was 5 m (issue 29): a length needs its unit."""
    assert main(["run", "--layout", "prototype", "--sim-time", "--seconds", "1", "--position", value]) == 2
    _one_line_error(capsys, "--position: expected a length with its unit, e.g. 5um or 0.5mm", repr(value))


def test_an_integer_bound_is_said_in_full(capsys):
    """Found by the abuse trial: `--seed 4294967296` was refused with "expected ... <= 4.29497e+09", a bound the
    value looks to be inside of."""
    assert main(["identify", "missing.h5", "--seed", "4294967296"]) == 2
    _one_line_error(capsys, "--seed: expected an integer >= 0 and <= 4294967295, got '4294967296'")


def test_lengths_take_their_units_and_numbers_their_options_unit():
    from controllers.reference import parse_length, parse_reference
    from rig import cliargs
    from rig.errors import RigError
    assert [parse_length(x) for x in ("5um", "5 um", "5µm", "0.005mm", "-250nm", "0", "1e-6m")] == \
        pytest.approx([5e-6, 5e-6, 5e-6, 5e-6, -2.5e-7, 0.0, 1e-6])
    with pytest.raises(RigError, match=r"amp '10' has no unit: give one, e.g. 10um or 10mm"):
        parse_reference("sine:amp=10,freq=5", 2e-4)
    with pytest.raises(RigError, match="has no unit"):
        parse_reference("hold:5", 2e-4)
    assert cliargs.length(" 5um ") == "5um"
    hz = cliargs.Number(gt=0, unit="Hz")
    assert [hz(x) for x in ("100", "100Hz", "100 hz", " 2.5Hz ")] == [100.0, 100.0, 100.0, 2.5]
    with pytest.raises(Exception, match="expected > 0 Hz"):
        hz("100V")


def test_an_unknown_option_is_named_by_its_command_with_the_nearest_option(capsys):
    from rig.cli import main
    assert main(["chirp", "--record", "x.h5", "--secnds", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("rig chirp: error: unrecognized arguments: --secnds 1; did you mean --seconds? "
                   "(see rig chirp --help)")
    assert main(["hil", "--frobnicate"]) == 2
    assert capsys.readouterr().err.strip() == "rig hil: error: unrecognized arguments: --frobnicate (see rig hil --help)"
    assert main(["--frobnicate"]) == 2
    assert capsys.readouterr().err.strip() == "rig: error: unrecognized arguments: --frobnicate (see rig --help)"
    assert main(["drill", "--only", "nan", "-x\rb"]) == 2          # a carriage return does not split the line
    assert capsys.readouterr().err.splitlines() == ["rig drill: error: unrecognized arguments: '-x\\rb' "
                                                    "(see rig drill --help)"]


@pytest.mark.parametrize("argv", [["run", "--sim-time", "--seconds", "0.3"], ["hil", "--seconds", "2"]])
def test_inject_after_the_runs_end_is_refused(capsys, argv):
    """Was: `rig run --seconds 0.3 --inject nan:front_left:accel@5` ran, said `injected ... at t = 5.000 s` and exited
    0 (nothing was injected); `rig hil` ran the whole run without the fault and without a word."""
    assert main(argv + ["--inject", "nan:front_left:stroke@5"]) == 2
    _one_line_error(capsys, "--inject 'nan:front_left:stroke@5'", "within the run", "--seconds")


def test_an_injection_the_run_never_reached_is_not_said_to_be_injected(caplog):
    """Was: the first injection faulted the run at 0.02 s, and it said `injected nan:front_right:accel@0.2 at t =
    0.200 s` all the same."""
    caplog.set_level(logging.INFO, logger="rig")
    assert main(["run", "--sim-time", "--seconds", "0.3", "--inject", "nan:front_left:accel@0.02",
                 "--inject", "nan:front_right:accel@0.2"]) == 1
    err = caplog.text
    assert "injected nan:front_left:accel@0.02 at t = 0.020 s" in err
    assert "injected nan:front_right:accel@0.2 at" not in err
    assert "not injected nan:front_right:accel@0.2: the run stopped first (fault)" in err


def test_a_fault_says_where_it_left_the_valves(caplog):
    """Was: `stopped (fault)` and the FAULT line, never a word on the valves (rig drill said `valves null`)."""
    caplog.set_level(logging.INFO, logger="rig")
    assert main(["run", "--sim-time", "--seconds", "0.3", "--inject", "nan:front_left:accel@0.1"]) == 1
    stop = [r.getMessage() for r in caplog.records if r.getMessage().startswith("stopped (fault)")]
    assert len(stop) == 1 and stop[0].endswith("valves at null"), stop


@pytest.mark.parametrize("when", ["nan", "inf", "-1"])
def test_a_script_time_that_never_comes_is_refused(tmp_path, capsys, when):
    """Was: `nan off` (and `inf off`) in a --script ran the whole run with the word never acted on, exit 0."""
    script = tmp_path / "s.txt"
    script.write_text(f"# times\n0.1 off\n{when} on\n")
    assert main(["run", "--sim-time", "--seconds", "0.3", "--script", str(script)]) == 2
    _one_line_error(capsys, f"--script {script}: line 3", "a time >= 0")


def test_a_control_file_that_is_a_folder_is_refused(tmp_path, capsys):
    """Was: `--control /tmp` ran the whole run polling a folder: `stop` written anywhere never reached it."""
    assert main(["run", "--sim-time", "--seconds", "0.2", "--control", str(tmp_path)]) == 2
    _one_line_error(capsys, f"control file {tmp_path}", "is a folder")


def test_a_script_that_is_not_text_is_one_line(tmp_path, capsys):
    """Was: a UnicodeDecodeError traceback."""
    script = tmp_path / "s.txt"
    script.write_bytes(b"\xff\xfe\x00\x01")
    assert main(["run", "--sim-time", "--seconds", "0.3", "--script", str(script)]) == 2
    _one_line_error(capsys, str(script), "is not UTF-8 text")


@pytest.mark.parametrize("layout, word", [
    ([], "track sine:amp=10um,freq=5"), ([], "setpoint 5um"), ([], "hold"),
    (["--layout", "prototype"], "isolation on"), (["--layout", "prototype"], "feedback")])
def test_a_script_word_the_layout_does_not_take_is_refused_at_the_start(tmp_path, capsys, layout, word):
    """Was: the script's words were checked against both layouts' words: a stand's word on the machine (or the
    machine's on a stand) started the run, was refused when its time came, and the run ended 0."""
    script = tmp_path / "s.txt"
    script.write_text(f"0.1 {word}\n")
    assert main(["run", *layout, "--sim-time", "--seconds", "0.3", "--script", str(script)]) == 2
    _one_line_error(capsys, "script at 0.1 s", repr(word))


def test_a_profile_longer_than_the_limit_is_refused_before_it_is_resampled(tmp_path, capsys):
    """Was: a csv: profile spanning 1e300 s was resampled whole before its length was checked (a traceback from
    numpy; 1e12 s: a 35 PiB allocation; 20000 s: 1.6 GB before the one line)."""
    prof = tmp_path / "p.csv"
    prof.write_text("time_s,position_m\n-1,0\n1e300,1e-6\n")
    assert main(["run", "--layout", "prototype", "--sim-time", "--seconds", "0.3", "--mode", "track",
                 "--reference", f"csv:{prof}"]) == 2
    _one_line_error(capsys, str(prof), "longer than controller.track_profile_s = 60 s")


def test_hil_bench_of_fewer_than_ten_periods_is_refused(capsys):
    """Was: `rig hil --bench --seconds 0.01` started the emulated rig and gave p99s of 5 round trips, exit 0."""
    assert main(["hil", "--bench", "--seconds", "0.01", "--json"]) == 2
    err = _one_line_error(capsys, "--seconds 0.01", "at least 10 periods at 500 Hz")
    assert err.startswith("rig hil: error:")


@pytest.mark.parametrize("when", ["0.3", "5"])
def test_a_script_word_at_or_after_the_runs_end_is_refused(tmp_path, capsys, when):
    """Was: `5 on` in a --script of a 0.3 s run ran the whole run with the word never acted on, exit 0, not a word
    said. Now refused before the run starts, as an --inject T at or after --seconds is (one rule: cliargs
    check_within_run): one line naming the file, the line and the time against --seconds."""
    script = tmp_path / "s.txt"
    script.write_text(f"# times\n0.1 off\n{when} on\n")
    assert main(["run", "--sim-time", "--seconds", "0.3", "--script", str(script)]) == 2
    err = _one_line_error(capsys, f"--script {script}: line 3", "within the run (< --seconds 0.3)", f"got {when} s")
    assert err.startswith("rig run: error: ")

"""The diagnosis's reading stage (rig/diagnose/reading.py): a file read as `rig diagnose` reads it, its values
checked for plausibility once, the command's kind and the loop's evidence found before the engine; a Recording in
hand checked the same way; bad input one RecordingError naming the source."""
from __future__ import annotations

import ast

import numpy as np
import pytest

import rig.plant.file as plant_file
import rig.recordings.samples as samples_mod
from rig.diagnose.reading import read, read_files
from rig.errors import RecordingError
from rig.plant.model import Plant
from rig.recordings.recording import Recording
from rig.recordings.rigformat import save_recording_csv
from sim_backend.linear import ActuatorParams
from tests.paths import REPO, SHARED

FS = 1000.0


def _chirp(n: int = 4000, scale: float = 1.0) -> Recording:
    t = np.arange(n) / FS
    cmd = np.sin(2 * np.pi * (1.0 + 20.0 * t) * t)
    noise = np.random.default_rng(0).normal(0.0, 1e-7, n)
    pos = (1e-3 * np.convolve(cmd, np.ones(20) / 20)[:n] + noise) * scale       # causal: the valve moves it
    return Recording.from_arrays(t, cmd, pos, source="chirp.csv")


@pytest.fixture
def plausibility_checks(monkeypatch):
    """Counts the real check_plausible's calls on the reading path (the plant file's and the samples')."""
    calls = []
    real = samples_mod.check_plausible

    def counted(rec):
        calls.append(rec.source)
        return real(rec)
    monkeypatch.setattr(samples_mod, "check_plausible", counted)
    monkeypatch.setattr(plant_file, "check_plausible", counted)
    return calls


def test_a_file_is_read_and_checked_once(tmp_path, plausibility_checks):
    path = save_recording_csv(_chirp(), tmp_path / "chirp.csv")
    r = read_files(path)
    assert plausibility_checks == [str(path)]                 # load_subject's check; the samples trust it
    assert r.samples.command.kind == "sweep" and r.samples.fs == FS
    assert not r.samples.loop.closed
    assert r.against == "Table 1" and isinstance(r.fitted_plant, ActuatorParams)
    np.testing.assert_array_equal(r.samples.cmd, r.rec.valve_cmd_V)


def test_a_recording_in_hand_is_checked_as_a_file_is(plausibility_checks):
    r = read(_chirp(), ActuatorParams())
    assert plausibility_checks == ["chirp.csv"]
    assert r.samples.command.kind == "sweep" and r.fitted_plant == ActuatorParams()
    with pytest.raises(RecordingError, match=r"chirp.csv: position_m is .* not a plausible value"):
        read(_chirp(scale=1e300), ActuatorParams())
    flat = Recording.from_arrays(np.arange(500) / FS, np.ones(500), np.zeros(500), source="flat.csv")
    with pytest.raises(RecordingError, match="flat.csv: valve_cmd_V or position_m is constant"):
        read(flat, ActuatorParams())


@pytest.mark.skipif(not (SHARED / "realdata").is_dir(), reason="../shared/realdata is absent")
def test_another_labs_file_through_its_plant_file(plausibility_checks):
    plant = REPO / "docs" / "examples" / "dryer.toml"
    r = read_files(SHARED / "realdata" / "dryer_delay" / "dryer.csv", plant)
    assert len(plausibility_checks) == 1
    assert r.plant.family == "transfer_function" and r.fitted_plant is r.plant
    assert r.rec.output_unit == "V" and r.samples.fs == 12.5
    with pytest.raises(RecordingError, match="the command is in V but the plant"):
        read(r.rec, Plant("mechanical_axis", {}, "N", "axis.toml"))


def test_the_engine_reads_no_file():
    """The stages after the reading stage import no reader and no check of a recording's values."""
    readers = {"rig.plant.file", "rig.recordings.signalmap", "rig.recordings.rigformat", "rig.recordings.files",
               "rig.recordings.closedloop", "rig.recordings.samples", "rig.recordings.recording"}
    for name in ("engine", "stages"):
        tree = ast.parse((REPO / "rig" / "diagnose" / f"{name}.py").read_text())
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        imported |= {f"{n.module}.{a.name}" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
                     for a in n.names}
        assert not imported & readers, (name, imported & readers)

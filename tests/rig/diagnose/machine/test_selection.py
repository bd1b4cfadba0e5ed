"""The selection of effects on closed-loop runs of the simulated rig, recorded as `rig prove --rig` records its
cases (the session `rig run --sim-time --record` builds) and diagnosed with the model's config:

- a rocking floor under a rig that is as the model says is named, and no mode the model lacks beside it (the
  floor is the replay's input: its rocking leaves no resonance to explain);
- a valve's deadband beside a machine mode moved a few per cent names both: the deadband, far the stronger,
  must not leave the weights so raised that the moved mode passes for noise.
"""
from __future__ import annotations

import pytest

from rig.commands.prove_rig import record_case
from rig.config import config_from_dict
from rig.diagnose.machine.prove import RigCase
from rig.diagnose.machine.result import diagnose_rig
from rig.recordings.runfile import read_run

pytestmark = pytest.mark.slow

SECONDS = 15.0
PLANT_ERROR = {"K_L": 1.05, "K_Q": 1.01, "K_C": 1.05, "w_nv": 0.985, "zeta": 1.07}   # what a refit absorbs


def _diagnosed(tmp_path, name: str, mode: str, rig_error: dict, rocking: dict):
    case = RigCase(name, {}, mode, True, SECONDS, 4e-6, 12345, dict(PLANT_ERROR), rig_error, rocking)
    path = tmp_path / f"{name}.h5"
    record_case(case, path)
    diag = diagnose_rig(read_run(path), config_from_dict(case.model_sections(), source="<the model>"))
    return {(e.name, e.location): e.parameters for e in diag.effects}, diag


def test_a_rocking_floor_under_a_clean_rig_names_the_rocking_and_no_missing_mode(tmp_path):
    named, diag = _diagnosed(tmp_path, "rocking", "feedback", {},
                             {"rocking_axis": "roll", "rocking_over_floor": 1.1})
    assert ("floor_rocking", "roll") in named, diag.summary
    assert set(named) == {("floor_rocking", "roll")}, (named, diag.candidates)


def test_a_deadband_beside_a_moved_mode_names_both(tmp_path):
    f = [1.0, 1.0, 1.0, 1.0, 1.05]                        # pitch (Table 2: 68 Hz) at 71.4 Hz
    named, diag = _diagnosed(tmp_path, "deadband_mode", "feedback_feedforward",
                             {"mode_frequency_factor": f, "valve_deadband_ma": [0.0, 0.8, 0.0, 0.0]}, {})
    assert set(named) == {("valve_deadband", "front_right"), ("mode_frequency", "pitch")}, (named, diag.candidates)
    assert named[("mode_frequency", "pitch")]["frequency_hz"] == pytest.approx(68.0 * 1.05, rel=0.03)
    assert named[("valve_deadband", "front_right")]["width_ma"] == pytest.approx(0.8, rel=0.25)

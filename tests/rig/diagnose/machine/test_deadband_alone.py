"""A valve's deadband and nothing else wrong: the deadband is named, and no sensor's gain beside it.

A closed-loop run with feedforward and floor accelerometers, as `rig prove --rig` records its cases (the session
`rig run --sim-time --record` builds), diagnosed with the model's config. What the deadband's model leaves at its
own mount, an accelerometer read a few tenths of a per cent off takes up: the blind proof named such a gain
(x0.997) beside a true deadband. A sensitivity is known only to its calibration's uncertainty (1-2 %), so a gain
inside it is no fault (effects.SENSOR_GAIN.least): it is refused and the search goes on. Nothing else is named:
the replay feeds the deadband valve's chamber as the simulated rig does (its spool's samples past the overlap,
interpolated linearly; the valve's response to a held effective command left an error at that mount which its
viscous term, x4.6, took up), and a broad extra mode polished onto its damping's bound (0.1, at 5.7 Hz) is dropped
as one fitted there is refused (docs/DIAGNOSIS.md).
"""
from __future__ import annotations

import pytest

from rig.commands.prove_rig import record_case
from rig.config import config_from_dict
from rig.diagnose.machine.prove import RigCase
from rig.diagnose.machine.result import diagnose_rig
from rig.recordings.runfile import read_run

pytestmark = pytest.mark.slow

SECONDS = 12.0
WIDTH_MA = 0.3                  # the proof draws 0.2-1.0 mA


@pytest.fixture(scope="module")
def named(tmp_path_factory):
    case = RigCase("deadband", {}, "feedback_feedforward", True, SECONDS, 3.5e-6, 4242, {},
                   {"valve_deadband_ma": [0.0, 0.0, WIDTH_MA, 0.0]})
    path = tmp_path_factory.mktemp("deadband") / "run.h5"
    record_case(case, path)
    diag = diagnose_rig(read_run(path), config_from_dict(case.model_sections(), source="<the model>"))
    return {(e.name, e.location): e.parameters for e in diag.effects}, diag.candidates


def test_a_deadband_alone_names_the_deadband_and_no_sensor_gain(named):
    effects, candidates = named
    assert not [k for k in effects if k[0] == "sensor_gain"], (effects, candidates)
    assert ("valve_deadband", "rear_left") in effects, (effects, candidates)
    assert effects[("valve_deadband", "rear_left")]["width_ma"] == pytest.approx(WIDTH_MA, rel=0.25)
    refused = [c for c in candidates if c["effect"] == "sensor_gain" and "below_least" in c]
    assert refused and all(not c["named"] and not c["passed"] for c in refused), candidates


def test_a_deadband_alone_names_nothing_else(named):
    effects, candidates = named
    assert set(effects) == {("valve_deadband", "rear_left")}, (effects, candidates)

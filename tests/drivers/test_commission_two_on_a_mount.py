"""`rig commission` on the emulated rig with two wiring faults on one mount, on three mounts at once (issue 27's
combinations, a mount carrying two): each fault named on its channel with its kind, nothing else, and the
calibration it writes holds each correction."""
from __future__ import annotations

import json
import tomllib

import pytest

from tests.drivers.test_commission import _commission
from tests.drivers.test_commission_sensors import _faults, _miswired

from rig.errors import EXIT_FINDINGS

FL, FR, RL, RR = "front_left", "front_right", "rear_left", "rear_right"
KEYS = ("ai_factor = [-1.0, 1.0, 0.10197, 1.0, 1.0, 1.0, 1.0, 1.0]\n"   # front_left inverted, rear_left a g range
        "valve_null_V = [0.3, 0.0, 0.0, 0.0]\n"                            # front_left's valve centres at 0.3 V
        "dt_factor = [1.0, 1.0, 10.0, -1.0]\n"                             # rear_left a decade up, rear_right inverted
        "valve_gain = [1.0, 1.0, 1.0, 0.6]\n")                             # rear_right's valve at 0.6 x


@pytest.mark.hil
def test_two_faults_on_one_mount_are_both_named_and_corrected(tmp_path):
    run, out = _commission(tmp_path / "c", "--config", str(_miswired(tmp_path, "two", KEYS)))
    assert run.returncode == EXIT_FINDINGS, run.stderr[-3000:]
    res = json.loads(run.stdout)
    assert _faults(res) == {(f"accel:{FL}", "sign"), (f"valve:{FL}", "null"), (f"accel:{RL}", "scale"),
                            (f"stroke:{RL}", "scale"), (f"stroke:{RR}", "sign"), (f"valve:{RR}", "gain")}, \
        res["findings"]
    cal = tomllib.loads((out / "commissioning.toml").read_text())
    assert cal["accel"][FL]["sign"] == -1 and cal["accel"][RL]["scale"] == pytest.approx(9.80665)
    assert cal["stroke"][RL]["scale"] == pytest.approx(0.1) and cal["stroke"][RR]["sign"] == -1
    assert cal["valve"][FL]["null_V"] == pytest.approx(0.3, abs=0.05)
    assert cal["valve"][RR]["gain"] == pytest.approx(0.6, rel=0.15)
    assert [cal[k][m].get("sign", 1) for k in ("accel", "stroke") for m in (FR,)] == [1, 1]

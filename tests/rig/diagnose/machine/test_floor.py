"""The floor's rocking test on the floor's own motion (floor accelerometers fitted): a floor of independent
motion at the mounts beside a common heave -- the simulated floor, whose displacement falls as 1/f -- is not
called rocking, however its few lowest bins fall; a floor rocking about roll is, about roll."""
from __future__ import annotations

import numpy as np
import pytest

from rig.config import config_from_dict
from rig.diagnose.machine.engine import nominal_theta, prepare, u_of
from rig.diagnose.machine.floor import floor_motion
from rig.recordings.runfile import RunRecording
from sim_backend.rig_plant import FloorMotion

DT = 1 / 5000
SECONDS = 15.0


def _floor_only_run(vibration: dict, seed: int) -> RunRecording:
    """A run whose mounts stand still (sensor noise only) on a measured floor: what the test reads is the floor."""
    cfg = config_from_dict({"vibration": {"rms_m": 5e-6, "seed": seed, **vibration}, "sensors": {"floor_accel": True}})
    n = int(SECONDS / DT)
    a_g = FloorMotion.from_config(cfg, DT).next_block(n)[:, 8:12]
    rng = np.random.default_rng(seed)
    return RunRecording("<floor>", 1 / DT, np.arange(n) * DT, 1e-4 * rng.standard_normal((n, 4)),
                        1e-8 * rng.standard_normal((n, 4)), np.zeros((n, 4)),
                        a_g + 1e-4 * rng.standard_normal((n, 4))), cfg


def _motion(vibration: dict, seed: int):
    run, cfg = _floor_only_run(vibration, seed)
    ctx = prepare(run, cfg)
    th = nominal_theta(ctx.base)
    return floor_motion(ctx.rp, th, u_of(ctx)(th))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_floor_of_independent_motion_is_not_called_rocking(seed):
    fm = _motion({}, seed)
    assert fm.measured and not fm.rocking and fm.ratio < 1.3, (fm.axis, fm.ratio, fm.z)


def test_a_rocking_floor_is_named_about_its_axis():
    fm = _motion({"rocking_rms_m": 4e-6, "rocking_axis": "roll"}, 1)
    assert fm.rocking and fm.axis == "roll" and fm.ratio > 2.0, (fm.axis, fm.ratio, fm.z)

"""An effect is named only where it moves the replay by more than twice the model's own fidelity
(engine.over_fidelity, OVER_FIDELITY: what two faithful models of the rig differ by, residual.FIDELITY): an
accelerometer read x1.002 is a change the model cannot tell from its own error, whatever its likelihood ratio;
one read x1.01, or a valve's 0.3 ms delay, stands well above it."""
from __future__ import annotations

import pytest

from rig.diagnose.machine import effects as fx
from rig.diagnose.machine.engine import OVER_FIDELITY, nominal_theta, over_fidelity, prepare
from rig.diagnose.machine.residual import FIDELITY
from rig.diagnose.machine.rigmodel import copy_theta
from rig.recordings.runfile import read_run
from tests.rig.diagnose.machine.support import open_loop_run, rig_cfg, write_run


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    path = tmp_path_factory.mktemp("fidelity") / "run.h5"
    write_run(path, open_loop_run(rig_cfg(True), 6.0, noise=False))
    return prepare(read_run(path), rig_cfg(True))


def _instance(ctx, key: str) -> fx.Instance:
    return next(i for i in fx.instances(ctx, valves_driven=True) if i.key == key)


@pytest.mark.parametrize("key, slot, value, above", [
    ("sensor_gain[accelerometer at rear_right]", ("gain_a", 3), 1.0 + 1.5 * FIDELITY[0], False),
    ("sensor_gain[accelerometer at rear_right]", ("gain_a", 3), 1.0 + 5.0 * FIDELITY[0], True),
    ("sensor_gain[stroke transducer at front_left]", ("gain_s", 0), 1.0 - 1.5 * FIDELITY[4], False),
    ("transport_delay[front_left]", ("delay_s", 0), 3e-4, True),
])
def test_an_effect_counts_only_above_the_models_fidelity(ctx, key, slot, value, above):
    th0 = nominal_theta(ctx.base)
    th = copy_theta(th0)
    th[slot[0]][slot[1]] = value
    at = ctx.rp.evaluate(th0, ctx.sp.hold)
    ratio = over_fidelity(ctx, at, th, _instance(ctx, key))
    assert (ratio > OVER_FIDELITY) == above, ratio
    if not above:
        assert 0.5 < ratio < OVER_FIDELITY, ratio     # the gain's own change (1.5 x the fidelity), measured so

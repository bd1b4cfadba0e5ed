"""An effect is named only where it moves the replay by more than twice the model's own fidelity
(engine.over_fidelity, OVER_FIDELITY: what two faithful models of the rig differ by, residual.FIDELITY): an
accelerometer read x1.002 is a change the model cannot tell from its own error, whatever its likelihood ratio;
one read x1.01, or a valve's 0.3 ms delay, stands well above it. Under isolation that error is FIDELITY of the
reading's parts (the floor's and the valves' cancelling one), several times FIDELITY of the reading (the fidelity
test's figure: at a deadband's mount it let the viscous term pass, test_deadband_alone.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig.commands.prove_rig import record_case
from rig.config import config_from_dict
from rig.diagnose.machine import effects as fx
from rig.diagnose.machine.engine import OVER_FIDELITY, nominal_theta, over_fidelity, prepare
from rig.diagnose.machine.prove import RigCase
from rig.diagnose.machine.residual import FIDELITY
from rig.diagnose.machine.rigmodel import copy_theta, responses
from rig.diagnose.machine.spectra import BANDS_HZ
from rig.recordings.runfile import read_run
from sim_backend.rig_plant import FloorMotion, RigPlant
from tests.rig.diagnose.machine.support import DT, open_loop_run, rig_cfg, write_run


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


@pytest.fixture(scope="module")
def isolated(tmp_path_factory):
    """A closed-loop run with feedforward (the rig as the model says), recorded as `rig prove --rig` records its
    cases; and the simulated rig driven open loop by the recorded commands, once with its sensors' noise (it
    must give the recording back) and once without."""
    case = RigCase("isolated", {}, "feedback_feedforward", True, 6.0, 3.5e-6, 4242, {}, {})
    path = tmp_path_factory.mktemp("isolated") / "run.h5"
    record_case(case, path)
    run = read_run(path)
    truth = config_from_dict(case.sections(), source="<the rig>")

    def driven(noise: bool):
        kw = {} if noise else {"accel_noise_mps2": 0.0, "stroke_noise_m": 0.0, "floor_noise_mps2": 0.0}
        plant = RigPlant(truth, DT, floor=FloorMotion.from_config(truth, DT), seed=truth.vibration.seed, **kw)
        out = np.empty((run.n, 12))
        prev = [0.0] * 4
        for k in range(run.n):
            out[k] = plant.accel_mps2 + plant.stroke_m + plant.floor_accel_mps2
            plant.step(prev)
            prev = run.valve_cmd_V[k]              # written in row k, acting from row k + 1
        return out
    return run, driven(True), driven(False), config_from_dict(case.model_sections(), source="<the model>")


@pytest.mark.slow
def test_under_isolation_the_model_errs_by_its_fidelity_of_the_parts_not_of_the_reading(isolated):
    """The recorded commands give the loop's readings back exactly; without noise the replay's residual is the
    model's own error (the floor's discretisation). Under isolation an accelerometer reads the small difference
    of the floor's part and the valves' cancelling one: the error is within FIDELITY of the parts (the commands'
    response and the rest), several times FIDELITY of the reading."""
    run, noisy, quiet, model = isolated
    assert np.array_equal(noisy[:, 0:4], run.accel_mps2) and np.array_equal(noisy[:, 4:8], run.stroke_m)
    ctx = prepare(dataclasses.replace(run, accel_mps2=quiet[:, 0:4], stroke_m=quiet[:, 4:8],
                                      floor_accel_mps2=quiet[:, 8:12]), model)
    th = nominal_theta(ctx.base)
    ev = ctx.rp.evaluate(th, None)
    err = np.abs(ev.r * ev.sd) ** 2
    R = responses(ctx.base, th, ctx.sp.w, floor=False)
    commanded = np.einsum("kci,ki->kc", R.Hu, ctx.sp.U) * R.gain_out[None, :]
    of_parts = FIDELITY[None, :] ** 2 * (np.abs(commanded) ** 2 + np.abs(ctx.sp.Y - commanded) ** 2)
    of_reading = (FIDELITY[None, :] * np.abs(ctx.sp.Y)) ** 2
    parts, reading = [], []
    for lo, hi in BANDS_HZ:
        sel = (ctx.sp.f_hz >= lo) & (ctx.sp.f_hz < hi)
        if sel.sum() >= 8:
            e = err[sel, 0:4].sum(axis=0)
            parts.append(np.sqrt(e / of_parts[sel, 0:4].sum(axis=0)))
            reading.append(np.sqrt(e / of_reading[sel, 0:4].sum(axis=0)))
    assert np.max(parts) < OVER_FIDELITY, np.round(parts, 2)
    assert np.max(reading) > 2.5 * OVER_FIDELITY, np.round(reading, 2)

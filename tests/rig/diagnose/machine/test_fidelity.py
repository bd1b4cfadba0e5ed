"""The model's own error, and an effect named only where it moves the replay by more than twice it
(engine.over_fidelity, OVER_FIDELITY). The simulated rig holds the floor linearly between samples, the replay takes
it continuous (a real floor is): residual.own_error computes what that leaves per bin from the floor's part, and
without noise it is the whole of the replay's residual, in open loop and under isolation. Under isolation an
accelerometer reads the small difference of the floor's part and the valves' cancelling one, and the error is
several times a share of the reading (0.2 %, the figure the fidelity test and the weights took before: it let a
deadband's mount's viscous term pass, test_deadband_alone.py).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig.commands.prove_rig import record_case
from rig.config import config_from_dict
from rig.diagnose.machine import effects as fx
from rig.diagnose.machine.engine import OVER_FIDELITY, nominal_theta, over_fidelity, prepare, u_of
from rig.diagnose.machine.prove import RigCase
from rig.diagnose.machine.rigmodel import copy_theta
from rig.diagnose.machine.spectra import BANDS_HZ
from rig.recordings.runfile import read_run
from sim_backend.rig_plant import FloorMotion, RigPlant
from tests.rig.diagnose.machine.support import DT, open_loop_run, rig_cfg, write_run

READING_SHARE = 2e-3            # the constant share of an accelerometer's reading the fidelity test took before


def _per_band(ctx, num: np.ndarray, den: np.ndarray, mask) -> np.ndarray:
    """(bands, 8) rms of num over rms of den per channel, in each band of at least 8 of mask's bins."""
    f = ctx.sp.f_hz[mask]
    out = []
    for lo, hi in BANDS_HZ:
        sel = (f >= lo) & (f < hi)
        if sel.sum() >= 8:
            out.append(np.sqrt(np.sum(np.abs(num[sel]) ** 2, axis=0) / np.sum(np.abs(den[sel]) ** 2, axis=0)))
    return np.array(out)


def _open_loop(tmp_path_factory, noise: bool):
    path = tmp_path_factory.mktemp("fidelity") / "run.h5"
    write_run(path, open_loop_run(rig_cfg(True), 6.0, noise=noise))
    return prepare(read_run(path), rig_cfg(True))


@pytest.fixture(scope="module")
def quiet(tmp_path_factory):
    return _open_loop(tmp_path_factory, False)


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    return _open_loop(tmp_path_factory, True)


def test_without_noise_the_replays_residual_is_the_models_own_error(quiet):
    ctx = quiet
    th = nominal_theta(ctx.base)
    ev = ctx.rp.evaluate(th, None)
    ratio = _per_band(ctx, ev.r * ev.sd, ctx.rp.faithful(th, ev), ev.mask)
    assert np.all(np.abs(ratio - 1.0) < 0.02), np.round(ratio, 3)


def _instance(ctx, key: str) -> fx.Instance:
    return next(i for i in fx.instances(ctx, valves_driven=True) if i.key == key)


@pytest.mark.parametrize("key, slot, value, above", [
    ("sensor_gain[accelerometer at rear_right]", ("gain_a", 3), 1.0005, False),
    ("sensor_gain[accelerometer at rear_right]", ("gain_a", 3), 1.003, True),
    ("mount_damping[rear_left]", ("mount_C", 2), 1.5, False),
    ("transport_delay[front_left]", ("delay_s", 0), 3e-4, True),
])
def test_an_effect_counts_only_above_the_models_own_error(ctx, key, slot, value, above):
    """In open loop (the sensors' noise as configured) the floor's part is most of a reading: the two readings of
    the floor differ by 0.05-0.2 % of an accelerometer's (more at higher frequencies); a gain of 1.0005 moves it
    by less, one of 1.003 by more. A mount's viscous term (1e-4 of the hydraulic force) half as large again
    moves it by a small part of that."""
    th0 = nominal_theta(ctx.base)
    th = copy_theta(th0)
    th[slot[0]][slot[1]] = value
    at = ctx.rp.evaluate(th0, ctx.sp.hold)
    ratio = over_fidelity(ctx, at, th, _instance(ctx, key))
    assert (ratio > OVER_FIDELITY) == above, ratio


def _isolated(tmp_path_factory, rig_error: dict):
    """A closed-loop run with feedforward, recorded as `rig prove --rig` records its cases; and the simulated rig
    driven open loop by the recorded commands, once with its sensors' noise (it must give the recording back) and
    once without."""
    case = RigCase("isolated", {}, "feedback_feedforward", True, 6.0, 3.5e-6, 4242, {}, rig_error)
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


@pytest.fixture(scope="module")
def isolated(tmp_path_factory):
    """The rig as the model says."""
    return _isolated(tmp_path_factory, {})


@pytest.fixture(scope="module")
def overlapped(tmp_path_factory):
    """The rig with a 0.3 mA spool deadband at rear_left (test_deadband_alone.py's)."""
    return _isolated(tmp_path_factory, {"valve_deadband_ma": [0.0, 0.0, 0.3, 0.0]})


@pytest.mark.slow
def test_under_isolation_the_models_error_follows_the_floors_part_not_the_reading(isolated):
    """The recorded commands give the loop's readings back exactly; without noise the replay's residual is the
    model's own error per band and channel, and a share of the reading would take it for several times smaller
    than it is."""
    run, noisy, quiet, model = isolated
    assert np.array_equal(noisy[:, 0:4], run.accel_mps2) and np.array_equal(noisy[:, 4:8], run.stroke_m)
    ctx = prepare(dataclasses.replace(run, accel_mps2=quiet[:, 0:4], stroke_m=quiet[:, 4:8],
                                      floor_accel_mps2=quiet[:, 8:12]), model)
    th = nominal_theta(ctx.base)
    ev = ctx.rp.evaluate(th, None)
    own = ctx.rp.faithful(th, ev)
    ratio = _per_band(ctx, ev.r * ev.sd, own, ev.mask)
    assert np.all(np.abs(ratio - 1.0) < 0.05), np.round(ratio, 3)
    reading = _per_band(ctx, own[:, 0:4], READING_SHARE * np.abs(ctx.sp.Y[:, 0:4]), ev.mask)
    assert np.max(reading) > 2.5 * OVER_FIDELITY, np.round(reading, 2)


@pytest.mark.slow
def test_a_deadband_valves_path_adds_no_error_of_its_own(overlapped):
    """The simulated rig feeds a deadband valve's chamber from its spool's samples past the overlap, interpolated
    linearly between them; so does the replay (rigmodel.predict). At the true deadband the residual at its mount is
    then the floor's own error alone, as at the others (the valve's response to a held effective command took it
    for 0.64-0.98 of it at 5-150 Hz on a 12 s run: the two discretisations' difference, up to 0.68 of the floor's error)."""
    run, noisy, quiet, model = overlapped
    assert np.array_equal(noisy[:, 0:4], run.accel_mps2) and np.array_equal(noisy[:, 4:8], run.stroke_m)
    ctx = prepare(dataclasses.replace(run, accel_mps2=quiet[:, 0:4], stroke_m=quiet[:, 4:8],
                                      floor_accel_mps2=quiet[:, 8:12]), model)
    th = nominal_theta(ctx.base)
    th["deadband_ma"][2] = 0.3
    U = u_of(ctx)(th)
    ev = ctx.rp.evaluate(th, None, U=U)
    above = ctx.sp.f_hz[ev.mask] >= 5.0             # below, a few bins a band and the record's ends
    mask = ev.mask.copy()
    mask[ev.mask] = above
    ratio = _per_band(ctx, (ev.r * ev.sd)[above], ctx.rp.faithful(th, ev, U=U)[above], mask)
    assert np.all(np.abs(ratio - 1.0) < 0.05), np.round(ratio, 3)

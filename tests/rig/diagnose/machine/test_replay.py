"""The replay in the frequency domain is the simulated rig: the recorded commands through the model's exact held
responses reproduce the rig to rounding, the recorded floor through its continuous responses to the model's
fidelity, and the deviations' terms are the simulator's own (a deviated rig is reproduced as well as the
modelled one once theta carries them)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rig.diagnose.machine.engine import nominal_theta
from rig.diagnose.machine.residual import Replay
from rig.diagnose.machine.rigmodel import Base, copy_theta
from rig.recordings.runfile import read_run
from rig.diagnose.machine.spectra import spectra_of
from tests.rig.diagnose.machine.support import DT, open_loop_run, rig_cfg, write_run

# the replay's residual over the signal in open loop (rms over the band): accelerometers 0.2 %, strokes 1 % (a
# stroke is the small difference of the machine's and the floor's motions); what it is per bin: test_fidelity.py
FIDELITY = np.array([2e-3] * 4 + [1e-2] * 4)


def _relative_residual(tmp_path, cfg, th_changes: dict, *, floor: bool = True) -> np.ndarray:
    """Per channel: the replay's residual (all nuisance terms out) over the channel's signal, rms over the band."""
    path = tmp_path / "run.h5"
    write_run(path, open_loop_run(cfg, 6.0, noise=False), floor=floor)
    run = read_run(path)
    sp = spectra_of(run)
    base = Base.of(rig_cfg(floor), DT)
    th = copy_theta(nominal_theta(base))
    for k, (i, v) in th_changes.items():
        th[k][i] = v
    scale = np.broadcast_to(np.mean(np.abs(sp.Y) ** 2, axis=0), sp.Y.shape)      # each channel's signal
    ev = Replay(sp, base, scale).evaluate(th)
    return np.sqrt(np.mean(np.abs(ev.r) ** 2, axis=0))


def test_the_commands_replay_exactly(tmp_path):
    cfg = rig_cfg(False)
    cfg = cfg.replace(vibration=dataclasses.replace(cfg.vibration, rms_m=0.0))
    assert np.max(_relative_residual(tmp_path, cfg, {}, floor=False)) < 1e-4


def test_the_floor_replays_to_the_models_fidelity(tmp_path):
    """The simulator holds the floor linearly between samples, the model takes it continuous: in open loop they
    differ by under 0.2 % of an accelerometer's signal, 1 % of a stroke's."""
    assert np.all(_relative_residual(tmp_path, rig_cfg(True), {}) < FIDELITY)


@pytest.mark.parametrize("rig_error, theta", [
    ({"valve_delay_s": (3e-4, 0.0, 0.0, 0.0)}, {"delay_s": (0, 3e-4)}),
    ({"accel_gain": (1.0, 1.0, 1.0, 1.1)}, {"gain_a": (3, 1.1)}),
    ({"mount_stiffness_factor": (1.0, 1.0, 1.3, 1.0)}, {"mount_K": (2, 1.3)}),
    ({"mode_frequency_factor": (1.0, 1.0, 1.0, 1.05, 1.0)}, {"mode_f": (3, 1.05)}),
    ({"floor_gain": (1.0, 0.9, 1.0, 1.0)}, {"gain_g": (1, 0.9)}),
])
def test_a_deviated_rig_is_reproduced_by_the_same_terms(tmp_path, rig_error, theta):
    off = _relative_residual(tmp_path, rig_cfg(True, **rig_error), {})
    on = _relative_residual(tmp_path, rig_cfg(True, **rig_error), theta)
    assert np.max(off / FIDELITY) > 10                  # the model as configured misses it
    assert np.all(on < FIDELITY)                        # theta with the simulator's term reproduces it

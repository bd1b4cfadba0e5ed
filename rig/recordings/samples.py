"""A recording's samples as a fit takes them: the command, the position and the acceleration as float arrays
(finite, plausible, not constant), what the command is (command.py) and whether the loop was closed
(closedloop.py). Everything here is read from the recording alone; the diagnosis's reading stage
(rig/diagnose/reading.py) adds the plant.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.errors import RecordingError
from rig.recordings import closedloop, command as command_mod
from rig.recordings.recording import check_plausible


@dataclass(frozen=True)
class Samples:
    cmd: np.ndarray                     # the command, in its unit (Recording.command_unit)
    pos: np.ndarray                     # the measured output
    acc: np.ndarray                     # the accelerometer (zeros without one)
    fs: float
    loop: closedloop.LoopEvidence       # was the command computed from the measured position?
    command: command_mod.Command        # what the recorded command is


def samples_of(rec, *, plausible_checked: bool = False) -> Samples:
    """The samples of a Recording (or any object with its fields), checked: at least 100, finite, plausible
    (unless the reader checked that already: rig.plant.file.load_subject), not constant. RecordingError names
    the file and what is wrong."""
    src = getattr(rec, "source", "recording")
    cmd = np.asarray(rec.valve_cmd_V, dtype=float)
    pos = np.asarray(rec.position_m, dtype=float)
    acc = np.asarray(getattr(rec, "accel_mps2", np.zeros_like(pos)), dtype=float)
    if len(cmd) < 100 or not (np.all(np.isfinite(cmd)) and np.all(np.isfinite(pos)) and np.all(np.isfinite(acc))):
        raise RecordingError(f"{src}: diagnosis needs at least 100 finite samples of valve_cmd_V and position_m")
    if not plausible_checked:
        check_plausible(rec)
    if np.ptp(cmd) <= 0 or np.ptp(pos) <= 0:
        raise RecordingError(f"{src}: valve_cmd_V or position_m is constant; diagnosis needs an excitation "
                             "(chirp, sweep, multisine, noise or steps) and the position it caused")
    fs = float(rec.fs_hz)
    loop = closedloop.check(cmd, pos, fs, getattr(rec, "meta", None), stated=getattr(rec, "closed_loop", ""))
    return Samples(cmd=cmd, pos=pos, acc=acc, fs=fs, loop=loop,
                   command=command_mod.analyse(cmd, fs, unit=getattr(rec, "command_unit", "V")))

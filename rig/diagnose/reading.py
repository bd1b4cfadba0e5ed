"""The diagnosis's reading stage: everything read and checked before the engine fits anything.

  read_files(recording, plant, config) -> Reading   `rig diagnose`: the configuration, the plant file, the
                                                    recording through its signal map, checked together
  read(rec, plant) -> Reading                       a Recording already in hand (a notebook, the proofs)

A Reading holds the recording, its plant and its checked samples (rig.recordings.samples: the command's kind,
the evidence of a closed loop): the engine (rig.diagnose.engine) takes it as it is, and reads no file and
checks no value again.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

from rig.errors import RecordingError
from rig.plant.file import load_subject
from rig.plant.model import Plant
from rig.recordings.samples import Samples, samples_of
from sim_backend.linear import ActuatorParams


@dataclass(frozen=True)
class Reading:
    rec: object                         # rig.recordings.Recording (or any object with its fields)
    plant: ActuatorParams | Plant       # as given: a Plant of any family, or the eha actuator's ActuatorParams
    against: str                        # the plant, named for people
    samples: Samples

    @property
    def fitted_plant(self) -> ActuatorParams | Plant:
        """What the engine fits: the eha plant as its nominal ActuatorParams, any other family as its Plant."""
        p = self.plant
        return p.actuator if isinstance(p, Plant) and p.family == "eha" else p


@contextmanager
def one_blas_thread():
    """One BLAS thread for the diagnosis: its products are tall and thin (n x 30), where OpenBLAS's threads only
    wait for each other (100x slower on a loaded 2-core machine); the two cores go to the simulators instead
    (lm._POOL)."""
    from threadpoolctl import threadpool_limits   # lazy: the BLAS limit is the diagnosis's alone
    with threadpool_limits(1, user_api="blas"):
        yield


def read_files(recording, plant_path=None, config_path=None, say: Callable[[str], None] | None = None) -> Reading:
    """What `rig diagnose` reads: the plant (the plant file's, else the configuration's eha actuator) and the
    recording through the plant file's signal map, checked together and for plausibility once
    (rig.plant.file.load_subject: one line naming file and key for any problem); then its samples."""
    subject = load_subject(recording, plant_path, config_path)
    (say or _quiet)("reading the command")
    with one_blas_thread():
        samples = samples_of(subject.rec, plausible_checked=True)
    return Reading(subject.rec, subject.plant, subject.against, samples)


def read(rec, plant: ActuatorParams | Plant, say: Callable[[str], None] | None = None) -> Reading:
    """A Recording in hand against a plant (ActuatorParams of the eha actuator, or a Plant of any family),
    checked as `rig diagnose` checks a file's."""
    if isinstance(plant, Plant) and plant.input_unit != getattr(rec, "command_unit", "V"):
        raise RecordingError(f"{rec.source}: the command is in {getattr(rec, 'command_unit', 'V')} but the plant "
                             f"({plant.source}) takes input_unit = {plant.input_unit!r}; check the signal map's "
                             "command unit or the plant")
    (say or _quiet)("reading the command")
    with one_blas_thread():
        samples = samples_of(rec, plausible_checked=False)
    return Reading(rec, plant, plant.source if isinstance(plant, Plant) else "the eha actuator", samples)


def _quiet(msg: str) -> None:
    pass

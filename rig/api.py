"""The Python API for notebooks and scripts: what the CLI does, as functions with typed results.

    import rig
    rec = rig.load_recording("chirp.h5")       # a Recording (time_s, valve_cmd_V, position_m, ...)
    ident = rig.identify_actuator(rec)         # an IdentResult (.params: ActuatorParams, .std, .fit)
    diag = rig.diagnose_recording(rec)         # a Diagnosis (.effects: NamedEffect, .verdict, ...)
    iso = rig.simulate_isolation(seconds=5)    # an IsolationComparison (.reduction_db, .vc_class)

The same rules as the commands apply: identify refuses a recording made under feedback alone (as
`rig identify` does), a recording with gaps is mended and says so (`Recording.gaps`), bad input raises
RigError with one line naming the file and field, a fit `rig identify` would flag (exit 5: poor fit,
closed-loop data) warns (SuspectFit), and a Session that never went ACTIVE warns (NeverActivated).
docs/PYTHON_API.md is the worked example; a test runs it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rig.recordings.recording import Recording

__all__ = ["SuspectFit", "load_recording", "record_chirp", "identify_actuator", "diagnose_recording", "simulate_isolation", "IsolationComparison"]


class SuspectFit(UserWarning):
    """An identification `rig identify` would finish with exit status 5: the parameters are returned, and
    `.fit["warning"]` says why they are not to be trusted."""


def _subject(recording, plant, config):
    """(recording, plant): a path is read and checked as the commands read it; a Recording is taken as it is."""
    from rig.plant.file import load_subject, plant_for
    if isinstance(recording, Recording):
        return recording, plant_for(plant, config)
    s = load_subject(Path(recording), plant, config)
    return s.rec, s.plant


def load_recording(path, *, plant=None, config=None) -> Recording:
    """A recording from a file: rig's own HDF5/CSV/.mat, or another lab's file read through a plant file's
    [signals] (plant=). Checked as `rig identify` checks it; gaps mended and named in .gaps."""
    from rig.plant.file import load_subject
    return load_subject(Path(path), plant, config).rec


def record_chirp(path, *, seconds: float = 100.0, amplitude_V: float = 2.0, f0_hz: float = 0.1, f1_hz: float = 100.0,
                 config=None, seed: int | None = None, overwrite: bool = False) -> Recording:
    """A chirp on the simulated actuator on its stand in simulated time, as `rig chirp --record PATH` (the same
    defaults: 0.1-100 Hz, 2 V, 100 s); the recording written to path and returned. Nothing is kept if the run
    fails. A file already at path is refused (RigError) unless overwrite=True, as the command refuses it
    without --overwrite."""
    import argparse
    from rig import cliargs
    from rig.chirp import run_chirp
    from rig.config import load_config
    from rig.errors import RigError
    from rig.recordings.rigformat import load_recording as _load
    try:
        seconds = cliargs.seconds(le=cliargs.MAX_CHIRP_S)(seconds)          # as rig chirp --seconds
    except argparse.ArgumentTypeError as e:
        raise RigError(f"record_chirp: seconds: {e}") from None
    p = Path(path)
    if p.is_dir():
        raise RigError(f"record_chirp: {p}: is a folder, expected a file name")
    if p.exists() and not overwrite:
        raise RigError(f"record_chirp: {p}: file exists (pass overwrite=True to replace it)")
    run_chirp(load_config(config), amplitude_V=amplitude_V, f0_hz=f0_hz, f1_hz=f1_hz, duration_s=seconds,
              out=Path(path), seed=seed)
    return _load(path)


def identify_actuator(recording, *, plant=None, config=None, starts: int = 8, seed: int = 0, refine_time_domain: bool = True,
             progress=None):
    """The actuator's x_d = {K_L, C, w_nv, zeta, K_Q, K_C} from an open-loop chirp (a path or a Recording),
    as `rig identify`: an IdentResult. config: a TOML whose [actuator] is the start (default Table 1).
    Refuses (RigError) a recording made under feedback alone."""
    from rig.identify import identify as _identify, refuse_feedback_only
    rec, pl = _subject(recording, plant, config)
    if pl.family != "eha":
        from rig.errors import RigError
        raise RigError(f"{pl.describe()}: identify() fits the eha actuator; for a {pl.family} plant use diagnose_recording()")
    refuse_feedback_only(rec)
    res = _identify(rec, pl.actuator, starts=starts, seed=seed, refine_time_domain=refine_time_domain,
                    progress=progress)
    if "warning" in res.fit:
        import warnings
        warnings.warn(f"identify_actuator: {res.fit['warning']}", SuspectFit, stacklevel=2)
    return res


def diagnose_recording(recording, *, plant=None, config=None, seed: int = 0, progress=None):
    """Where the recording and the model disagree, and which physics explains it, as `rig diagnose`: a
    Diagnosis (typed, frozen; rig/diagnose/results.py). plant: a plant file (default the eha actuator of
    Table 1, or of config)."""
    from rig.diagnose.engine import diagnose_reading
    from rig.diagnose.reading import read, read_files
    from rig.plant.file import plant_for
    if isinstance(recording, Recording):
        reading = read(recording, plant_for(plant, config), progress)
    else:                                   # read and checked as `rig diagnose` reads it
        reading = read_files(Path(recording), plant, config, progress)
    return diagnose_reading(reading, progress=progress, seed=seed)


@dataclass(frozen=True)
class IsolationComparison:
    """Isolation off, feedback and feedback + floor feedforward over the same floor motion (`rig demo`)."""
    seconds: float                         # metered per mode
    floor_rms_um: float
    table_rms_um: dict                     # per mode, and per mode + "_1_100hz"
    reduction_db: dict                     # table 1-100 Hz, per isolation mode (feedback, feedback_feedforward)
    vc_class: dict                         # the table's vibration-criterion class per mode
    max_band_amplification_db: dict        # the worst one-third-octave band, per isolation mode
    figures: dict                          # everything `rig demo --json` prints


def simulate_isolation(seconds: float = 10.0, *, config=None, settle_s: float = 1.0, model_error_pct: float = 10.0,
             rms_um: float | None = None, progress=None) -> IsolationComparison:
    """The four-mount rig on the simulated plant in simulated time, isolation off / feedback / feedback +
    feedforward over the same floor (the actuators model_error_pct off the controllers' model, as
    `rig demo`). For a run of your own, use rig.runtime.session.Session (see docs/PYTHON_API.md)."""
    import argparse
    from rig.commands.demo import RANGES
    from rig.compare import compare, demo_config
    from rig.errors import RigError
    for name, value in (("seconds", seconds), ("settle_s", settle_s), ("rms_um", rms_um),
                        ("model_error_pct", model_error_pct)):
        try:
            if value is not None:
                RANGES[name](value)                             # as rig demo's option
        except argparse.ArgumentTypeError as e:
            raise RigError(f"simulate_isolation: {name}: {e}") from None
    cfg, plant = demo_config(config, rms_um=rms_um, model_error_pct=model_error_pct, log=progress)
    res, _ = compare(cfg, seconds=seconds, settle_s=settle_s, log=progress)
    res["plant"] = plant
    return IsolationComparison(seconds=float(seconds), floor_rms_um=res["floor_rms_um"],
                               table_rms_um=dict(res["table_rms_um"]),
                               reduction_db=dict(res["reduction_db"]["table_1_100hz"]),
                               vc_class=dict(res["vc_class"]),
                               max_band_amplification_db=dict(res["max_band_amplification_db"]), figures=res)

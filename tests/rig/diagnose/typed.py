"""A typed Diagnosis (rig.diagnose.results) built from a few figures, for tests of what reads one (grading)."""
from __future__ import annotations

import numpy as np

from rig.recordings.command import analyse
from rig.diagnose.results import Diagnosis, Fit, FitFigures, Mismatch, NamedEffect, Verdict
from rig.diagnose.sensor import SensorLine, SensorTerms

STATS = {"delta_bic_fit": 10.0, "lr_holdout": 1.0, "lr_needed": 0.5, "holdout_gain": 0.1, "dk": 1}


def figures(nrmse: float = 0.1, over: float = 2.0, rms_m: float = 1e-7) -> FitFigures:
    return FitFigures(nrmse, rms_m, over, nrmse, nrmse, over, over, 5, 2)


def diagnosis(effects: dict, *, fit: tuple[FitFigures, FitFigures, FitFigures] | None = None,
              params_refit: dict | None = None, lines_hz: tuple[float, ...] = ()) -> Diagnosis:
    """effects: name -> parameters; lines_hz: pickup lines the sensor terms report on the position."""
    mm = Mismatch(uncorrelated={"lines": []}, command={}, bands_hz=[], windows_s=[], after_refit={"bands_hz": []},
                  after_augmented={"bands_hz": []}, regimes={}, worst_windows={}, chirp_band_hz=[0.1, 100.0],
                  notes=())
    sensor = SensorTerms(lines=[SensorLine(f, 1e-8, 0.0, "position_m", "pickup") for f in lines_hz])
    return Diagnosis(effects=tuple(NamedEffect(n, p, 1.0, STATS) for n, p in effects.items()), groups=(),
                     mismatch=mm, fit=Fit(*(fit or (figures(), figures(), figures()))),
                     params_refit=params_refit or {}, noise_m=2e-8, verdict=Verdict("explained", 1.0, 2.0, True),
                     sensor=sensor, command=analyse(np.sin(np.arange(5000) / 30.0), 1000.0), plant={},
                     candidates=())

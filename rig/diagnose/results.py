"""What a diagnosis finds, as typed values (frozen): the stages of rig.diagnose.engine hand them on, rig.diagnose.report
turns them into prose, diagnosis.json, fit.csv and plots, and a notebook reads them as they are.

  Diagnosis    the whole result: the effects named, where the model and the recording differ, the fit figures,
               the verdict, the sensor terms, the series behind fit.csv and the data behind every plot
  NamedEffect  one effect of the catalogue (rig.diagnose.catalogue) named, with its parameters and the tests it passed
  Mismatch     where the models and the recording differ: bands, windows, regimes, distortion, lines, notes
  Fit          the figures of the three models (nominal, refit, augmented): FitFigures each
  Verdict      does the augmented model describe the recording, and what the evidence suggests if not
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from rig.recordings.command import Command
from rig.diagnose.noise import NoiseFloor
from rig.diagnose.sensor import SensorTerms

MODELS = ("nominal", "refit", "augmented")


@dataclass(frozen=True)
class NamedEffect:
    """An effect named: its parameters in SI units (the catalogue's keys, and what the report adds), its score
    (the held-out log-likelihood ratio) and the test statistics it passed (rig.diagnose.search.compare);
    line_evidence: the two-sensor test's finding for a line."""
    name: str
    parameters: dict
    score: float
    stats: dict
    line_evidence: str = ""
    interval: dict = field(default_factory=dict)    # key -> (low, high): 95 % (rig.diagnose.uncertainty)
    share: float | None = None      # of the refit's held-out residual variance it removes, the others kept
    evidence: float | None = None   # held-out log-likelihood ratio of taking it out (the effects' order)
    bias: dict = field(default_factory=dict)        # key -> the reduced model's bias, already taken off the
                                                    # parameters and the interval (rig.diagnose.reduction)


@dataclass(frozen=True)
class FitFigures:
    """One model against the recording: NRMSE (whole record on the samples used, fit blocks, held-out blocks),
    residual rms and residual over the noise (the same three), and the parameters it spent."""
    nrmse: float
    residual_rms_m: float
    residual_over_noise: float
    nrmse_fit: float
    nrmse_holdout: float
    residual_over_noise_fit: float
    residual_over_noise_holdout: float
    n_parameters: int
    n_sensor_parameters: int


@dataclass(frozen=True)
class Fit:
    nominal: FitFigures
    refit: FitFigures
    augmented: FitFigures

    def model(self, name: str) -> FitFigures:
        return {"nominal": self.nominal, "refit": self.refit, "augmented": self.augmented}[name]

    def as_dict(self) -> dict:
        return {m: asdict(self.model(m)) for m in MODELS}


@dataclass(frozen=True)
class Mismatch:
    """Where the models and the recording differ (rig.diagnose.locate measures each)."""
    uncorrelated: dict              # lines not caused by the command: forces and pickup
    command: dict                   # the command as read: kind, description, band
    bands_hz: list                  # FRF bands beyond their uncertainty, nominal model
    windows_s: list                 # time windows, nominal model
    after_refit: dict               # bands and windows after the linear refit
    after_augmented: dict           # bands after the augmented fit
    regimes: dict                   # refit residual by command level and velocity sign
    worst_windows: dict             # model -> the worst time windows
    chirp_band_hz: list
    notes: tuple[str, ...]          # what the diagnosis did with the recording (mid-run start, clipping, ...)
    regimes_augmented: dict = field(default_factory=dict)   # the augmented residual by command level, velocity
    harmonics: dict | None = None   # a sweep's harmonics
    multisine_lines: dict | None = None     # a multisine's unexcited lines
    not_claimed: tuple[NamedEffect, ...] = ()   # effects fitted but not named (the model does not describe it)

    def as_dict(self) -> dict:
        d = {"uncorrelated": self.uncorrelated, "command": self.command}
        if self.harmonics is not None:
            d["harmonics"] = self.harmonics
        if self.multisine_lines is not None:
            d["multisine_lines"] = self.multisine_lines
        d.update(bands_hz=self.bands_hz, windows_s=self.windows_s, after_refit=self.after_refit,
                 after_augmented=self.after_augmented, regimes=self.regimes,
                 regimes_augmented=self.regimes_augmented, worst_windows=self.worst_windows,
                 chirp_band_hz=self.chirp_band_hz)
        if self.not_claimed:
            d["not_claimed"] = [{"name": e.name, "parameters": e.parameters} for e in self.not_claimed]
        d["notes"] = list(self.notes)
        return d


@dataclass(frozen=True)
class Verdict:
    """status: explained | partly | incomplete | not_described | no_claim. The figures it rests on: the augmented
    and refit models' held-out residual over the noise; named: effects were named (explained by them, not by the
    refit); no_claim: why the recording allows no claim; suggestions: what the evidence suggests (one sentence
    each); rest: where the residual the model leaves lies (bands, windows, regimes), when it is above the noise;
    noise: how the noise the verdict rests on was found."""
    status: str
    holdout_over_noise: float = 0.0
    refit_over_noise: float = 0.0
    named: bool = False
    no_claim: str = ""
    suggestions: tuple[str, ...] = ()
    rest: tuple[str, ...] = ()
    noise: str = ""


@dataclass(frozen=True)
class Diagnosis:
    effects: tuple[NamedEffect, ...]
    groups: tuple[tuple[str, ...], ...]      # confounded effects (cannot be told apart on this recording)
    mismatch: Mismatch
    fit: Fit
    params_refit: dict                       # the refit linear parameters
    noise_m: float                           # the position noise estimate, rms
    verdict: Verdict
    sensor: SensorTerms
    command: Command
    plant: dict                              # family, input unit, fitted linear keys, shooting
    candidates: tuple[dict, ...]             # every candidate tried with its test statistics
    series: dict = field(default_factory=dict)   # nominal_m, refit_m, augmented_m, augmented_sensor_m
    frf: dict = field(default_factory=dict)      # freqs_hz, measured, nominal, refit, augmented, coherence, ...
    evidence: dict = field(default_factory=dict)  # plot data behind each named effect and sensor term
    used: np.ndarray | None = None               # samples the fits used (not clipped, past the start)
    noise_floor: NoiseFloor | None = None
    timing_s: float = 0.0

    def names(self) -> list[str]:
        return sorted(e.name for e in self.effects)

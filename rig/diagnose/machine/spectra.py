"""The recording in the frequency domain: one DFT of the whole record per channel, at the bins the diagnosis uses.

Whole-record DFTs of a linear system relate exactly, bin by bin, up to one term per slow mode that the states
at the record's two ends add (rigmodel.Responses.Tb, a nuisance fitted with the model). Bins: band_hz of the
record's frequency grid, every `step`-th one for the fits and the ones halfway between held out (the proof that
a named effect predicts data it was not fitted on); step keeps either set near MAX_BINS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.recordings.runfile import RunRecording

BAND_HZ = (0.3, 150.0)          # the floor's band and the actuators' (valve 83 Hz); below 0.3 Hz the blend and
                                # the centring hold the strokes, above 150 Hz the machine-on-actuator modes
MAX_BINS = 1200                 # per set (fit, held out): the models are smooth over many bins of a long record
BANDS_HZ = ((0.3, 1.0), (1.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 60.0), (60.0, 100.0),
            (100.0, 150.0))     # where the mismatch is reported (the paper's bands, the machine modes split)
CHANNELS = ("accel", "stroke")
NOISE_BAND = (0.35, 0.45)       # x the sample rate: the sensors' own noise (the rig and its valves are quiet there)


@dataclass
class Spectra:
    fs_hz: float
    n: int                      # samples in the record
    f_hz: np.ndarray            # (K,) the bins used (fit and held out together, ascending)
    Y: np.ndarray               # (K, 8) accelerometers then stroke transducers
    U: np.ndarray               # (K, 4) valve commands
    G: np.ndarray | None        # (K, 4) floor accelerometers (None: not fitted)
    fit: np.ndarray             # (K,) bool
    hold: np.ndarray            # (K,) bool
    bin_index: np.ndarray       # (K,) index into the record's rfft grid
    noise: np.ndarray           # (8,) or (12,) each channel's noise per bin (variance) in its top band, where
                                # the rig moves little: the sensors' own (accelerometers, strokes, floor)

    @property
    def w(self) -> np.ndarray:
        return 2 * math.pi * self.f_hz

    def band_of(self) -> np.ndarray:
        """Per bin: the index into BANDS_HZ (-1 outside)."""
        out = np.full(len(self.f_hz), -1)
        for b, (lo, hi) in enumerate(BANDS_HZ):
            out[(self.f_hz >= lo) & (self.f_hz < hi)] = b
        return out

    def with_command(self, U: np.ndarray) -> "Spectra":
        """The same bins with other valve commands (a deadband's effective command)."""
        return Spectra(self.fs_hz, self.n, self.f_hz, self.Y, U, self.G, self.fit, self.hold, self.bin_index,
                       self.noise)


def band_for(fs_hz: float) -> tuple[float, float]:
    lo, hi = BAND_HZ
    return lo, min(hi, 0.3 * fs_hz)


def spectra_of(run: RunRecording, *, max_bins: int = MAX_BINS) -> Spectra:
    """The DFTs of the record at the bins of BAND_HZ (see the module docstring)."""
    n = run.n
    freqs = np.fft.rfftfreq(n, 1.0 / run.fs_hz)
    lo, hi = band_for(run.fs_hz)
    idx = np.flatnonzero((freqs >= lo) & (freqs <= hi))
    step = 2 * max(1, math.ceil(len(idx) / (2 * max_bins)))
    sel = idx[(idx - idx[0]) % (step // 2) == 0] if step > 2 else idx
    fit = ((sel - idx[0]) % step) == 0
    hold = ~fit

    top = (freqs >= NOISE_BAND[0] * run.fs_hz) & (freqs <= NOISE_BAND[1] * run.fs_hz)
    outs = [run.accel_mps2, run.stroke_m] + ([run.floor_accel_mps2] if run.floor_measured else [])
    full = np.fft.rfft(np.hstack(outs), axis=0)
    noise = np.median(np.abs(full[top]) ** 2, axis=0) / math.log(2)    # median of an exponential variable
    Y = full[sel, :8]
    G = full[sel, 8:12] if run.floor_measured else None
    U = np.fft.rfft(run.valve_cmd_V, axis=0)[sel]
    return Spectra(run.fs_hz, n, freqs[sel], Y, U, G, fit, hold, sel, noise)


def command_spectrum(u: np.ndarray, sp: Spectra) -> np.ndarray:
    """The DFT of a command series (n, 4) at the bins of sp."""
    return np.fft.rfft(u, axis=0)[sp.bin_index]

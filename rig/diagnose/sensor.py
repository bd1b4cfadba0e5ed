"""Sensor terms: what the transducers add to a recording, modelled apart from the physics and never named as
effects (docs/DIAGNOSIS.md, "Sensor terms").

Position channel, as nuisance regressors of every model (nominal, refit, augmented), fitted by linear least
squares inside each evaluation (variable projection):
  offset and linear drift        the transducer's arbitrary, temperature-dependent zero
  slow wander                    cosines below a quarter of the lowest excited frequency (0.05-0.5 Hz: thermal
                                 drift that is not a straight line), as many as the data support (BIC)
  line pickup                    sinusoids at lines the position shows and the accelerometer does not
Accelerometer channel: its offset, its gain against the position's second derivative (a calibration check), and
lines it shows that the position does not (pickup on that channel).

Two sensors tell pickup from a force: a force at f moves the mass, so the accelerometer shows the line at
(2 pi f)^2 times the position's amplitude; pickup on the position transducer has no such partner.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MAINS_HZ = (50.0, 60.0)
WANDER_MAX_HZ = 0.5             # the fastest a transducer's zero wanders (temperature: minutes, not seconds)
MAINS_TOL = 0.005               # within 0.5 % of a mains harmonic: "at the mains frequency" (grids hold 0.2 %)


# ---- typed results -----------------------------------------------------------------------------------
@dataclass
class SensorLine:
    frequency_hz: float
    amplitude: float                  # m (position channel) or m/s^2 (accelerometer channel)
    phase_rad: float
    channel: str                      # position_m | accel_mps2
    source: str                       # pickup | force | pickup (assumed)
    accel_ratio: float | None = None  # accelerometer line / the line a force would give, |.|
    evidence: str = ""

    def as_dict(self) -> dict:
        d = {"frequency_hz": self.frequency_hz, "channel": self.channel, "source": self.source,
             "phase_rad": self.phase_rad, "evidence": self.evidence}
        d["amplitude_m" if self.channel == "position_m" else "amplitude_mps2"] = self.amplitude
        if self.accel_ratio is not None:
            d["accel_over_force_prediction"] = self.accel_ratio
        mains = mains_harmonic(self.frequency_hz)
        if mains:
            d["mains"] = {"base_hz": mains[0], "harmonic": mains[1]}
        return d


@dataclass
class AccelCheck:
    usable: bool
    gain: complex = 1.0               # accel / (second derivative of position) in the excited band
    coherence: float = 0.0
    note: str = ""


@dataclass
class Clip:
    channel: str
    low: float | None
    high: float | None
    samples: int
    first_s: float

    def as_dict(self) -> dict:
        return {"channel": self.channel, "low": self.low, "high": self.high, "samples": self.samples,
                "first_s": self.first_s}


@dataclass
class SensorTerms:
    offset_m: float = 0.0
    drift_m_per_s: float = 0.0
    wander_terms: int = 0
    wander_rms_m: float = 0.0
    lines: list[SensorLine] = field(default_factory=list)          # pickup on either channel
    accel_offset_mps2: float | None = None
    accel: AccelCheck | None = None
    quantisation_step_m: float = 0.0
    accel_quantisation_step_mps2: float = 0.0
    clipped: list[Clip] = field(default_factory=list)
    start_transient_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    unit: str = "m"                   # the measured output's unit (a plant file's [signals] output: any)

    def as_dict(self) -> dict:
        pos = [l for l in self.lines if l.channel == "position_m"]
        acc = [l for l in self.lines if l.channel == "accel_mps2"]
        d = {"offset_m": self.offset_m, "drift_m_per_s": self.drift_m_per_s,
             "lines": [{"frequency_hz": l.frequency_hz, "amplitude_m": l.amplitude, **l.as_dict()} for l in pos],
             "wander": {"terms": self.wander_terms, "rms_m": self.wander_rms_m},
             "accel_offset_mps2": self.accel_offset_mps2,
             "accel_lines": [l.as_dict() for l in acc],
             "quantisation_step_m": self.quantisation_step_m or None,
             "accel_quantisation_step_mps2": self.accel_quantisation_step_mps2 or None,
             "clipped": [c.as_dict() for c in self.clipped],
             "start_transient_s": self.start_transient_s,
             "notes": list(self.notes)}
        if self.unit != "m":                # the _m keys then hold the output in its own unit
            d["output_unit"] = self.unit
        if self.accel is not None:
            d["accelerometer"] = {"usable": self.accel.usable, "gain": abs(self.accel.gain),
                                  "phase_deg": math.degrees(np.angle(self.accel.gain)),
                                  "coherence": self.accel.coherence, "note": self.accel.note}
        return d


def mains_harmonic(f_hz: float) -> tuple[float, int] | None:
    """(mains frequency, harmonic number) when f is within 0.5 % of a harmonic of 50 or 60 Hz (up to the 20th)."""
    for base in MAINS_HZ:
        k = round(f_hz / base)
        if 1 <= k <= 20 and abs(f_hz - k * base) <= MAINS_TOL * k * base:
            return base, int(k)
    return None


# ---- the nuisance basis of the position channel ----------------------------------------------------
class SensorBasis:
    """Columns (n, m): 1, t, wander cosines, sin/cos of each pickup line. t scaled to [-1, 1].

    zero_terms False: no offset, drift or wander columns (a plant simulated from segment-wise initial states:
    those states hold the transducer's zero, rig.diagnose.engine)."""

    def __init__(self, n: int, fs: float, wander_terms: int = 0, lines_hz: tuple[float, ...] = (),
                 zero_terms: bool = True):
        self.n, self.fs = n, fs
        self.zero_terms = bool(zero_terms)
        self.wander_terms = int(wander_terms) if zero_terms else 0
        self.lines_hz = tuple(float(f) for f in lines_hz)
        t = np.arange(n) / fs
        cols = [np.ones(n), 2.0 * np.arange(n) / max(n - 1, 1) - 1.0] if zero_terms else []
        for k in range(2, 2 + self.wander_terms):
            cols.append(np.cos(math.pi * k * (np.arange(n) + 0.5) / n))
        for f in self.lines_hz:
            cols += [np.sin(2 * math.pi * f * t), np.cos(2 * math.pi * f * t)]
        self.B = np.column_stack(cols) if cols else np.zeros((n, 0))

    @property
    def m(self) -> int:
        return self.B.shape[1]

    @property
    def n_zero(self) -> int:
        """Columns of the zero (offset, drift, wander) before the lines."""
        return 2 + self.wander_terms if self.zero_terms else 0

    def with_(self, wander_terms: int | None = None, lines_hz=None) -> "SensorBasis":
        return SensorBasis(self.n, self.fs, self.wander_terms if wander_terms is None else wander_terms,
                           self.lines_hz if lines_hz is None else lines_hz, self.zero_terms)

    def terms(self, coef: np.ndarray) -> dict:
        """Offset (the zero at t = 0), drift, wander rms and the lines (f, amplitude, phase of sin) from the
        fitted coefficients."""
        n, fs = self.n, self.fs
        T = (n - 1) / fs if n > 1 else 1.0
        c = np.asarray(coef, float)
        drift = 2.0 * c[1] / T if self.zero_terms else 0.0     # d/dt of c1 (2 t/T - 1)
        offset = float(self.zero(c)[0]) if n else 0.0   # the zero at t = 0
        wander = self.B[:, 2:2 + self.wander_terms] @ c[2:2 + self.wander_terms] if self.wander_terms else None
        lines = []
        j = self.n_zero
        for f in self.lines_hz:
            a, b = c[j], c[j + 1]
            lines.append((f, float(math.hypot(a, b)), float(math.atan2(b, a))))
            j += 2
        return {"offset_m": float(offset), "drift_m_per_s": float(drift),
                "wander_rms_m": float(np.std(wander)) if wander is not None else 0.0, "lines": lines}

    def zero(self, coef: np.ndarray) -> np.ndarray:
        """Offset + drift + wander (without the lines)."""
        k = self.n_zero
        return self.B[:, :k] @ np.asarray(coef)[:k]


def max_wander_terms(duration_s: float, f_lo_hz: float, cap: int = 24) -> int:
    """Cosines up to a quarter of the lowest excited frequency, kept within 0.05-0.5 Hz (a transducer's zero
    moves with its temperature: minutes, not seconds), and at least four of them (a short recording still sees
    a curved zero); term k has frequency k / (2 T)."""
    f_max = min(max(0.25 * f_lo_hz, 0.05), WANDER_MAX_HZ)
    return int(max(0, min(cap, max(4, math.floor(2.0 * duration_s * f_max) - 1))))


# ---- lines and the two sensors ---------------------------------------------------------------------------
def line_amplitude(x: np.ndarray, fs: float, f_hz: float, mask: np.ndarray | None = None) -> tuple[complex, float]:
    """Complex amplitude a (x ~ Re(a e^{j w t}) = |a| cos(w t + arg a)) of a stationary line at f_hz, least
    squares on the masked samples, and its 1-sigma uncertainty from the same projection at ten neighbouring
    off-line frequencies (which holds whatever the noise colour)."""
    n = len(x)
    t = np.arange(n) / fs
    m = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    xm, tm = x[m] - np.mean(x[m]), t[m]
    T = n / fs

    def amp(f):                 # 2 x 2 normal equations of [cos, sin]
        w = 2 * math.pi * f * tm
        co, si = np.cos(w), np.sin(w)
        a11, a22, a12 = co @ co, si @ si, co @ si
        b1, b2 = co @ xm, si @ xm
        det = a11 * a22 - a12 * a12
        if det <= 0:
            return 0j
        return complex((a22 * b1 - a12 * b2) / det, -(a11 * b2 - a12 * b1) / det)

    a = amp(f_hz)
    offs = [f_hz + s * k / T for k in (3.5, 5.5, 7.5, 9.5, 11.5) for s in (-1, 1)]
    offs = [f for f in offs if 0 < f < fs / 2]
    sig = float(np.sqrt(np.mean([abs(amp(f)) ** 2 for f in offs]) / 2)) if offs else 0.0
    return a, sig


def accel_check(pos: np.ndarray, acc: np.ndarray, fs: float, band: tuple[float, float],
                mask: np.ndarray | None = None) -> AccelCheck:
    """Is the accelerometer the second derivative of the position in the excited band? Its gain (complex,
    median over coherent bins) calibrates the force prediction of a line; a gain far from 1 is reported."""
    from scipy.signal import csd, welch
    if np.ptp(acc) <= 0:
        return AccelCheck(False, note="the accelerometer channel is constant (no accelerometer recorded): "
                                       "pickup cannot be told from a force by the sensors")
    x = pos - np.mean(pos)
    a = acc - np.mean(acc)
    n = len(x)
    nper = int(min(n // 4, 2 ** int(math.log2(max(64, 2 * fs)))))
    if nper < 32:
        return AccelCheck(False, note="too short to check the accelerometer")
    f, Sxx = welch(x, fs=fs, nperseg=nper)
    _, Saa = welch(a, fs=fs, nperseg=nper)
    _, Sxa = csd(x, a, fs=fs, nperseg=nper)
    with np.errstate(divide="ignore", invalid="ignore"):
        coh = np.abs(Sxa) ** 2 / (Sxx * Saa)
        ratio = (Sxa / Sxx) / (-(2 * np.pi * f) ** 2)
    lo, hi = max(band[0], 1.0), min(band[1], 0.4 * fs)
    sel = (f >= lo) & (f <= hi) & np.isfinite(coh) & (coh > 0.8)
    if sel.sum() < 5:
        cm = float(np.nanmedian(coh[(f >= lo) & (f <= hi)])) if np.any((f >= lo) & (f <= hi)) else 0.0
        return AccelCheck(False, coherence=cm,
                          note=f"the accelerometer does not follow the position's second derivative in the excited "
                               f"band (median coherence {cm:.2f}): pickup cannot be told from a force by the sensors")
    g = complex(np.median(ratio[sel].real), np.median(ratio[sel].imag))
    spread = float(np.median(np.abs(ratio[sel] / g - 1)))
    cm = float(np.median(coh[sel]))
    note = f"accelerometer = {abs(g):.3g} x the position's second derivative (coherence {cm:.3f})"
    if abs(abs(g) - 1) > 0.1 or abs(np.angle(g)) > 0.2:
        note += ": not 1, check its calibration or units; the line tests use this gain"
    usable = spread < 0.3
    if not usable:
        note += f"; the ratio varies by {100 * spread:.0f} % over the band, so it is not used"
    return AccelCheck(usable, g, cm, note)


def classify_line(f_hz: float, x_amp: complex, x_sig: float, a_amp: complex, a_sig: float,
                  check: AccelCheck) -> tuple[str, float | None, str]:
    """(source, |accel / force prediction|, evidence) of a line seen in the position residual.

    force: the accelerometer shows it at (2 pi f)^2 times the position amplitude (ratio near 1);
    pickup: the position shows it, the accelerometer does not (ratio near 0) where it could have;
    without a usable accelerometer, or where a force's line would be below the accelerometer's noise, a line at a
    mains harmonic is taken as pickup and any other line as a possible force."""
    w2 = (2 * math.pi * f_hz) ** 2
    pred = -w2 * check.gain * x_amp if check.usable else 0.0
    mains = mains_harmonic(f_hz)
    if check.usable and abs(pred) > 5 * max(a_sig, 1e-300):
        ratio = abs(a_amp) / abs(pred)
        txt = (f"position {abs(x_amp):.3g} m; a force would show {abs(pred):.3g} m/s^2 on the accelerometer, "
               f"it shows {abs(a_amp):.3g} m/s^2 (noise {a_sig:.2g})")
        if ratio < 0.5:
            return "pickup", ratio, f"line in position but not in acceleration: {txt}"
        return "force", ratio, f"line in both sensors, consistent with a force: {txt}"
    why = (check.note if not check.usable else
           f"a force's line ({abs(pred):.2g} m/s^2) would be below the accelerometer's noise ({a_sig:.2g})")
    if mains:
        return ("pickup (assumed)", None,
                f"line at the {mains[0]:g} Hz mains frequency (harmonic {mains[1]}) taken as pickup; {why}")
    return "force", None, f"line not at a mains frequency, taken as a possible force; {why}"


# ---- clipping --------------------------------------------------------------------------------------------
def flat_tops(x: np.ndarray, min_run: int = 3) -> tuple[np.ndarray, float | None, float | None]:
    """Samples sitting at the channel's extreme values in runs of at least min_run (flat tops at a converter's
    range). Returns (mask, low level or None, high level or None); confirm against a model before calling it
    a clip (a quantised slow peak also dwells at its maximum)."""
    x = np.asarray(x, float)
    mask = np.zeros(len(x), bool)
    levels = []
    for lvl, side in ((np.max(x), 1), (np.min(x), -1)):
        tol = 1e-9 * max(abs(lvl), 1e-30)
        at = (x >= lvl - tol) if side > 0 else (x <= lvl + tol)
        if at.sum() < min_run:
            levels.append(None)
            continue
        d = np.diff(np.r_[0, at.astype(int), 0])
        st, en = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
        runs = (en - st) >= min_run
        if not runs.any():
            levels.append(None)
            continue
        for a, b in zip(st[runs], en[runs]):
            mask[a:b] = True
        levels.append(float(lvl))
    return mask, levels[1], levels[0]

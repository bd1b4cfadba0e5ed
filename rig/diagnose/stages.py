"""The stages of a diagnosis before and after the search (rig.diagnose.engine runs them in order), each a function
from one typed value to the next:

  (read)         files -> Reading           rig.diagnose.reading: read and checked, the command's kind, the loop
  prepare        Reading -> Prepared        the samples every fit leaves out, the Problem
  refit          Prepared -> Refitted       nominal model, linear refit, sensor terms, lines sorted by two sensors
  screen         Refitted -> Screened       distortion the command's structure shows; excited enough for a claim?
  (search)       Screened -> Selection      rig.diagnose.search
  settle         Selection -> Settled       pickup the distortion hid, the augmented model's noise floor
  locate         Settled -> Located         where each model and the recording differ, the fit figures
  (conclude)     Located -> Diagnosis       rig.diagnose.conclude
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from rig.recordings import command as command_mod
from rig.diagnose import locate, noise as noise_mod, sensor as sensor_mod
from rig.diagnose.lines import choose_wander, residual_lines
from rig.diagnose.plants import model_for
from rig.diagnose.problem import N_BLOCKS, ModelFit, Problem
from rig.diagnose.reading import Reading
from rig.diagnose.results import Fit, FitFigures
from rig.diagnose.search import Selection
from rig.diagnose.verdict import no_claim_reason
from rig.errors import RecordingError

HARMONIC_SCREEN = 4.0              # nonlinear distortion / noise that makes nonlinear candidates worth fitting
MIN_SNR = 3.0                      # motion rms / noise below which the recording is too poorly excited
START_TRANSIENT_S = 1.0            # left out when the recording starts mid-run (the plant forgets in ~0.1 s, a
                                   # lightly damped stand mode in ~1 s)


@dataclass(frozen=True)
class Prepared:
    rec: object
    cmd: np.ndarray
    pos: np.ndarray
    acc: np.ndarray
    fs: float
    cmd_info: command_mod.Command
    notes: tuple[str, ...]
    use: np.ndarray                     # samples every fit uses
    clip: tuple                         # position flat tops: (candidate mask, low level, high level)
    transient_s: float
    band: tuple[float, float]           # the band the command excites
    no_claim: str
    pb: Problem
    rough: noise_mod.Roughness          # what the output's own roughness allows the noise to be


@dataclass(frozen=True)
class Refitted:
    prep: Prepared
    pb: Problem                         # the noise and the sensor basis found
    nom: ModelFit
    refit: ModelFit
    check: sensor_mod.AccelCheck
    acc_clip: np.ndarray
    acc_use: np.ndarray
    acc_model: np.ndarray | None
    pickup: tuple                       # SensorLine on the position
    acc_pickup: tuple                   # SensorLine on the accelerometer
    lines: tuple                        # force lines (dicts, strongest first): the projected line's candidates
    q: float                            # the position's converter step
    q_acc: float
    floor_ref: noise_mod.NoiseFloor
    y_nom: np.ndarray                   # the nominal and refit models as the measurement (sensor terms in)
    y_ref: np.ndarray


@dataclass(frozen=True)
class Screened:
    fitted: Refitted
    distortion: tuple                   # (mismatch key, measurement) of the distortion the command shows, or Nones
    nonlinear_hint: bool | None
    no_claim: str


@dataclass(frozen=True)
class Settled:
    screened: Screened
    sel: Selection
    pb: Problem
    nom: ModelFit
    refit: ModelFit
    pickup: tuple
    y_nom: np.ndarray
    y_ref: np.ndarray
    y_aug: np.ndarray
    r_ref: np.ndarray
    floor_aug: noise_mod.NoiseFloor


@dataclass(frozen=True)
class Located:
    settled: Settled
    frf: dict
    mismatch: dict                      # the parts of Mismatch located here
    fit: Fit


def floor(pb: Problem, r: np.ndarray, cmd_info: command_mod.Command) -> noise_mod.NoiseFloor:
    """The noise floor of a residual, the response taken out as the command's kind allows (rig.diagnose.noise)."""
    if cmd_info.kind == "multisine":
        return noise_mod.floor(r, pb.fs, pb.use, period=cmd_info.period)
    if cmd_info.kind in ("noise", "steps") and not _feedback(pb):
        return noise_mod.floor(r * pb.use, pb.fs, pb.use, cmd=pb.cmd)
    return noise_mod.floor(r, pb.fs, pb.use)


def capped_noise(pb: Problem, rough: noise_mod.Roughness, q: float) -> float:
    """A plant file's plant: the noise never above what the measured output's own roughness allows (a residual
    floor that model error fills everywhere -- a closed loop's moves, a plant far from its model -- had put an
    encoder resolving micrometres at 0.25 mm), nor below the converter step's q/sqrt(12). The eha plant keeps the
    estimator its proofs measured (docs/DIAGNOSIS.md)."""
    if pb.plant.family == "eha" or not math.isfinite(rough.rms):
        return pb.noise
    return max(min(pb.noise, rough.rms), q / math.sqrt(12.0) if q else 0.0) or pb.noise


def noise_how(T: "Settled") -> str:
    """How the noise the verdict rests on was found, in words."""
    P, R = T.screened.fitted.prep, T.screened.fitted
    pb, kind = T.pb, P.cmd_info.kind
    if kind == "multisine":
        how = "the residual minus its mean period (what repeats is the response)"
    elif kind in ("noise", "steps") and not _feedback(pb):
        how = "the part of the residual not coherent with the command"
    else:
        how = "the time median of the residual's short-time spectra" + (
            " (closed loop: the part coherent with the command is the noise fed back)" if _feedback(pb) else "")
    q_floor = R.q / math.sqrt(12.0) if R.q else 0.0
    if pb.plant.family != "eha" and P.rough.rms <= pb.noise * (1 + 1e-9) and P.rough.rms > q_floor:
        return (f"from the measured output's own roughness (its differences of order {P.rough.order}, which white "
                f"noise of {P.rough.rms:.3g} would give; a smooth response adds to them): the residual's floor, "
                f"{how}, is {T.floor_aug.rms_m:.3g} and holds model error, which the recording contradicts")
    if q_floor and abs(pb.noise - q_floor) <= 1e-9 * q_floor:
        return f"from the converter's step {R.q:.3g}: its floor q/sqrt(12) = {q_floor:.3g} rms"
    return f"from {how}"


def _feedback(pb: Problem) -> bool:
    """The command was computed from the measured position (a plant file's axis under its controller): its
    part coherent with the residual is then the position's noise fed back, not the plant's response, so the noise
    floor is not estimated by removing it. (The eha plant keeps its estimator: its closed-loop recordings get no
    open-loop claim.)"""
    return pb.plant.family != "eha" and pb.loop is not None and pb.loop.closed


def _excited_band(cmd_info: command_mod.Command, fs: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """The band the command excites, and where a stand mode is looked for: a sweep's or multisine's band; for a
    broadband command (noise, steps) wherever its spectrum is within 60 dB of its peak."""
    band = cmd_info.band_hz if cmd_info.band_hz[1] > 0 else (1.0, 0.45 * fs)
    b_hi = band[1] if cmd_info.kind in ("sweep", "multisine") else max(band[1], cmd_info.wide_band_hz[1])
    base_band = (max(5.0, 1.1 * band[0]), max(min(0.97 * b_hi, 0.45 * fs), 6.0))
    if base_band[1] <= base_band[0]:
        base_band = (5.0, max(6.0, 0.45 * fs))
    return band, base_band


def prepare(r: Reading) -> Prepared:
    """The samples every fit leaves out (clipped, the start transient) and the fitting problem, from what the
    reading stage read and checked (rig.diagnose.reading)."""
    rec, p0, s = r.rec, r.fitted_plant, r.samples
    cmd, pos, acc, fs, cmd_info = s.cmd, s.pos, s.acc, s.fs, s.command
    notes: list[str] = []
    notes.append(f"command: {cmd_info.describe()}")
    plant = model_for(p0)
    if fs < 500.0 and plant.family == "eha":
        notes.append(f"sampled at {fs:g} Hz, below the 500 Hz the valve's dynamics (~{p0.w_nv / 2 / math.pi:.0f} Hz)"
                     " need to be seen")
    if plant.segmented:
        notes.append("the plant has a pole at the origin (it integrates: marginally stable), so simulated open loop "
                     "from the recorded command its position drifts; it is simulated segment-wise instead, each "
                     "segment from its own initial state (multiple shooting)")
    use = np.ones(len(cmd), bool)
    clip_cand, clip_lo, clip_hi = sensor_mod.flat_tops(pos)
    if clip_cand.any():
        use &= ~np.convolve(clip_cand, np.ones(3), "same").astype(bool)
    transient_s = 0.05                          # start-up instants carry no information
    if cmd_info.starts_mid_run and not plant.segmented:     # segments start from their own estimated states
        transient_s = START_TRANSIENT_S
        notes.append(f"the command is {cmd_info.start_V:.3g} {getattr(rec, 'command_unit', 'V')} at the first sample, so the plant was not at rest "
                     f"when the recording began (a mid-run start): the first {transient_s:g} s are left out of the "
                     f"fit (the start transient)")
    use[: int(transient_s * fs)] = False
    if use.sum() < 50:
        raise RecordingError(f"{rec.source}: fewer than 50 usable samples after the start transient and the "
                             "clipped samples")
    band, base_band = _excited_band(cmd_info, fs)
    pb = Problem(cmd, pos, fs, p0, use, base_band=base_band, broadband=cmd_info.kind in ("noise", "steps"),
                 loop=s.loop)
    return Prepared(rec=rec, cmd=cmd, pos=pos, acc=acc, fs=fs, cmd_info=cmd_info, notes=tuple(notes), use=use,
                    clip=(clip_cand, clip_lo, clip_hi), transient_s=transient_s, band=band,
                    no_claim=no_claim_reason(rec, cmd_info), pb=pb, rough=noise_mod.roughness(pos, use))


def refit(P: Prepared, say: Callable[[str], None]) -> Refitted:
    """Nominal model, refit of the linear parameters, and the sensor terms found on the way: slow wander, the
    accelerometer's check, pickup told from force lines by the two sensors, the converter step."""
    pb, cmd_info, fs, band = P.pb, P.cmd_info, P.fs, P.band
    nominal_lin = dict(pb.nominal)
    say("nominal model")
    nom = pb.evaluate(nominal_lin, {}, k=0)
    pb = pb.with_(noise=floor(pb, pb.y - pb.series(nom), cmd_info).rms_m or 1e-12)
    say("refit of the linear parameters")
    fit_ = pb.fit(nominal_lin, {}, max_iter=10)
    say("sensor terms")
    # a noise or steps command excites from DC on: no band edge to keep the wander below; the BIC decides
    f_lo = 4.0 * sensor_mod.WANDER_MAX_HZ if pb.broadband else max(band[0], 1.0 / max(P.rec.duration_s, 1e-3))
    wander_max = min(sensor_mod.max_wander_terms(P.rec.duration_s, f_lo),
                     N_BLOCKS // 4)     # a cosine spans at least four blocks: it interpolates over a held-out one
    if pb.shoot is not None:
        wander_max = 0                  # the segments' initial states hold the zero
    k_w = choose_wander(pb, fit_, wander_max)
    if k_w:
        pb = pb.with_(basis=pb.basis.with_(wander_terms=k_w))
        fit_ = pb.evaluate(fit_.lin, {}, fit_.k)       # polished once, below, with the lines
    r_ref0 = pb.y - pb.series(fit_)
    pb = pb.with_(noise=floor(pb, r_ref0, cmd_info).rms_m or pb.noise)
    acc_clip = sensor_mod.flat_tops(P.acc)[0] if np.ptp(P.acc) > 0 else np.zeros(pb.n, bool)
    acc_use = P.use & ~acc_clip
    check = sensor_mod.accel_check(pb.y - pb.basis.zero(fit_.coef), P.acc, fs,
                                   (band[0], max(band[1], cmd_info.wide_band_hz[1])), acc_use)
    acc_model = pb.plant.accel(fit_.lin, P.cmd, fs) if check.usable else None
    pickup, force_lines, acc_pickup = residual_lines(pb, r_ref0, P.acc, acc_model, check, fs, cmd_info, acc_use)
    if pickup:
        pb = pb.with_(basis=pb.basis.with_(lines_hz=tuple(l.frequency_hz for l in pickup)))
    if pickup or k_w:
        fit_ = pb.fit(fit_.lin, {}, max_iter=4)
    nom = pb.evaluate(nominal_lin, {}, k=0)
    y_nom, y_ref = pb.series(nom), pb.series(fit_)
    floor_ref = floor(pb, pb.y - y_ref, cmd_info)
    pb = pb.with_(noise=floor_ref.rms_m or pb.noise)
    q = noise_mod.quantisation_step(P.pos)
    q_acc = noise_mod.quantisation_step(P.acc) if np.ptp(P.acc) > 0 else 0.0
    if q > 0:
        pb = pb.with_(noise=max(pb.noise, q / math.sqrt(12.0)))
    pb = pb.with_(noise=capped_noise(pb, P.rough, q))
    lines = tuple({"frequency_hz": l.frequency_hz, "amplitude_m": l.amplitude, "accel_ratio": l.accel_ratio,
                   "evidence": l.evidence} for l in sorted(force_lines, key=lambda l: -l.amplitude))
    return Refitted(prep=P, pb=pb, nom=nom, refit=fit_, check=check, acc_clip=acc_clip, acc_use=acc_use,
                    acc_model=acc_model, pickup=tuple(pickup), acc_pickup=tuple(acc_pickup), lines=lines, q=q,
                    q_acc=q_acc, floor_ref=floor_ref, y_nom=y_nom, y_ref=y_ref)


def distortion(R: Refitted, pb: Problem, r_harm: np.ndarray,
               x_multi: np.ndarray) -> tuple[str | None, dict | None, bool | None]:
    """Nonlinear distortion the command's own structure shows: a sweep's harmonics in r_harm, or a multisine's
    unexcited lines in x_multi. (mismatch key, measurement, distortion above the screen); None when the command
    has neither (or the multisine's lines could not be read)."""
    P = R.prep
    if command_mod.harmonic_window_ok(P.cmd_info):
        h = locate.harmonics(r_harm * P.use, P.cmd_info.phase, P.fs, pb.noise)
        return "harmonics", h, h["odd_over_noise"] > HARMONIC_SCREEN
    if P.cmd_info.kind == "multisine":
        ms = locate.multisine_lines(P.cmd_info, x_multi, P.use, R.floor_ref, [l["frequency_hz"] for l in R.lines])
        vals = [v for v in (ms.get("odd_z"), ms.get("even_z")) if v is not None]
        return "multisine_lines", ms, (bool(vals) and max(vals) > 2 * HARMONIC_SCREEN) if ms else None
    return None, None, None


def screen(R: Refitted, say: Callable[[str], None]) -> Screened:
    """What the refit leaves: distortion; and whether the recording is excited enough for a claim."""
    pb = R.pb
    say("locating the mismatch")
    key, d, hint = distortion(R, pb, pb.y - R.y_ref, pb.y - pb.basis.B @ R.refit.coef)
    moved = (pb.y - pb.basis.zero(R.refit.coef) - pb.basis.B[:, pb.basis.n_zero:] @
             R.refit.coef[pb.basis.n_zero:])[R.prep.use]
    snr = float(np.std(moved) / pb.noise) if pb.noise > 0 else 0.0
    no_claim = R.prep.no_claim
    if not no_claim and snr < MIN_SNR:
        no_claim = (f"the position moves only {snr:.1f}x its noise (beyond the sensor's zero and lines): too "
                    "poorly excited for a claim")
    return Screened(R, (key, d) if d else (None, None), hint, no_claim)


def settle(S: Screened, sel: Selection, prev: Settled | None = None) -> Settled:
    """Lines the distortion of the refit residual hid: pickup found now joins the sensor terms (every model is
    re-evaluated with it; the physics parameters stay). Then the noise floor of the augmented residual. prev: the
    models as an earlier settle left them (before the pair step)."""
    R = S.fitted
    P = R.prep
    if prev is None:
        pb, nom, refit_, pickup, y_nom, y_ref = R.pb, R.nom, R.refit, R.pickup, R.y_nom, R.y_ref
    else:
        pb, nom, refit_, pickup, y_nom, y_ref = prev.pb, prev.nom, prev.refit, prev.pickup, prev.y_nom, prev.y_ref
    aug = sel.current
    pb = pb.with_(noise=min(pb.noise, floor(pb, pb.y - pb.series(aug), P.cmd_info).rms_m or pb.noise))
    more, _, _ = residual_lines(pb, pb.y - pb.series(aug), P.acc, R.acc_model, R.check, P.fs, P.cmd_info,
                                R.acc_use)
    more = [l for l in more if all(abs(l.frequency_hz - x) > 2.0 / P.rec.duration_s for x in pb.basis.lines_hz)]
    if more:
        pickup = pickup + tuple(more)
        pb = pb.with_(basis=pb.basis.with_(lines_hz=pb.basis.lines_hz + tuple(l.frequency_hz for l in more)))
        nom = pb.evaluate(nom.lin, nom.fx, nom.k)
        refit_ = pb.evaluate(refit_.lin, refit_.fx, refit_.k)
        sel = Selection(pb.evaluate(aug.lin, aug.fx, aug.k), sel.chosen, sel.stats, sel.groups, sel.tried,
                        sel.round1)
        y_nom, y_ref = pb.series(nom), pb.series(refit_)
    y_aug = pb.series(sel.current)
    floor_aug = floor(pb, pb.y - y_aug, P.cmd_info)
    pb = pb.with_(noise=min(pb.noise, max(floor_aug.rms_m, R.q / math.sqrt(12.0) if R.q else 0.0)) or pb.noise)
    pb = pb.with_(noise=capped_noise(pb, P.rough, R.q))
    return Settled(S, sel, pb, nom, refit_, pickup, y_nom, y_ref, y_aug, pb.y - y_ref, floor_aug)


def _figures(pb: Problem, yhat: np.ndarray, k: int) -> FitFigures:
    r = pb.y - yhat
    u = pb.use

    def nrmse(m):
        yy = pb.y[m]
        return float(np.sqrt(np.sum(r[m] ** 2) / max(np.sum((yy - yy.mean()) ** 2), 1e-300)))
    rr = float(np.sqrt(np.mean(r[u] ** 2)))
    return FitFigures(nrmse=nrmse(u), residual_rms_m=rr, residual_over_noise=rr / pb.noise,
                      nrmse_fit=nrmse(pb.mfit), nrmse_holdout=nrmse(pb.mhold),
                      residual_over_noise_fit=float(np.sqrt(np.mean(r[pb.mfit] ** 2)) / pb.noise),
                      residual_over_noise_holdout=float(np.sqrt(np.mean(r[pb.mhold] ** 2)) / pb.noise),
                      n_parameters=k + pb.basis.m, n_sensor_parameters=pb.basis.m)


def locate_mismatch(T: Settled) -> Located:
    """Where the mismatch lives (bands, windows, regimes) for each model, and the fit figures."""
    P, R = T.screened.fitted.prep, T.screened.fitted
    pb, use, aug = T.pb, P.use, T.sel.current
    B = pb.basis.B
    frf = locate.frf_bands(pb.cmd * use, (pb.y - B @ aug.coef) * use,
                           {"nominal": (T.y_nom - B @ T.nom.coef) * use, "refit": (T.y_ref - B @ T.refit.coef) * use,
                            "augmented": (T.y_aug - B @ aug.coef) * use}, P.fs, *P.band)
    wins, worst, _ = locate.mismatch_windows((pb.y - T.y_nom) * use, P.fs, pb.noise)
    wins_r, worst_r, _ = locate.mismatch_windows(T.r_ref * use, P.fs, pb.noise)
    _, worst_a, _ = locate.mismatch_windows((pb.y - T.y_aug) * use, P.fs, pb.noise)
    frac = float(sum(l["amplitude_m"] ** 2 / 2 for l in R.lines) / max(np.mean(T.r_ref[use] ** 2), 1e-300)) \
        if R.lines else 0.0
    mm = {
        "uncorrelated": {"lines": list(R.lines), "pickup": [l.as_dict() for l in R.pickup + R.acc_pickup],
                         "fraction_of_refit_residual_in_lines": frac},
        "command": {"kind": P.cmd_info.kind, "description": P.cmd_info.describe(),
                    "band_hz": [float(P.band[0]), float(P.band[1])]},
        "bands_hz": locate.mismatch_bands(frf, "nominal"),
        "windows_s": wins,
        "after_refit": {"bands_hz": locate.mismatch_bands(frf, "refit"), "windows_s": wins_r},
        "after_augmented": {"bands_hz": locate.mismatch_bands(frf, "augmented")},
        "regimes": locate.regimes(pb.cmd, pb.y - B @ T.refit.coef, T.r_ref, P.fs, pb.noise, use),
        "regimes_augmented": locate.regimes(pb.cmd, pb.y - B @ aug.coef, pb.y - T.y_aug, P.fs, pb.noise, use),
        "worst_windows": {"nominal": worst, "refit": worst_r, "augmented": worst_a},
        "chirp_band_hz": [float(P.band[0]), float(P.band[1])],
    }
    fit = Fit(nominal=_figures(pb, T.y_nom, 0), refit=_figures(pb, T.y_ref, T.refit.k),
              augmented=_figures(pb, T.y_aug, aug.k))
    return Located(T, frf, mm, fit)

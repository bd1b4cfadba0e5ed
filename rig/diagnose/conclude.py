"""The last stage (Located -> Diagnosis): the sensor terms of the augmented model and the odd samples, the named
effects with their parameters and the tests they passed, the verdict, the data behind every plot, and the typed
result (rig.diagnose.results)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.signal import welch

from rig.diagnose import catalogue, evidence as evidence_mod, reduction, sensor as sensor_mod, uncertainty, units
from rig.diagnose.problem import ModelFit, Problem
from rig.diagnose.results import Diagnosis, Mismatch, NamedEffect
from rig.diagnose.stages import Located, noise_how
from rig.diagnose.verdict import verdict as judge


def conclude(L: Located, t_start: float, clock) -> Diagnosis:
    """The named effects with their parameters and tests, the verdict, the evidence behind each claim."""
    T = L.settled
    R = T.screened.fitted
    P = R.prep
    pb, sel, augmented = T.pb, T.sel, T.sel.current
    sensor, clip_notes = sensor_terms(L)
    unit = sensor.unit
    mm = L.mismatch
    stand = uncertainty.standings(pb, augmented, T.refit, sel.chosen, sel.round1)
    bias, too_long = reduction.bias(pb, augmented) if sel.chosen else ({}, "")   # the reduced model's own, taken off
    shown = replace(augmented, fx=reduction.corrected(pb, augmented, bias))
    effects = tuple(sorted((NamedEffect(name, public_params(pb, name, shown), float(sel.stats[name]["lr_holdout"]),
                                        sel.stats[name],
                                        R.lines[0]["evidence"] if catalogue.get(name).projected and R.lines else "",
                                        interval=reduction.shifted(stand[name].interval, bias.get(name, {})),
                                        share=stand[name].share, evidence=stand[name].evidence,
                                        bias=bias.get(name, {}))
                            for name in sel.chosen), key=lambda e: -e.evidence))    # the strongest first
    v = judge(pb, T.screened.no_claim, bool(effects), L.fit, T.refit, R.check)
    v = replace(v, rest=rest_of(mm, L.fit) if v.status not in ("explained", "no_claim") else (),
                noise=noise_how(T))
    not_claimed = ()
    if v.status == "not_described" and effects:
        not_claimed, effects = effects, ()
    key, dist = T.screened.distortion
    mismatch = Mismatch(notes=P.notes + tuple(clip_notes) + ((too_long,) if too_long else ()), not_claimed=not_claimed,
                        harmonics=dist if key == "harmonics" else None,
                        multisine_lines=dist if key == "multisine_lines" else None, **mm)
    frf_out = {k: (v_.tolist() if not np.iscomplexobj(v_) else {"re": v_.real.tolist(), "im": v_.imag.tolist()})
               for k, v_ in L.frf.items()}
    frf_out["residual_spectra"] = _residual_spectra(pb, {"nominal": T.y_nom, "refit": T.y_ref,
                                                         "augmented": T.y_aug})
    ev = evidence_mod.collect(pb, P.cmd_info, T.refit, augmented, effects, mismatch, sensor, P.acc, R.acc_use,
                              R.check, R.acc_model, T.floor_aug)
    series = {"nominal_m": T.y_nom, "refit_m": T.y_ref, "augmented_m": T.y_aug,
              "augmented_sensor_m": pb.basis.B @ augmented.coef}
    return Diagnosis(effects=effects, groups=sel.groups if effects else (), mismatch=mismatch, fit=L.fit,
                     params_refit=pb.plant.public_linear(T.refit.lin), noise_m=float(pb.noise), verdict=v,
                     sensor=sensor, command=P.cmd_info, plant=_plant_doc(pb, augmented, unit), candidates=sel.tried,
                     series=series, frf=frf_out, evidence=ev, used=P.use, noise_floor=T.floor_aug,
                     timing_s=clock() - t_start)


def _moves_under(pred: np.ndarray, at: np.ndarray) -> float:
    """How far the model's response moves, at the median, within the runs where the reading sits exactly flat at
    its extreme (a slow peak's dwell on a quantised level moves it by about one step; a clip, by its whole
    excursion beyond the range)."""
    d = np.diff(np.r_[0, at.astype(int), 0])
    runs = [pred[a:b] for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]
    return float(np.median([np.ptp(r) for r in runs])) if runs else 0.0


def rest_of(mm: dict, fit) -> tuple[str, ...]:
    """Where the residual the augmented model leaves lies: the bands still off, the worst time windows, the regimes
    where it is largest (each a phrase)."""
    out = []
    bands = mm["after_augmented"]["bands_hz"]
    if bands:
        out.append("the bands " + ", ".join(f"{a:.3g}-{b:.3g} Hz" for a, b in bands[:5])
                   + (f" (+{len(bands) - 5} more)" if len(bands) > 5 else ""))
    worst = [w for w in mm["worst_windows"].get("augmented", []) if w["over_noise"] > 1.5]
    if worst:
        out.append("the time windows " + ", ".join(f"{w['t0_s']:.4g}-{w['t1_s']:.4g} s ({w['over_noise']:.1f}x noise)"
                                                    for w in worst))
    reg = {k: v["rms_over_noise"] for k, v in mm.get("regimes_augmented", {}).items()}
    if len(reg) > 1:
        typical = float(np.median(list(reg.values())))
        high = sorted((k for k, v in reg.items() if v > 1.25 * typical), key=lambda k: -reg[k])[:2]
        if high:
            out.append("the regimes " + ", ".join(f"{k.replace('_', ' ')} ({reg[k]:.1f}x noise, against "
                                                  f"{typical:.1f}x typical)" for k in high))
    return tuple(out)


def public_params(pb: Problem, name: str, f: ModelFit) -> dict:
    prm = dict(f.fx.get(name, {}))
    if catalogue.get(name).projected and f.dist is not None:
        fq, a, b = f.dist
        line = pb.force_basis(f.lin, f.fx) @ np.array([a, b])
        tail = line[-max(10, int(pb.fs)):]                      # steady state: the last second
        prm.update(force_n=math.hypot(a, b), phase_rad=math.atan2(b, a),
                   amplitude_m=float(math.sqrt(2.0) * np.sqrt(np.mean(tail ** 2))))
    derived = catalogue.get(name).derived
    if derived is not None:
        prm.update(derived(prm, pb.fs))
    return {k: float(v) for k, v in prm.items()}


def _residual_spectra(pb: Problem, models: dict) -> dict:
    """Welch amplitude spectral densities of each residual (m/sqrt(Hz)) and the noise floor."""
    out = {}
    nper = int(min(pb.n, 4 * pb.fs))
    f = np.array([])
    for k, yhat in models.items():
        f, P = welch((pb.y - yhat) * pb.use, fs=pb.fs, nperseg=nper)
        out[k] = np.sqrt(P / max(pb.use.mean(), 1e-6)).tolist()
    out["freqs_hz"] = f.tolist()
    out["noise_asd"] = float(pb.noise / math.sqrt(pb.fs / 2))
    return out


def _clips(L: Located) -> tuple[list[sensor_mod.Clip], list[str]]:
    """Flat tops of the measured output that the refit goes beyond, or moves under (a converter's or a sensor's
    range: an output clip), and of the accelerometer; the notes that say so."""
    T = L.settled
    R = T.screened.fitted
    P = R.prep
    pb, pos, fs = T.pb, P.pos, P.fs
    unit = getattr(P.rec, "output_unit", "m")
    clip_cand, clip_lo, clip_hi = P.clip
    clips, notes = [], []
    if clip_cand.any():
        pred = pb.series(T.refit)
        for lvl, side in ((clip_hi, 1), (clip_lo, -1)):
            if lvl is None:
                continue
            at = clip_cand & ((pos >= lvl - 1e-9 * abs(lvl)) if side > 0 else (pos <= lvl + 1e-9 * abs(lvl)))
            beyond = float(np.mean((pred[at] - lvl) * side)) if at.any() else 0.0
            if beyond > max(3 * pb.noise, R.q) or _moves_under(pred, at) > max(3 * pb.noise, 2 * R.q):
                clips.append(sensor_mod.Clip("position_m", lvl if side < 0 else None, lvl if side > 0 else None,
                                             int(at.sum()), float(np.argmax(at) / fs)))
        if clips:
            what = "position" if unit in ("m", "rad") else "output"
            notes.append(f"{what} clipped at " + ", ".join(
                f"{units.amount(c.high if c.high is not None else c.low, unit, '.4g')} ({c.samples} samples, first "
                f"at {c.first_s:.4g} s)" for c in clips) + ": an output clip (the sensor's or its converter's "
                "range: the model's response goes on beyond or under it while the reading stays exactly flat); the "
                "clipped samples are left out of the fit")
    if R.acc_clip.any():
        clips.append(sensor_mod.Clip("accel_mps2", float(np.min(P.acc)), float(np.max(P.acc)),
                                     int(R.acc_clip.sum()), float(np.argmax(R.acc_clip) / fs)))
        notes.append(f"accelerometer flat at its range in {int(R.acc_clip.sum())} samples: left out of the line "
                       "tests")
    return clips, notes


def sensor_terms(L: Located) -> tuple[sensor_mod.SensorTerms, list[str]]:
    """The sensor terms of the augmented model, the accelerometer's offset and the odd samples; the notes on the
    odd samples."""
    T = L.settled
    R = T.screened.fitted
    P = R.prep
    pb, acc, check, q = T.pb, P.acc, R.check, R.q
    terms = pb.basis.terms(T.sel.current.coef)
    pickup = [replace(l, amplitude=a_, phase_rad=ph_) for l, (f_, a_, ph_) in zip(T.pickup, terms["lines"])]
    pickup += list(T.pickup[len(pickup):])
    clipped, notes = _clips(L)
    acc_off = None
    if np.ptp(acc) > 0:
        am = R.acc_model if R.acc_model is not None else 0.0
        acc_off = float(np.mean((acc - (check.gain.real * am if check.usable else 0.0))[R.acc_use]))
    sensor = sensor_mod.SensorTerms(
        offset_m=terms["offset_m"], drift_m_per_s=terms["drift_m_per_s"], wander_terms=pb.basis.wander_terms,
        wander_rms_m=terms["wander_rms_m"], lines=pickup + list(R.acc_pickup), accel_offset_mps2=acc_off,
        accel=check, quantisation_step_m=q, accel_quantisation_step_mps2=R.q_acc, clipped=clipped,
        start_transient_s=P.transient_s if P.cmd_info.starts_mid_run else 0.0, notes=[],
        unit=getattr(P.rec, "output_unit", "m"))
    if pb.shoot is not None:
        sensor.notes.append("no offset or drift is fitted: the segment-wise initial states hold the transducer's zero")
    if q > 0:
        sensor.notes.append(f"output quantised in steps of {units.amount(q, sensor.unit)}: a noise floor of "
                            f"{units.amount(q / math.sqrt(12), sensor.unit)} rms (step/sqrt(12)); residual "
                            "structure below it means nothing")
    if check.note:
        sensor.notes.append(check.note)
    return sensor, notes


def _plant_doc(pb: Problem, augmented: ModelFit, unit: str) -> dict:
    """What diagnosis.json says of the plant: its family, the command's and the measured output's units, the linear
    parameters of the augmented model, and the segment-wise initial states when the plant integrates."""
    doc = {"family": pb.plant.family, "input_unit": pb.plant.input_unit, "output_unit": unit,
           "free_parameters": list(pb.lin_keys),
           "augmented_linear": pb.plant.public_linear(augmented.lin)}
    if pb.shoot is not None:
        doc["shooting"] = pb.shoot.as_dict(pb.fs)
    return doc

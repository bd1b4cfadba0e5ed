"""The last stage (Located -> Diagnosis): the sensor terms of the augmented model and the odd samples, the named
effects with their parameters and the tests they passed, the verdict, the data behind every plot, and the typed
result (rig.diagnose.results)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.signal import welch

from rig.diagnose import catalogue, evidence as evidence_mod, sensor as sensor_mod
from rig.diagnose.problem import ModelFit, Problem
from rig.diagnose.results import Diagnosis, Mismatch, NamedEffect
from rig.diagnose.stages import Located
from rig.diagnose.verdict import verdict as judge


def conclude(L: Located, t_start: float, clock) -> Diagnosis:
    """The named effects with their parameters and tests, the verdict, the evidence behind each claim."""
    T = L.settled
    R = T.screened.fitted
    P = R.prep
    pb, sel, augmented = T.pb, T.sel, T.sel.current
    sensor, clip_notes = sensor_terms(L)
    mm = L.mismatch
    effects = tuple(NamedEffect(name, public_params(pb, name, augmented), float(sel.stats[name]["lr_holdout"]),
                                sel.stats[name],
                                R.lines[0]["evidence"] if catalogue.get(name).projected and R.lines else "")
                    for name in sel.chosen)
    v = judge(pb, T.screened.no_claim, bool(effects), L.fit, T.refit, R.check)
    not_claimed = ()
    if v.status == "not_described" and effects:
        not_claimed, effects = effects, ()
    key, dist = T.screened.distortion
    mismatch = Mismatch(notes=P.notes + tuple(clip_notes), not_claimed=not_claimed,
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
                     sensor=sensor, command=P.cmd_info, plant=_plant_doc(pb, augmented), candidates=sel.tried,
                     series=series, frf=frf_out, evidence=ev, used=P.use, noise_floor=T.floor_aug,
                     timing_s=clock() - t_start)


def public_params(pb: Problem, name: str, f: ModelFit) -> dict:
    prm = dict(f.fx.get(name, {}))
    if catalogue.get(name).projected and f.dist is not None:
        fq, a, b = f.dist
        line = pb.force_basis(f.lin, f.fx) @ np.array([a, b])
        tail = line[-max(10, int(pb.fs)):]                      # steady state: the last second
        prm.update(force_n=math.hypot(a, b), phase_rad=math.atan2(b, a),
                   amplitude_m=float(math.sqrt(2.0) * np.sqrt(np.mean(tail ** 2))))
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
    """Flat tops of the position that the refit goes beyond (a converter's range), and of the accelerometer; the
    notes that say so."""
    T = L.settled
    R = T.screened.fitted
    P = R.prep
    pb, pos, fs = T.pb, P.pos, P.fs
    clip_cand, clip_lo, clip_hi = P.clip
    clips, notes = [], []
    if clip_cand.any():
        pred = pb.series(T.refit)
        for lvl, side in ((clip_hi, 1), (clip_lo, -1)):
            if lvl is None:
                continue
            at = clip_cand & ((pos >= lvl - 1e-9 * abs(lvl)) if side > 0 else (pos <= lvl + 1e-9 * abs(lvl)))
            beyond = float(np.mean((pred[at] - lvl) * side)) if at.any() else 0.0
            if beyond > max(3 * pb.noise, R.q):
                clips.append(sensor_mod.Clip("position_m", lvl if side < 0 else None, lvl if side > 0 else None,
                                             int(at.sum()), float(np.argmax(at) / fs)))
        if clips:
            notes.append("position clipped at " + ", ".join(
                f"{(c.high if c.high is not None else c.low):.4g} m ({c.samples} samples, first at {c.first_s:.3f} s)"
                for c in clips) + ": the clipped samples are left out of the fit")
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
        start_transient_s=P.transient_s if P.cmd_info.starts_mid_run else 0.0, notes=[])
    if pb.shoot is not None:
        sensor.notes.append("no offset or drift is fitted: the segment-wise initial states hold the transducer's zero")
    if q > 0:
        sensor.notes.append(f"position quantised in steps of {q:.3g} m: a noise floor of {q / math.sqrt(12):.3g} m rms "
                            f"(step/sqrt(12)); residual structure below it means nothing")
    if check.note:
        sensor.notes.append(check.note)
    return sensor, notes


def _plant_doc(pb: Problem, augmented: ModelFit) -> dict:
    """What diagnosis.json says of the plant: its family, the command's unit, the linear parameters of the
    augmented model, and the segment-wise initial states when the plant integrates."""
    doc = {"family": pb.plant.family, "input_unit": pb.plant.input_unit,
           "free_parameters": list(pb.lin_keys),
           "augmented_linear": pb.plant.public_linear(augmented.lin)}
    if pb.shoot is not None:
        doc["shooting"] = pb.shoot.as_dict(pb.fs)
    return doc

"""One recording's line of a batch summary, made from the typed results of the analysis (rig.diagnose.results
Diagnosis; a run of the four-mount rig's RigDiagnosis, rig.diagnose.machine.result; rig.identify IdentResult; the
dict of rig.diagnose.refit.identify_plant).

A row's content (JSON-safe, floats exact):
  verdict      the diagnosis's verdict status (explained, partly, not_described, no_claim); identify: ""
  effects      {effect name: {parameter key: value in SI}} as named (a run of the rig: "name[location]")
  parameters   {key: value} the identified linear parameters (a diagnosis: the augmented model's fitted ones)
  std          {key: 1 sigma} where the analysis gives one (identify)
  units        {key: unit} of the parameters
  figures      the fit's figures ({"residual_over_noise_holdout", "nrmse", "noise_m"}; identify: nrmse, FRF error)
  notes        short notes (weakly identified parameters, a warning)
  recording    {"samples", "fs_hz", "duration_s"}
The batch adds what it knows around it (rig.batch.run): name, path, status, error, date, time, worker.
"""
from __future__ import annotations

import math

from rig.identify import UNITS as EHA_UNITS
from sim_backend.linear import IDENTIFIED


def _num(v):
    """A value as JSON keeps it exactly (a float's repr round-trips); non-finite -> None, others as text."""
    if isinstance(v, bool):
        return v
    if isinstance(v, (int, float)) or hasattr(v, "__float__"):
        f = float(v)
        return f if math.isfinite(f) else None
    return str(v)


def _recording(rec) -> dict:
    return {"samples": rec.n, "fs_hz": float(rec.fs_hz), "duration_s": float(rec.duration_s)}


def diagnosis_row(diag, rec) -> dict:
    """A Diagnosis (rig.diagnose.results) as a summary row."""
    free = diag.plant.get("free_parameters") or list(diag.params_refit)
    lin = diag.plant.get("augmented_linear") or diag.params_refit
    aug = diag.fit.augmented
    return {"verdict": diag.verdict.status,
            "effects": {e.name: {k: _num(v) for k, v in e.parameters.items()} for e in diag.effects},
            "parameters": {k: _num(lin[k]) for k in free if k in lin},
            "std": {},
            "units": {k: EHA_UNITS.get(k, "") for k in free},
            "figures": {"residual_over_noise_holdout": _num(aug.residual_over_noise_holdout),
                        "nrmse": _num(aug.nrmse), "noise_m": _num(diag.noise_m)},
            "notes": [" ~ ".join(g) + " confounded" for g in diag.groups],
            "recording": _recording(rec)}


def rig_diagnosis_row(diag, rec) -> dict:
    """A run of the four-mount rig's diagnosis (rig.diagnose.machine.result RigDiagnosis) as a summary row: each
    effect under "name[location]" (two mounts may have the same effect), the refit's common factors and latency
    as its parameters, and the worst mount's held-out residual over expected, model and diagnosed."""
    def worst(model: str):
        return _num(max(v for m in diag.fit[model].values() for v in m.values()))
    return {"verdict": diag.verdict,
            "effects": {f"{e.name}[{e.location}]": {k: _num(v) for k, v in e.parameters.items()}
                        for e in diag.effects},
            "parameters": {k: _num(v) for k, v in diag.refit.items()},
            "std": {},
            "units": {k: "s" if k.endswith("_s") else "" for k in diag.refit},
            "figures": {"worst_mount_residual_model": worst("nominal"),
                        "worst_mount_residual_diagnosed": worst("augmented")},
            "notes": [str(n) for n in diag.notes],
            "recording": _recording(rec)}


def identify_row(res, rec) -> dict:
    """An IdentResult (rig.identify, the eha actuator's six parameters) as a summary row."""
    f = res.fit
    notes = [f"{k} weakly identified" for k in res.weakly_identified]
    if "warning" in f:
        notes.append(str(f["warning"]))
    return {"verdict": "", "effects": {},
            "parameters": {k: _num(getattr(res.params, k)) for k in IDENTIFIED},
            "std": {k: _num(res.std[k]) for k in IDENTIFIED if k in res.std},
            "units": {k: EHA_UNITS[k] for k in IDENTIFIED},
            "figures": {"nrmse": _num(f["nrmse"]), "frf_err_db": _num(f["frf_err_db"]),
                        "frf_err_deg": _num(f["frf_err_deg"])},
            "notes": notes, "recording": _recording(rec)}


def identify_plant_row(res: dict, rec) -> dict:
    """rig.diagnose.refit.identify_plant's result (a plant file's free parameters) as a summary row."""
    keys = list(res["std"]) or list(res["start"])
    notes = [f"{k} at its bound" for k in res.get("at_bounds", [])]
    if "warning" in res:
        notes.append(str(res["warning"]))
    f = res["fit"]
    return {"verdict": "", "effects": {},
            "parameters": {k: _num(res["parameters"][k]) for k in keys},
            "std": {k: _num(v) for k, v in res["std"].items()},
            "units": {k: "" for k in keys},
            "figures": {"nrmse": _num(f["nrmse"]), "residual_rms_m": _num(f["residual_rms_m"])},
            "notes": notes, "recording": _recording(rec)}

"""Blind proof of the diagnosis (issue 7): make recordings that hide known effects, diagnose them, grade.

Cases are drawn from a seed: the paper's Table 1 model with its six identified parameters moved +-15 %, zero,
one or two effects from the catalogue (rig/diagnose/catalogue/: each effect's "stand" draw) with physically
plausible parameters,
and the recordings' sensor noise. They are simulated with sim_backend.actuator.simulate_stand (the physics that
matches the reference recordings), diagnosed without the truth, and graded:
  right  = the named set of effects is exactly the true set ("none" when both are empty)
  errors = relative parameter error of each true effect that was named (targets: delay 20 %, frequency 5 %).
"""
from __future__ import annotations

import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, asdict
from multiprocessing import get_context
from pathlib import Path
from typing import Callable

import numpy as np

from rig import excitation as ex
from rig.diagnose import catalogue, report
from rig.diagnose.engine import diagnose
from rig.diagnose.results import MODELS
from rig.errors import RigError
from rig.recordings.recording import Recording
from rig.recordings.rigformat import load_recording
from sim_backend.actuator import linear_chirp, simulate_stand
from sim_backend.linear import IDENTIFIED, ActuatorParams
from sim_backend.sensors import Line, SensorHabits

CATALOGUE = catalogue.for_proof("stand")      # the effects drawn, in the draws' order
NONE = "none"
POSITION_NOISE_M = 2e-8          # rms, as the shared recordings (README)
ACCEL_NOISE_MPS2 = 2e-4
LINEAR_SPREAD = 0.15             # six identified parameters moved by up to +-15 %
TARGETS = {"delay_s": 0.20, "frequency_hz": 0.05}   # relative error targets of issue 7


@dataclass
class Case:
    """One blind case: what is hidden in it and how it is recorded."""
    name: str
    effects: dict                       # answers.json style {"transport_delay": {"delay_s": ...}, ...}
    linear: dict                        # true K_L, C, w_nv, zeta, K_Q, K_C
    fs_hz: float = 1000.0
    duration_s: float = 100.0
    amplitude_V: float = 2.0
    seed: int = 0
    hidden: dict = field(default_factory=dict)   # simulator-only parameters (base mass, disturbance force/phase)
    excitation: dict = field(default_factory=dict)   # {"kind": ..., generator keywords}; empty: the paper's chirp
    sensor: dict = field(default_factory=dict)       # sim_backend.sensors.SensorHabits fields; empty: white noise
    pre_s: float = 0.0                  # the recording starts this long after the excitation did (mid-run start)
    habits: list[str] = field(default_factory=list)  # short tags of the habits drawn (for the score by habit)

    def noise_m(self) -> float:
        """The position noise the recording really carries (converter step included)."""
        if not self.sensor:
            return POSITION_NOISE_M
        q = self.sensor.get("quant_step_m", 0.0)
        return math.sqrt(self.sensor.get("position_noise_m", POSITION_NOISE_M) ** 2 + q * q / 12.0)

    def pickup_lines_hz(self) -> list[float]:
        return [l["frequency_hz"] for l in self.sensor.get("position_lines", [])]

    def pickup_lines_m(self) -> list[float]:
        return [l["amplitude"] for l in self.sensor.get("position_lines", [])]


# ---- case generation ---------------------------------------------------------------------------------
def _disturbance_force_n(p: ActuatorParams, f_hz: float, amplitude_m: float, base: dict | None = None) -> float:
    """Force giving a position line of amplitude_m at f_hz: scale a short simulated 1 N response (with the stand
    mode when the case has one: a soft stand lets the force move piston and housing together)."""
    fs = 2000.0
    n = int(fs * max(1.0, 40.0 / f_hz))
    if base:
        n = max(n, int(fs * 8.0 / (base["damping_ratio"] * base["frequency_hz"])))    # past its ring-down
    fx = catalogue.stand_effects({"base_resonance": base} if base else {},
                                 disturbance_frequency_hz=f_hz, disturbance_force_n=1.0)
    y = simulate_stand(p, np.zeros(n), fs, fx)
    tail = y["position_m"][n // 2:]                    # past the start transient
    t = np.arange(n)[n // 2:] / fs
    X = np.c_[np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t), np.ones_like(t)]
    c, *_ = np.linalg.lstsq(X, tail, rcond=None)
    return amplitude_m / max(float(np.hypot(c[0], c[1])), 1e-15)


@dataclass(frozen=True)
class DrawContext:
    """What an effect's draw for this proof knows (rig/diagnose/catalogue: Draw): the case's actuator, the
    command's peak, the position noise, the effects drawn before it (with their simulator-only extras) and the
    force that gives a position line of a given amplitude."""
    p: ActuatorParams
    amplitude_V: float
    position_noise_m: float
    drawn: dict

    def line_force_n(self, f_hz: float, amplitude_m: float, base: dict | None) -> float:
        return _disturbance_force_n(self.p, f_hz, amplitude_m, base)


def _draw_effects(names, rng: np.random.Generator, p: ActuatorParams, amplitude_V: float,
                  sens: dict) -> tuple[dict, dict]:
    """Plausible parameters of each effect named (catalogue parameters, simulator-only extras), a line drawn
    apart from the pickup lines (mixed lines are out of scope)."""
    effects, hidden = {}, {}
    for name in sorted(names):
        draw = catalogue.get(name).draws["stand"]
        ctx = DrawContext(p, amplitude_V, POSITION_NOISE_M, {n: {**v, **hidden.get(n, {})} for n, v in effects.items()})
        for _ in range(20):
            effects[name], extra = draw.draw(rng, ctx)
            f_d = effects[name].get("frequency_hz") if draw.apart_from_pickup else None
            if f_d is None or all(abs(f_d - l["frequency_hz"]) > 2.0 for l in sens.get("position_lines", [])):
                break
        if extra:
            hidden[name] = extra
    return effects, hidden


EXCITATIONS = ("linear_chirp", "log_sweep", "multilevel_chirp", "odd_multisine", "band_noise", "steps")
RATES_HZ = (500.0, 1000.0, 2000.0, 5000.0, 10000.0)
RATE_WEIGHTS = (0.15, 0.3, 0.3, 0.15, 0.1)


def _draw_excitation(rng: np.random.Generator, duration_s: float) -> tuple[dict, float]:
    """One of the excitation types with plausible settings; returns (keywords for rig.excitation, peak V)."""
    kind = str(rng.choice(EXCITATIONS))
    a = round(float(rng.uniform(1.8, 2.5)), 2)
    if kind == "linear_chirp":
        return {"kind": kind, "f0_hz": 0.1, "f1_hz": 100.0, "amplitude_V": a}, a
    if kind == "log_sweep":
        return {"kind": kind, "f0_hz": round(float(rng.uniform(0.1, 0.5)), 3), "f1_hz": 100.0, "amplitude_V": a}, a
    if kind == "multilevel_chirp":
        top = round(float(rng.uniform(2.5, 3.3)), 2)
        levels = [round(top * r, 3) for r in (1 / 6, 0.5, 1.0)]
        return {"kind": kind, "f0_hz": 0.1, "f1_hz": 100.0, "levels_V": levels}, top
    if kind == "odd_multisine":
        per = float(rng.choice([5.0, 10.0]))
        return {"kind": kind, "f0_hz": 0.1, "f1_hz": 100.0, "amplitude_V": a, "period_s": per,
                "seed": int(rng.integers(2 ** 31))}, a
    if kind == "band_noise":
        a = round(float(rng.uniform(2.0, 3.0)), 2)
        return {"kind": kind, "f0_hz": 0.1, "f1_hz": 100.0, "amplitude_V": a, "seed": int(rng.integers(2 ** 31))}, a
    return {"kind": "steps", "amplitude_V": a, "seed": int(rng.integers(2 ** 31))}, a


def _draw_sensor(rng: np.random.Generator, fs: float) -> tuple[dict, list[str]]:
    """The habits of a rig's sensors with random sizes (sim_backend.sensors.SensorHabits fields) and their tags.
    Varied the way another simulator might: noise colour and level, a filter before the converter, the step,
    line amplitudes and phases, the drift's shape."""
    tags = []
    noise = float(rng.uniform(1e-8, 4e-8))
    colour = str(rng.choice(["white", "white", "lowpass", "pink"]))
    corner = float(rng.uniform(0.1, 0.4) * fs) if colour == "lowpass" else float(rng.uniform(0.5, 5.0))
    hab = {"position_noise_m": noise, "accel_noise_mps2": float(rng.uniform(1e-4, 5e-4)), "noise_colour": colour,
           "noise_corner_hz": corner if colour != "white" else 0.0,
           "offset_m": float(rng.choice([-1, 1]) * rng.uniform(0.5e-6, 20e-6)),
           "drift_m_per_s": float(rng.choice([-1, 1]) * rng.uniform(5e-9, 80e-9)),
           "drift_shape": str(rng.choice(["linear", "exponential", "wander"])),
           "drift_tau_s": float(rng.uniform(20.0, 120.0)),
           "accel_offset_mps2": float(rng.uniform(-0.1, 0.1)), "seed": int(rng.integers(2 ** 31))}
    if hab["drift_shape"] == "wander":
        hab["wander_m"] = float(rng.uniform(1.0, 5.0) * noise)
    tags.append("offset")
    tags.append(f"drift:{hab['drift_shape']}")
    if colour != "white":
        tags.append(f"noise:{colour}")
    if rng.random() < 0.3:
        hab["adc_filter_hz"] = float(rng.uniform(0.3, 0.45) * fs)
        tags.append("adc-filter")
    if rng.random() < 0.6:
        mains = float(rng.choice([50.0, 60.0])) * (1 + float(rng.uniform(-0.002, 0.002)))
        lines = [{"frequency_hz": mains, "amplitude": float(rng.uniform(0.5, 8.0) * noise),
                  "phase_rad": float(rng.uniform(-math.pi, math.pi))}]
        for k in range(2, 6):
            if k * mains < 0.45 * fs and rng.random() < 0.5:
                lines.append({"frequency_hz": k * mains,
                              "amplitude": lines[0]["amplitude"] * float(rng.uniform(0.1, 0.5)),
                              "phase_rad": float(rng.uniform(-math.pi, math.pi))})
        hab["position_lines"] = lines
        tags.append(f"pickup:{mains:.0f}Hz" + (f"x{len(lines)}" if len(lines) > 1 else ""))
    if rng.random() < 0.2:
        mains = float(rng.choice([50.0, 60.0]))
        hab["accel_lines"] = [{"frequency_hz": mains,
                               "amplitude": float(rng.uniform(5.0, 30.0) * hab["accel_noise_mps2"]),
                               "phase_rad": float(rng.uniform(-math.pi, math.pi))}]
        tags.append("accel-pickup")
    if rng.random() < 0.4:
        hab["quant_step_m"] = float(rng.uniform(0.3, 4.0) * noise)
        tags.append("quantised")
    return hab, tags


def draw_cases(n: int, seed: int, *, duration_s: float = 100.0, p0: ActuatorParams | None = None,
               habits: bool = False) -> list[Case]:
    """n blind cases from seed: >= 25 % clean, the rest one or two effects, every catalogue effect used.

    habits: every case also carries the habits of real recordings (sensor offset, drift, pickup, quantisation,
    coloured noise, mid-run starts, any excitation type, sample rates 500 Hz - 10 kHz, lengths 20-200 s);
    duration_s is then the longest a case may be."""
    if n < 1:
        raise RigError(f"--n: expected at least 1 case, got {n}")
    p0 = p0 or ActuatorParams()
    rng = np.random.default_rng(seed)
    n0 = max(1, math.ceil(0.25 * n)) if n > 1 else 0
    n2 = round(0.3 * n) if n > 2 else 0
    n1 = n - n0 - n2
    counts = [0] * n0 + [1] * n1 + [2] * n2
    rng.shuffle(counts)
    singles = list(rng.permutation(CATALOGUE))        # cycle the catalogue so each effect appears
    cases = []
    for i, k in enumerate(counts):
        if k == 1:
            names = [str(singles[i % len(singles)])]
        else:
            names = [str(s) for s in rng.choice(CATALOGUE, size=k, replace=False)]
        lin = {key: float(getattr(p0, key) * rng.uniform(1 - LINEAR_SPREAD, 1 + LINEAR_SPREAD))
               for key in IDENTIFIED}
        p = p0.with_(**lin)
        amplitude = round(float(rng.uniform(1.8, 2.5)), 2)
        fs = float(rng.choice([1000.0, 2000.0]))
        dur, exc, sens, pre, tags = duration_s, {}, {}, 0.0, []
        if habits:
            fs = float(rng.choice(RATES_HZ, p=RATE_WEIGHTS))
            longest = min(duration_s, 200.0, 6e5 / fs)          # at most 600 k samples: prove stays affordable
            dur = round(float(np.exp(rng.uniform(math.log(20.0), math.log(max(20.0, longest))))), 1)
            exc, amplitude = _draw_excitation(rng, dur)
            sens, tags = _draw_sensor(rng, fs)
            span = "20-50s" if dur < 50 else ("50-100s" if dur < 100 else "100-200s")
            tags = [exc["kind"], f"fs{fs:g}", span] + tags
            if rng.random() < 0.35:
                pre = round(float(rng.uniform(2.0, 0.3 * dur)), 2)
                tags.append("mid-run")
        effects, hidden = _draw_effects(names, rng, p, amplitude, sens)
        tag = "+".join(effects) or "nominal"
        cases.append(Case(name=f"c{i + 1:02d}_{tag}", effects=effects, linear=lin, fs_hz=fs,
                          duration_s=dur, amplitude_V=amplitude, seed=int(rng.integers(2 ** 31)),
                          hidden=hidden, excitation=exc, sensor=sens, pre_s=pre, habits=tags))
    return cases


def excitation_of(case: Case):
    """The command of a case (rig.excitation), pre_s longer than the recording for a mid-run start."""
    if not case.excitation:
        return ex.linear_chirp(case.fs_hz, case.duration_s, 0.1, 100.0, case.amplitude_V)
    kw = dict(case.excitation)
    kind = kw.pop("kind")
    total = case.duration_s + case.pre_s
    if kind == "multilevel_chirp":
        n_lv = len(kw["levels_V"])
        return ex.multilevel_chirp(case.fs_hz, (total - 0.5 * (n_lv - 1)) / n_lv, **kw)
    return getattr(ex, kind)(case.fs_hz, total, **kw)


def simulate_case(case: Case, p0: ActuatorParams | None = None):
    """The recording of a case (zero-order hold, the plant on its stand, the sensors) as a Recording."""
    p = (p0 or ActuatorParams()).with_(**case.linear)
    full = {name: {**prm, **case.hidden.get(name, {})} for name, prm in case.effects.items()}
    if not case.excitation and not case.sensor and not case.pre_s:
        t, cmd = linear_chirp(case.fs_hz, case.duration_s, 0.1, 100.0, case.amplitude_V)
        fx = catalogue.stand_effects(full, position_noise_m=POSITION_NOISE_M, accel_noise_mps2=ACCEL_NOISE_MPS2,
                                     seed=case.seed)
        y = simulate_stand(p, cmd, case.fs_hz, fx)
        return Recording.from_signals(cmd, y["position_m"], y["accel_mps2"], fs_hz=case.fs_hz, source=case.name)
    cmd = excitation_of(case).cmd_V
    y = simulate_stand(p, cmd, case.fs_hz, catalogue.stand_effects(full))
    kw = dict(case.sensor)
    for key in ("position_lines", "accel_lines"):
        kw[key] = tuple(Line(**l) for l in kw.get(key, []))
    kw.setdefault("position_noise_m", POSITION_NOISE_M)
    kw.setdefault("accel_noise_mps2", ACCEL_NOISE_MPS2)
    kw.setdefault("seed", case.seed)
    pos, acc = SensorHabits(**kw).apply(y["position_m"], y["accel_mps2"], case.fs_hz)
    k0 = int(round(case.pre_s * case.fs_hz))
    return Recording.from_signals(cmd[k0:], pos[k0:], acc[k0:], fs_hz=case.fs_hz, source=case.name)


# ---- grading -----------------------------------------------------------------------------------------
def _fit_figure(diag, model: str, key: str) -> float | None:
    v = getattr(diag.fit.model(model), key)
    return None if v is None else float(v)


LINE_FOUND = 0.05               # a reported line within 5 % of a true one is that line; none: the line was missed


def _line_grades(true_hz: list[float], diag, true_m: list[float] | None = None) -> dict:
    """Each true pickup line: reported among the sensor's position lines, and within 1 % of its frequency?
    errors: relative frequency error of the nearest reported line (None when none is within 5 %: missed)."""
    rep = [l.frequency_hz for l in diag.sensor.lines if l.channel == "position_m"]
    errs = []
    for f in true_hz:
        near = min((abs(r - f) / f for r in rep), default=None)
        errs.append(near if near is not None and near <= LINE_FOUND else None)
    missed = [{"frequency_hz": f, "amplitude_m": a} for f, a, e in zip(true_hz, true_m or [None] * len(true_hz), errs)
              if e is None]
    return {"true_hz": list(true_hz), "reported_hz": rep, "errors": errs, "n": len(true_hz),
            "found": sum(e is not None for e in errs), "within": sum(e is not None and e <= 0.01 for e in errs),
            "missed": missed}


def grade(name: str, truth: dict, diag, *, true_linear: dict | None = None, elapsed_s: float = 0.0,
          cpu_s: float | None = None, noise_m: float | None = None, pickup_hz: list[float] | None = None,
          pickup_m: list[float] | None = None, habits: list[str] | None = None, duration_s: float | None = None,
          fs_hz: float | None = None) -> dict:
    """One row of the proof table from the true effects (answers.json style) and a Diagnosis."""
    named = {e.name: dict(e.parameters) for e in diag.effects}
    errors = {}
    for eff, prm in truth.items():
        if eff not in named:
            continue
        for key, true_v in prm.items():
            est = named[eff].get(key)
            if est is None or not isinstance(true_v, (int, float)) or true_v == 0:
                continue
            errors[f"{eff}.{key}"] = abs(float(est) - float(true_v)) / abs(float(true_v))
    lin_err = None
    if true_linear and diag.params_refit:
        errs = [abs(float(diag.params_refit[k]) - v) / abs(v) for k, v in true_linear.items()
                if k in diag.params_refit and v]
        lin_err = max(errs) if errs else None
    aug_rms = _fit_figure(diag, "augmented", "residual_rms_m")
    return {
        "case": name,
        "habits": list(habits or []),
        "truth": sorted(truth),
        "named": sorted(named),
        "right": set(truth) == set(named),
        "truth_parameters": truth,
        "named_parameters": named,
        "parameter_errors": errors,
        "linear_max_error": lin_err,
        "groups": [list(g) for g in diag.groups],
        "nrmse": {m: _fit_figure(diag, m, "nrmse") for m in MODELS},
        "residual_over_noise": {m: _fit_figure(diag, m, "residual_over_noise") for m in MODELS},
        "true_noise_m": noise_m,
        "residual_over_true_noise": (aug_rms / noise_m) if (aug_rms is not None and noise_m) else None,
        "holdout_nrmse": {m: _fit_figure(diag, m, "nrmse_holdout") for m in MODELS},
        "pickup_lines": _line_grades(pickup_hz or [], diag, pickup_m),
        "verdict": diag.verdict.status,
        "elapsed_s": elapsed_s,
        "cpu_s": cpu_s,
        "duration_s": duration_s,
        "fs_hz": fs_hz,
        "summary": report.summary(diag),
    }


def confusion(rows: list[dict]) -> dict[str, dict[str, int]]:
    """Effect-level confusion, rows = truth, columns = named, "none" = no effect.

    A true effect that was named counts on the diagonal. A missed effect counts against each wrongly named
    effect of the same case (mistaken for it), or against "none" if nothing wrong was named. A wrongly named
    effect with no missed effect to explain it counts in row "none" (invented). A clean case named clean is
    (none, none).
    """
    seen = {x for r in rows for x in list(r["truth"]) + list(r["named"])}
    labels = list(CATALOGUE) + sorted(seen - set(CATALOGUE)) + [NONE]     # another plant's catalogue names too
    m = {a: {b: 0 for b in labels} for a in labels}
    for r in rows:
        truth, named = set(r["truth"]), set(r["named"])
        if not truth and not named:
            m[NONE][NONE] += 1
        missed, invented = truth - named, named - truth
        for t in truth & named:
            m[t][t] += 1
        for t in missed:
            for x in (invented or {NONE}):
                m[t][x] += 1
        if not missed:
            for x in invented:
                m[NONE][x] += 1
    return m


def _resid(r: dict) -> float | None:
    """Augmented residual over the noise: the true noise when the case knows it, else the engine's estimate."""
    v = r.get("residual_over_true_noise")
    return v if v is not None else r["residual_over_noise"]["augmented"]


def score(rows: list[dict]) -> dict:
    """Overall figures of the proof against the issues' targets."""
    n = len(rows)
    right = sum(r["right"] for r in rows)
    clean = [r for r in rows if not r["truth"]]
    invented_clean = sum(1 for r in clean if r["named"])
    def within(suffix, tol):
        errs = [e for r in rows for k, e in r["parameter_errors"].items() if k.endswith(suffix)]
        return {"n": len(errs), "within": sum(e <= tol for e in errs), "tolerance": tol,
                "worst": max(errs) if errs else None}
    ron = [_resid(r) for r in rows if _resid(r) is not None]
    times = [r["elapsed_s"] for r in rows]
    at2k = [r for r in rows if (r.get("duration_s") or 0) >= 50.0 and r.get("fs_hz") == 2000.0]
    per100 = [r["elapsed_s"] * 100.0 / r["duration_s"] for r in at2k]     # the issue's budget: 100 s at 2 kHz
    cpu100 = [r["cpu_s"] * 100.0 / r["duration_s"] for r in at2k if r.get("cpu_s") is not None]
    with_habits = [r for r in rows if r.get("habits")]
    lines = [r.get("pickup_lines") or {"n": 0, "within": 0, "errors": []} for r in rows]
    line_errs = [e for g in lines for e in g["errors"] if e is not None]
    out = {
        "cases": n, "right": right, "fraction_right": right / n if n else 0.0,
        "clean_cases": len(clean), "invented_on_clean": invented_clean,
        "delays": within(".delay_s", TARGETS["delay_s"]),
        "frequencies": within(".frequency_hz", TARGETS["frequency_hz"]),
        "residual_within_1.3_noise": {"n": len(ron), "within": sum(v <= 1.3 for v in ron),
                                      "worst": max(ron) if ron else None},
        "seconds_per_case": {"mean": float(np.mean(times)) if times else None,
                             "median": float(np.median(times)) if times else None,
                             "max": float(np.max(times)) if times else None},
        "seconds_per_100s_at_2khz": {"median": float(np.median(per100)) if per100 else None,
                                     "max": float(np.max(per100)) if per100 else None,
                                     "n": len(per100),
                                     "cpu_median": float(np.median(cpu100)) if cpu100 else None,
                                     "cpu_max": float(np.max(cpu100)) if cpu100 else None,
                                     "note": "cases at 2 kHz of 50 s or more, wall and CPU time scaled to 100 s"},
    }
    if with_habits:
        out["habit_cases"] = len(with_habits)
        out["sensor_named_as_physics"] = sum(1 for r in with_habits if set(r["named"]) - set(r["truth"]))
        out["mains_lines"] = {"n": sum(g["n"] for g in lines), "found": sum(g.get("found", 0) for g in lines),
                              "within_1pct": sum(g["within"] for g in lines),
                              "worst": max(line_errs) if line_errs else None,
                              "missed": [{"case": r["case"], **m} for r in rows
                                         for m in (r.get("pickup_lines") or {}).get("missed", [])]}
        out["by_habit"] = by_habit(rows)
    return out


def _habit_key(tag: str) -> str:
    return tag.split(":")[0] if tag.startswith(("pickup", "drift")) else tag


def by_habit(rows: list[dict]) -> dict[str, dict]:
    """Per habit tag: cases, named right, invented effects, residual within 1.3 x the true noise."""
    out: dict[str, dict] = {}
    for r in rows:
        for tag in r.get("habits") or []:
            for key in {tag, _habit_key(tag)}:
                d = out.setdefault(key, {"cases": 0, "right": 0, "invented": 0, "residual_ok": 0})
                d["cases"] += 1
                d["right"] += int(r["right"])
                d["invented"] += int(bool(set(r["named"]) - set(r["truth"])))
                v = _resid(r)
                d["residual_ok"] += int(v is not None and v <= 1.3)
    return dict(sorted(out.items()))


# ---- running -----------------------------------------------------------------------------------------
def _p0_from(p0_dict: dict) -> ActuatorParams:
    return ActuatorParams(**p0_dict)


def _run_generated(case: Case, p0_dict: dict, seed: int) -> dict:
    p0 = _p0_from(p0_dict)
    rec = simulate_case(case, p0)
    t0, c0 = time.perf_counter(), time.process_time()
    diag = diagnose(rec, p0, seed=seed)
    return grade(case.name, case.effects, diag, true_linear=case.linear, elapsed_s=time.perf_counter() - t0,
                 cpu_s=time.process_time() - c0, noise_m=case.noise_m(), pickup_hz=case.pickup_lines_hz(),
                 pickup_m=case.pickup_lines_m(), habits=case.habits, duration_s=rec.duration_s, fs_hz=rec.fs_hz)


def _run_file(path: str, truth: dict, true_linear: dict | None, p0_dict: dict, seed: int,
              noise_m: float | None = None) -> dict:
    rec = load_recording(path)
    t0, c0 = time.perf_counter(), time.process_time()
    diag = diagnose(rec, _p0_from(p0_dict), seed=seed)
    return grade(Path(path).name, truth, diag, true_linear=true_linear, elapsed_s=time.perf_counter() - t0,
                 cpu_s=time.process_time() - c0, noise_m=noise_m, duration_s=rec.duration_s, fs_hz=rec.fs_hz)


def read_answers(cases_dir: Path) -> list[tuple[Path, dict, dict | None, float | None]]:
    """(recording path, true effects, true linear parameters, position noise rms) from a folder with
    answers.json."""
    ans_path = cases_dir / "answers.json"
    if not cases_dir.is_dir():
        raise RigError(f"--cases {cases_dir}: not a folder")
    if not ans_path.is_file():
        raise RigError(f"--cases {cases_dir}: no answers.json in the folder (expected "
                       "{\"recording file\": {\"effects\": {...}, \"true_linear_parameters\": {...}}})")
    try:
        answers = json.loads(ans_path.read_text())
    except (OSError, ValueError) as e:
        raise RigError(f"{ans_path}: not readable JSON ({e})") from None
    if not isinstance(answers, dict) or not answers:
        raise RigError(f"{ans_path}: expected an object {{recording file: {{\"effects\": ...}}}}")
    out = []
    for fname, entry in sorted(answers.items()):
        if not isinstance(entry, dict) or not isinstance(entry.get("effects"), dict):
            raise RigError(f"{ans_path}: entry {fname!r} needs an \"effects\" object")
        unknown = set(entry["effects"]) - set(CATALOGUE)
        if unknown:
            raise RigError(f"{ans_path}: entry {fname!r} has unknown effect(s) {', '.join(sorted(unknown))} "
                           f"(known: {', '.join(CATALOGUE)})")
        path = cases_dir / fname
        if not path.is_file():
            raise RigError(f"{ans_path}: recording {fname!r} listed but not found in {cases_dir}")
        out.append((path, entry["effects"], entry.get("true_linear_parameters"), entry.get("position_noise_m_rms")))
    return out


def _pool(workers: int):
    # spawn: no forked numba/BLAS thread state; one BLAS thread per worker so 2 workers fit 2 cores
    return ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"))


def run_jobs(jobs: list[tuple[Callable, tuple, str]], workers: int,
             progress: Callable[[int, int, str], None] | None = None) -> list[dict]:
    """Run (fn, args, label) jobs over `workers` processes; rows come back in job order."""
    rows: list[dict | None] = [None] * len(jobs)
    if workers <= 1 or len(jobs) == 1:
        for i, (fn, args, label) in enumerate(jobs):
            rows[i] = fn(*args)
            if progress:
                progress(i + 1, len(jobs), label)
        return rows  # type: ignore[return-value]
    saved = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                             "NUMBA_NUM_THREADS")}
    os.environ.update({k: "1" for k in saved})
    try:
        with _pool(workers) as ex:
            futs = {ex.submit(fn, *args): (i, label) for i, (fn, args, label) in enumerate(jobs)}
            done = 0
            for fut in as_completed(futs):
                i, label = futs[fut]
                rows[i] = fut.result()
                done += 1
                if progress:
                    progress(done, len(jobs), label)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return rows  # type: ignore[return-value]


def prove_generated(n: int, seed: int, p0: ActuatorParams, *, duration_s: float = 100.0, workers: int = 2,
                    progress=None, habits: bool = False) -> tuple[list[Case], list[dict]]:
    cases = draw_cases(n, seed, duration_s=duration_s, p0=p0, habits=habits)
    jobs = [(_run_generated, (c, p0.as_dict(), seed), c.name) for c in cases]
    return cases, run_jobs(jobs, workers, progress)


def prove_folder(cases_dir: Path, p0: ActuatorParams, *, seed: int = 0, workers: int = 2,
                 progress=None) -> list[dict]:
    entries = read_answers(Path(cases_dir))
    jobs = [(_run_file, (str(path), truth, lin, p0.as_dict(), seed, noise), path.name)
            for path, truth, lin, noise in entries]
    return run_jobs(jobs, workers, progress)


# ---- presentation ------------------------------------------------------------------------------------
def _names(xs: list[str]) -> str:
    return " + ".join(xs) if xs else NONE


def _fmt(v, spec=".3f") -> str:
    return "-" if v is None else format(v, spec)


def _short_key(k: str) -> str:
    eff, key = k.split(".", 1)
    short = catalogue.short(eff)
    return f"{short}.{key.replace('_hz', '').replace('_s', '').replace('_ma', '').replace('_n', '')}"


def _habits_cell(r: dict) -> str:
    return ", ".join(r.get("habits") or []) or "-"


def table_markdown(rows: list[dict]) -> str:
    head = ("| case | habits | truth | named | ok | parameter errors | NRMSE nominal -> refit -> augmented "
            "| resid/noise aug | s |\n|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        errs = ", ".join(f"{_short_key(k)} {100 * e:.1f}%" for k, e in sorted(r["parameter_errors"].items())) or "-"
        nr = r["nrmse"]
        lines.append(f"| {r['case']} | {_habits_cell(r)} | {_names(r['truth'])} | {_names(r['named'])} | "
                     f"{'yes' if r['right'] else 'NO'} | {errs} | {_fmt(nr['nominal'])} -> {_fmt(nr['refit'])} -> "
                     f"{_fmt(nr['augmented'])} | {_fmt(_resid(r), '.2f')} | "
                     f"{r['elapsed_s']:.1f} |")
    return head + "\n".join(lines) + "\n"


def habits_markdown(s: dict) -> str:
    """The summary by habit: how the diagnosis fared on the cases that carried each habit."""
    bh = s.get("by_habit") or {}
    if not bh:
        return ""
    head = "| habit | cases | named right | invented effect | residual <= 1.3 x noise |\n|---|---|---|---|---|\n"
    return head + "\n".join(f"| {k} | {v['cases']} | {v['right']} | {v['invented']} | {v['residual_ok']} |"
                             for k, v in bh.items()) + "\n"


def confusion_markdown(m: dict[str, dict[str, int]]) -> str:
    labels = list(m)
    head = "| truth \\ named | " + " | ".join(labels) + " |\n|---|" + "---|" * len(labels) + "\n"
    body = "\n".join(f"| {a} | " + " | ".join(str(m[a][b]) if m[a][b] else "." for b in labels) + " |"
                     for a in labels)
    return head + body + "\n"


def score_text(s: dict) -> str:
    d, f, r = s["delays"], s["frequencies"], s["residual_within_1.3_noise"]
    sp, sp100 = s["seconds_per_case"], s.get("seconds_per_100s_at_2khz") or {}
    out = [
        f"score: {s['right']}/{s['cases']} named right ({100 * s['fraction_right']:.0f} %, target 95 %); "
        f"invented on clean cases: {s['invented_on_clean']}/{s['clean_cases']} (target 0)",
        f"delays within 20 %: {d['within']}/{d['n']} (worst {_fmt(d['worst'] and 100 * d['worst'], '.1f')} %); "
        f"frequencies within 5 %: {f['within']}/{f['n']} (worst {_fmt(f['worst'] and 100 * f['worst'], '.1f')} %)",
        f"augmented residual <= 1.3 x noise: {r['within']}/{r['n']} (worst {_fmt(r['worst'], '.2f')}); "
        f"diagnosis time per case: median {_fmt(sp.get('median'), '.1f')} s, mean {_fmt(sp['mean'], '.1f')} s, "
        f"max {_fmt(sp['max'], '.1f')} s" + (f"; per 100 s at 2 kHz ({sp100['n']} cases): median "
                                            f"{_fmt(sp100.get('median'), '.1f')} s, max {_fmt(sp100.get('max'), '.1f')} s "
                                            f"wall, CPU median {_fmt(sp100.get('cpu_median'), '.1f')} s, max "
                                            f"{_fmt(sp100.get('cpu_max'), '.1f')} s" if sp100.get("n") else ""),
    ]
    if "habit_cases" in s:
        ml = s["mains_lines"]
        missed = "; ".join(f"{m['case']} {m['frequency_hz']:.2f} Hz"
                           + (f" ({m['amplitude_m'] * 1e9:.2g} nm)" if m.get("amplitude_m") else "")
                           for m in ml.get("missed", []))
        out.append(f"habits in {s['habit_cases']} cases: sensor artefact named as physics in "
                   f"{s['sensor_named_as_physics']} (target 0); pickup lines found {ml.get('found', ml['n'])}/"
                   f"{ml['n']}, reported within 1 % of their frequency: {ml['within_1pct']}/{ml.get('found', ml['n'])}"
                   f" (worst {_fmt(ml['worst'] and 100 * ml['worst'], '.2f')} %)"
                   + (f"; missed: {missed}" if missed else ""))
    return "\n".join(out)


def report_markdown(rows: list[dict], title: str) -> str:
    s = score(rows)
    hab = habits_markdown(s)
    return (f"# {title}\n\n{table_markdown(rows)}\n## Confusion matrix (effects)\n\n"
            f"{confusion_markdown(confusion(rows))}\n" + (f"## By habit\n\n{hab}\n" if hab else "")
            + "## Score\n\n" + score_text(s).replace("\n", "\n\n") + "\n")


def report_json(rows: list[dict], title: str, cases: list[Case] | None = None) -> dict:
    out = {"title": title, "rows": rows, "confusion": confusion(rows), "score": score(rows)}
    if cases is not None:
        out["cases"] = [asdict(c) for c in cases]
    return out

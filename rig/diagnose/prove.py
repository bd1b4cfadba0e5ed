"""Blind proof of the diagnosis (issue 7): make recordings that hide known effects, diagnose them, grade.

Cases are drawn from a seed: the paper's Table 1 model with its six identified parameters moved +-15 %, zero,
one or two effects from the catalogue (rig/diagnose/catalogue/: each effect's "stand" draw) with physically
plausible parameters,
and the recordings' sensor noise. They are simulated with sim_backend.actuator.simulate_stand (the physics that
matches the reference recordings), diagnosed without the truth, and graded (rig/diagnose/grading.py).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from rig import excitation as ex
from rig.batch import pool
from rig.diagnose import catalogue
from rig.diagnose.grading import grade
from rig.diagnose.engine import diagnose
from rig.errors import RigError
from rig.recordings.recording import Recording
from rig.recordings.rigformat import load_recording
from sim_backend.actuator import linear_chirp, simulate_stand
from sim_backend.linear import IDENTIFIED, ActuatorParams
from sim_backend.sensors import Line, SensorHabits

CATALOGUE = catalogue.for_proof("stand")      # the effects drawn, in the draws' order
POSITION_NOISE_M = 2e-8          # rms, as the shared recordings (README)
ACCEL_NOISE_MPS2 = 2e-4
LINEAR_SPREAD = 0.15             # six identified parameters moved by up to +-15 %


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
@dataclass(frozen=True)
class DrawContext:
    """What an effect's draw for this proof knows (rig/diagnose/catalogue: Draw): the case's actuator, the
    command's peak, the position noise and the effects drawn before it (with their simulator-only extras)."""
    p: ActuatorParams
    amplitude_V: float
    position_noise_m: float
    drawn: dict


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


def run_jobs(jobs: list[tuple[Callable, tuple, str]], workers: int,
             progress: Callable[[int, int, str], None] | None = None, *, scheduler: str | None = None) -> list[dict]:
    """Run (fn, args, label) jobs over `workers` local processes, or on the Dask cluster of `scheduler`
    (rig.batch.pool); rows come back in job order. A job that raised stops the proof with its exception."""
    rows: list[dict | None] = [None] * len(jobs)
    tasks = [(fn, args) for fn, args, _ in jobs]
    for done, (i, out) in enumerate(pool.run_tasks(tasks, workers=workers, scheduler=scheduler), 1):
        if isinstance(out, BaseException):
            raise out
        rows[i] = out
        if progress:
            progress(done, len(jobs), jobs[i][2])
    return rows  # type: ignore[return-value]


def prove_generated(n: int, seed: int, p0: ActuatorParams, *, duration_s: float = 100.0, workers: int = 2,
                    progress=None, habits: bool = False, scheduler: str | None = None) -> tuple[list[Case], list[dict]]:
    cases = draw_cases(n, seed, duration_s=duration_s, p0=p0, habits=habits)
    jobs = [(_run_generated, (c, p0.as_dict(), seed), c.name) for c in cases]
    return cases, run_jobs(jobs, workers, progress, scheduler=scheduler)


def prove_folder(cases_dir: Path, p0: ActuatorParams, *, seed: int = 0, workers: int = 2,
                 progress=None, scheduler: str | None = None) -> list[dict]:
    entries = read_answers(Path(cases_dir))
    jobs = [(_run_file, (str(path), truth, lin, p0.as_dict(), seed, noise), path.name)
            for path, truth, lin, noise in entries]
    return run_jobs(jobs, workers, progress, scheduler=scheduler)

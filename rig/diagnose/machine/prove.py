"""The blind proof on the four-mount rig (`rig prove --rig`): closed-loop runs of the simulated rig hide zero, one
or two machine-level effects; each run is recorded as `rig run --record` records it, diagnosed without the truth,
and graded.

A case (drawn from the seed): the isolation mode of the run (off, feedback, feedback + floor feedforward), floor
accelerometers fitted or not, the floor's level and realisation, the four actuators' common parameters off the
model by up to 8 % ([plant_error]: what a refit absorbs), and the effects with sizes a physical rig would show and
its run can tell (effects.DRAWS). Graded as the axis proofs are: right = the named set is the true set, each
effect at the right mode, mount or sensor (a mode's frequency within FREQ_TOL); clean cases must name nothing.
The runs themselves are rig/commands/prove_rig.py's (they need the runtime's session, a layer above).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rig.config import MOUNTS, Config
from rig.diagnose.machine import effects as fx
from rig.errors import RigError
from sim_backend.machine import modal_model_from_config
from sim_backend.rig_plant import rig_state_space

MODES = ("off", "feedback", "feedback_feedforward")
FREQ_TOL = 0.03                 # issue 28: frequencies within 3 %
ACT_SPREAD = 0.08               # the actuators' common parameters off the model by up to this
NONE = "none"


@dataclass
class RigCase:
    name: str
    effects: dict               # {effect: {"location": ..., parameters}}
    mode: str
    floor_sensors: bool
    duration_s: float
    floor_rms_m: float
    floor_seed: int
    plant_error: dict
    rig_error: dict = field(default_factory=dict)
    rocking: dict = field(default_factory=dict)
    tags: list = field(default_factory=list)

    def truth(self) -> set[tuple[str, str]]:
        return {(k, v["location"]) for k, v in self.effects.items()}

    def sections(self) -> dict:
        """The simulated rig's config (TOML sections): what it really is."""
        vib = {"rms_m": self.floor_rms_m, "seed": self.floor_seed}
        if self.rocking:
            vib["rocking_rms_m"] = self.rocking["rocking_over_floor"] * self.floor_rms_m
            vib["rocking_axis"] = self.rocking["rocking_axis"]
        out = {"sensors": {"floor_accel": self.floor_sensors}, "vibration": vib, "plant_error": dict(self.plant_error)}
        if self.rig_error:
            out["rig_error"] = dict(self.rig_error)
        return out

    def model_sections(self) -> dict:
        """The config the user diagnoses with: the model, with the run's sensors and floor (no errors)."""
        return {"sensors": {"floor_accel": self.floor_sensors}}


@dataclass
class _Conditions:
    """What a drawn effect needs to know of its run (effects.DRAWS)."""
    modal: object
    mode: str
    floor_sensors: bool
    coupled_hz: list


def coupled_modes_hz(cfg: Config) -> list[float]:
    """The rig's coupled flexible modes below 200 Hz (the machine on its four actuators)."""
    ev = np.linalg.eigvals(rig_state_space(cfg).A)
    f = np.abs(ev.imag) / (2 * math.pi)
    return sorted({round(float(x), 2) for x in f[(f > 1.0) & (f < 200.0) & (np.abs(ev.real) < 30)]})


def _merge(dst: dict, src: dict) -> None:
    """[rig_error] keys of two effects in one case: per-mount lists combined (one effect per mount each)."""
    for k, v in src.items():
        if k in dst and isinstance(v, list):
            dst[k] = [b if b not in (0.0, 1.0) else a for a, b in zip(dst[k], v)]
        else:
            dst[k] = v


def _kinds(cond: _Conditions) -> list[str]:
    return [name for name, (_, tells) in fx.DRAWS.items() if tells(cond)]


def draw_cases(n: int, seed: int, *, duration_s: float = 60.0, cfg: Config | None = None) -> list[RigCase]:
    """n blind cases from seed: a quarter clean (at least one), about 30 % with two effects, the rest one; the
    effects cycled so every kind appears."""
    if n < 1:
        raise RigError(f"--n: expected at least 1 case, got {n}")
    cfg = cfg or Config()
    modal = modal_model_from_config(cfg)
    coupled = coupled_modes_hz(cfg)
    rng = np.random.default_rng(seed)
    n0 = max(1, math.ceil(0.25 * n)) if n > 1 else 0
    n2 = round(0.3 * n) if n > 2 else 0
    counts = [0] * n0 + [2] * n2 + [1] * (n - n0 - n2)
    rng.shuffle(counts)
    order = [str(x) for x in rng.permutation(list(fx.DRAWS))]
    cases, used = [], 0
    for i, k in enumerate(counts):
        mode = str(rng.choice(MODES, p=(0.3, 0.35, 0.35)))
        floor = True if mode == "feedback_feedforward" else bool(rng.random() < 0.5)
        cond = _Conditions(modal, mode, floor, coupled)
        kinds = _kinds(cond)
        names: list[str] = []
        while len(names) < k:
            cand = order[used % len(order)]
            used += 1
            if cand in kinds and cand not in names:
                names.append(cand)
        effects, rig_error, rocking, locations = {}, {}, {}, set()
        for name in names:
            for _ in range(50):
                loc, truth, keys, vib = fx.DRAWS[name][0](rng, cond)
                if loc not in locations or fx.BY_NAME[name].shared_place:
                    break
            locations.add(loc)
            effects[str(name)] = {"location": loc, **{k: (float(v) if isinstance(v, np.floating) else v)
                                                      for k, v in truth.items()}}
            _merge(rig_error, keys)
            rocking.update(vib)
        pe = {key: round(float(rng.uniform(1 - ACT_SPREAD, 1 + ACT_SPREAD)), 4)
              for key in ("K_L", "K_Q", "K_C", "w_nv", "zeta")}
        tag = "+".join(effects) or "clean"
        cases.append(RigCase(f"r{i + 1:02d}_{tag}", effects, mode, floor, float(duration_s),
                             round(float(rng.uniform(2e-6, 5e-6)), 9), int(rng.integers(2 ** 31)), pe, rig_error,
                             rocking, [mode, "floor" if floor else "no-floor"]))
    return cases


def grade(case: RigCase, diag, *, elapsed_s: float, cpu_s: float) -> dict:
    """One row of the proof table: the named set against the truth, frequency errors, the fit per mount."""
    named = {(e.name, e.location) for e in diag.effects}
    truth = case.truth()
    errors = {}
    for e in diag.effects:
        t = case.effects.get(e.name)
        if t and t["location"] == e.location and "frequency_hz" in t and "frequency_hz" in e.parameters:
            errors[f"{e.name}.frequency_hz"] = abs(e.parameters["frequency_hz"] - t["frequency_hz"]) / t["frequency_hz"]
    wrong_place = sorted(f"{n} at {loc}" for n, loc in named - truth if n in {k for k, _ in truth})
    fit = diag.fit
    return {
        "case": case.name, "mode": case.mode, "floor": case.floor_sensors, "duration_s": case.duration_s,
        "truth": sorted(f"{n}[{loc}]" for n, loc in truth), "named": sorted(f"{n}[{loc}]" for n, loc in named),
        "right": named == truth, "wrong_place": wrong_place, "frequency_errors": errors,
        "truth_parameters": case.effects,
        "named_parameters": {f"{e.name}[{e.location}]": e.parameters for e in diag.effects},
        "fit_worst_mount": {k: max(max(v.values()) for v in fit[k].values()) for k in fit},
        "verdict": diag.verdict, "elapsed_s": elapsed_s, "cpu_s": cpu_s,
        "seconds_per_60s": elapsed_s * 60.0 / case.duration_s, "summary": diag.summary,
    }


def score(rows: list[dict]) -> dict:
    n = len(rows)
    clean = [r for r in rows if not r["truth"]]
    errs = [e for r in rows for e in r["frequency_errors"].values()]
    named_cases = [r for r in rows if r["truth"] and r["named"]]
    place = sum(1 for r in rows for t in r["truth"] if t in r["named"])
    n_true = sum(len(r["truth"]) for r in rows)
    t60 = [r["seconds_per_60s"] for r in rows]
    return {"cases": n, "right": sum(r["right"] for r in rows), "fraction_right": sum(r["right"] for r in rows) / n,
            "clean_cases": len(clean), "invented_on_clean": sum(1 for r in clean if r["named"]),
            "true_effects": n_true, "found_at_the_right_place": place,
            "named_at_a_wrong_place": sum(len(r["wrong_place"]) for r in rows),
            "frequencies": {"n": len(errs), "within": sum(e <= FREQ_TOL for e in errs), "tolerance": FREQ_TOL,
                            "worst": max(errs) if errs else None},
            "seconds_per_60s": {"median": float(np.median(t60)) if t60 else None,
                                "max": float(np.max(t60)) if t60 else None},
            "cases_with_effects_named": len(named_cases)}


def table_markdown(rows: list[dict]) -> str:
    head = ("| case | run | truth | named | ok | frequency error | worst mount resid. model -> diagnosed | s |\n"
            "|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        fe = ", ".join(f"{100 * v:.2f} %" for v in r["frequency_errors"].values()) or "-"
        fw = r["fit_worst_mount"]
        lines.append(f"| {r['case']} | {r['mode']}, {'floor' if r['floor'] else 'no floor'} | "
                     f"{' + '.join(r['truth']) or NONE} | {' + '.join(r['named']) or NONE} | "
                     f"{'yes' if r['right'] else 'NO'} | {fe} | {fw['nominal']:.2f} -> {fw['augmented']:.2f} | "
                     f"{r['elapsed_s']:.0f} |")
    return head + "\n".join(lines) + "\n"


def confusion(rows: list[dict]) -> dict:
    """Effect kinds: truth rows, named columns ("none": nothing); a wrong place counts off the diagonal."""
    labels = [e.name for e in fx.CATALOGUE] + [NONE]
    m = {a: {b: 0 for b in labels} for a in labels}
    for r in rows:
        truth = set(r["truth"])
        named = set(r["named"])
        if not truth and not named:
            m[NONE][NONE] += 1
        for t in truth & named:
            k = t.split("[")[0]
            m[k][k] += 1
        missed, invented = truth - named, named - truth
        for t in missed:
            for x in (invented or {NONE}):
                m[t.split("[")[0]][x.split("[")[0] if x != NONE else NONE] += 1
        if not missed:
            for x in invented:
                m[NONE][x.split("[")[0]] += 1
    return m


def confusion_markdown(m: dict) -> str:
    labels = [a for a in m if any(m[a].values()) or any(m[b][a] for b in m)]
    head = "| truth \\ named | " + " | ".join(labels) + " |\n|---|" + "---|" * len(labels) + "\n"
    return head + "\n".join(f"| {a} | " + " | ".join(str(m[a][b]) if m[a][b] else "." for b in labels) + " |"
                            for a in labels) + "\n"


def score_text(s: dict) -> str:
    f = s["frequencies"]
    t = s["seconds_per_60s"]
    worst = "-" if f["worst"] is None else f"{100 * f['worst']:.2f} %"
    return (f"score: {s['right']}/{s['cases']} named right ({100 * s['fraction_right']:.0f} %, target 90 %); invented "
            f"on clean runs: {s['invented_on_clean']}/{s['clean_cases']} (target 0); true effects found at the right "
            f"mode, mount or sensor: {s['found_at_the_right_place']}/{s['true_effects']}, named at a wrong one: "
            f"{s['named_at_a_wrong_place']}; frequencies within {100 * f['tolerance']:.0f} %: {f['within']}/{f['n']} "
            f"(worst {worst}); diagnosis time per 60 s of recording: median {t['median']:.1f} s, max {t['max']:.1f} s")


def report_markdown(rows: list[dict], title: str) -> str:
    s = score(rows)
    return (f"# {title}\n\n{table_markdown(rows)}\n## Confusion matrix (effects)\n\n"
            f"{confusion_markdown(confusion(rows))}\n## Score\n\n{score_text(s)}\n")


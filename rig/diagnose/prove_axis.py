"""Blind proof of the diagnosis on a plant file's mechanical axis (`rig prove --plant FILE`): cases drawn on that
plant, recorded by sim_backend.axis (real stick-slip friction, the drive's cascade in closed loop, an encoder),
diagnosed without the truth, graded as rig.diagnose.prove grades the actuator's cases.

Each case: the plant's free parameters moved +-15 % within their bounds; none, one or two of the effects with an
"axis" draw in the catalogue (rig/diagnose/catalogue/) with plausible sizes relative to the drive's force; open loop (band-limited noise command) or closed loop (back-and-forth moves under
a P-PI cascade tuned on the nominal plant, its reference starting at the encoder's reading); the encoder's step,
white noise and an offset; 20-30 s at 1 kHz.
In closed loop a saturation is drawn as 40-90 % of the peak command the same run asks for without it, and the
controller's output is clipped at 1.5 x that peak (its converter's range): a saturation the loop survives.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from rig import excitation as ex
from rig.diagnose import catalogue
from rig.diagnose.engine import diagnose
from rig.diagnose.grading import grade
from rig.diagnose.prove import Case, run_jobs
from rig.errors import RigError
from rig.plant.file import parse_plant
from rig.plant.model import Plant
from rig.recordings.recording import Recording
from sim_backend.axis import Axis, Loop, Sensor, simulate_axis, trapezoid_program

AXIS_CATALOGUE = catalogue.for_proof("axis")      # the effects drawn, in the draws' order
FS_HZ = 1000.0
ACCEL_TYP_MPS2 = 1.0           # the open-loop command's size: a force that accelerates the mass by ~1 m/s^2 ...
SPEED_TYP_MPS = 0.1            # ... or holds ~0.1 m/s against the damping, whichever is larger


def _scale(plant: Plant, v: dict) -> tuple[float, float]:
    """(peak command of the open-loop cases, the drive's force per command unit)."""
    g = v["gain_n_per_unit"]
    F = max(v["mass_kg"] * ACCEL_TYP_MPS2, v["damping_n_s_per_m"] * SPEED_TYP_MPS)
    return F / g, g


@dataclass(frozen=True)
class DrawContext:
    """What an effect's draw for this proof knows (rig/diagnose/catalogue: Draw): the plant's input unit, the
    open-loop command's peak and the drive's peak force."""
    u: str
    u_peak: float
    F_peak: float


def _names(names: list[str]) -> list[str]:
    """Effects drawn together with one they are not drawn with give way to their `instead`; an effect that needs
    another (its `with_`) brings it."""
    for n in list(names):
        d = catalogue.get(n).draws["axis"]
        if n in names and any(o in names for o in d.not_with):
            names = [x for x in names if x != n] + [d.instead] * (d.instead not in names)
    for n in list(names):
        names += [w for w in catalogue.get(n).draws["axis"].with_ if w not in names]
    return names


def draw_axis_cases(n: int, seed: int, plant: Plant) -> list[Case]:
    """n blind cases on the plant: >= 25 % clean, the rest one or two effects (each effect appears)."""
    if plant.family != "mechanical_axis":
        raise RigError(f"{plant.source}: rig prove --plant makes its cases on a mechanical_axis plant (this one is "
                       f"{plant.family}; an eha plant file is proven by rig prove --config)")
    if n < 1:
        raise RigError(f"--n: expected at least 1 case, got {n}")
    rng = np.random.default_rng(seed)
    n0 = max(1, math.ceil(0.25 * n)) if n > 1 else 0
    n2 = round(0.3 * n) if n > 2 else 0
    counts = [0] * n0 + [1] * (n - n0 - n2) + [2] * n2
    rng.shuffle(counts)
    singles = list(rng.permutation(AXIS_CATALOGUE))
    cases = []
    for i, k in enumerate(counts):
        names = [str(singles[i % len(singles)])] if k == 1 else \
            [str(x) for x in rng.choice(AXIS_CATALOGUE, size=k, replace=False)] if k else []
        names = _names(names)
        lin = {}
        for key, p in plant.params.items():
            if p.free:
                lin[key] = float(np.clip(p.value * rng.uniform(0.85, 1.15), p.lo, p.hi))
        v = plant.values(**lin)
        u_peak, g = _scale(plant, v)
        closed = bool(rng.random() < 0.5)
        ctx = DrawContext(plant.input_unit, u_peak, u_peak * g)
        effects = {nm: catalogue.get(nm).draws["axis"].draw(rng, ctx)[0] for nm in sorted(names)}
        sensor = {"step_m": float(rng.choice([0.0, 1e-7, 5e-7])), "noise_m": float(rng.uniform(0.0, 5e-7)),
                  "offset_m": float(rng.uniform(-1e-3, 1e-3))}
        dur = round(float(rng.uniform(20.0, 30.0)), 1)
        exc = {"kind": "closed_loop" if closed else "band_noise", "seed": int(rng.integers(2 ** 31))}
        tags = [exc["kind"], "quantised" if sensor["step_m"] else "unquantised"]
        case = Case(name=f"a{i + 1:02d}_{'+'.join(effects) or 'nominal'}", effects=effects, linear=lin,
                    fs_hz=FS_HZ, duration_s=dur, amplitude_V=u_peak, seed=int(rng.integers(2 ** 31)),
                    excitation=exc, sensor=sensor, habits=tags)
        scaled = [nm for nm in effects if catalogue.get(nm).draws["axis"].loop_scaled]
        if closed and scaled:
            frac = np.random.default_rng([case.seed, 1]).uniform(*SATURATION_CLOSED_LOOP)  # the draws after it stay
            _closed_loop_saturation(case, plant, float(frac), scaled[0])
        cases.append(case)
    return cases


SATURATION_CLOSED_LOOP = (0.4, 0.9)     # the drive's limit as a fraction of the peak command the loop asks for
DAC_RANGE = 1.5                         # the controller's output range over that peak


def _closed_loop_saturation(case: Case, plant: Plant, fraction: float, name: str) -> None:
    """A saturation the loop survives, as on a real axis: the limit is a fraction of the peak command the same
    run asks for without it (the open-loop draw's scale says nothing of what the controller commands), and the
    controller's output is clipped at its converter's range (1.5 x that peak) instead of growing without bound
    while the drive is saturated."""
    free = replace(case, effects={k: v for k, v in case.effects.items() if k != name})
    peak = float(np.max(np.abs(simulate_axis_case(free, plant).valve_cmd_V)))
    case.effects[name] = {catalogue.get(name).keys(plant.input_unit)[0]: fraction * peak}
    case.excitation["u_max"] = DAC_RANGE * peak


def _loop_for(v: dict, u_max: float = math.inf) -> Loop:
    """A P-P cascade on the nominal plant: velocity loop at ~90 rad/s, position loop at half of it; its output
    clipped at u_max."""
    wv = 90.0
    return Loop(kp_per_s=0.5 * wv, kv=wv * v["mass_kg"] / v["gain_n_per_unit"], ki=0.0, u_max=min(u_max, 1e9))


def _moves(rng, duration_s: float) -> list[tuple[float, float]]:
    out, t = [], 0.0
    while t < duration_s:
        d = float(rng.uniform(0.02, 0.15)); vm = float(rng.uniform(0.02, 0.15))
        out += [(d, vm), (-d, vm)]
        t += 2 * (d / vm + vm / 0.8 + 0.3)
    return out


def simulate_axis_case(case: Case, plant: Plant) -> Recording:
    v = plant.values(**case.linear)
    ax = Axis(mass_kg=v["mass_kg"], damping_n_s_per_m=v["damping_n_s_per_m"],
              stiffness_n_per_m=v.get("stiffness_n_per_m", 0.0), gain_n_per_unit=v["gain_n_per_unit"],
              **catalogue.terms("axis", case.effects, plant.input_unit))
    sensor = Sensor(step_m=case.sensor["step_m"], noise_m=case.sensor["noise_m"], offset_m=case.sensor["offset_m"],
                    seed=case.seed)
    rng = np.random.default_rng(case.excitation["seed"])
    if case.excitation["kind"] == "closed_loop":
        # the reference starts where the encoder reads the carriage (its offset), as a drive's position loop is
        # enabled: no start-up kick (a kick of up to ~9 V from the offset had set the saturation draw's peak, so
        # the limit acted only in the start-up samples the diagnosis leaves out)
        ref = trapezoid_program(case.fs_hz, _moves(rng, case.duration_s), 0.8, 0.3,
                                start_m=case.sensor["offset_m"])[: int(case.duration_s * case.fs_hz)]
        nominal = plant.values()
        loop = _loop_for(nominal, case.excitation.get("u_max", math.inf))
        cmd, pos = simulate_axis(ax, case.fs_hz, reference=ref, loop=loop, sensor=sensor)
    else:
        cmd_in = ex.band_noise(case.fs_hz, case.duration_s, 0.3, 30.0, case.amplitude_V,
                               seed=case.excitation["seed"]).cmd_V
        cmd, pos = simulate_axis(ax, case.fs_hz, command=cmd_in, sensor=sensor)
    rec = Recording.from_signals(cmd, pos, None, fs_hz=case.fs_hz, source=case.name)
    rec.command_unit = plant.input_unit
    rec.accel_present = False
    return rec


def _run_axis_case(case: Case, plant_table: dict, source: str, seed: int) -> dict:
    plant = parse_plant(plant_table, source)
    rec = simulate_axis_case(case, plant)
    t0, c0 = time.perf_counter(), time.process_time()
    diag = diagnose(rec, plant, seed=seed)
    noise = math.sqrt(case.sensor["noise_m"] ** 2 + case.sensor["step_m"] ** 2 / 12.0)
    return grade(case.name, case.effects, diag, true_linear=case.linear, elapsed_s=time.perf_counter() - t0,
                 cpu_s=time.process_time() - c0, noise_m=noise or None, habits=case.habits,
                 duration_s=rec.duration_s, fs_hz=rec.fs_hz)


def plant_table(plant: Plant) -> dict:
    """The [plant] table that makes this plant again (the worker processes rebuild it)."""
    t = {"family": plant.family, "input_unit": plant.input_unit}
    for k, p in plant.params.items():
        t[k] = {"value": p.value, "min": p.lo, "max": p.hi} if p.free else p.value
    return t


def prove_plant(n: int, seed: int, plant: Plant, *, workers: int = 2, progress=None,
                scheduler: str | None = None) -> tuple[list[Case], list[dict]]:
    cases = draw_axis_cases(n, seed, plant)
    table = plant_table(plant)
    jobs = [(_run_axis_case, (c, table, plant.source, seed), c.name) for c in cases]
    return cases, run_jobs(jobs, workers, progress, scheduler=scheduler)


def cases_json(cases: list[Case]) -> list[dict]:
    return [asdict(c) for c in cases]

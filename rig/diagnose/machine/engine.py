"""The diagnosis of a run of the four-mount rig, stage by stage (issue 28).

  prepare    the record's DFTs at the bins of the band (spectra.py), the configured model (rigmodel.py)
  nominal    the replay of the recorded valve commands and floor through the configured model
  refit      the four actuators' common parameters, the machine's common damping and the command's latency
             (what an identification moves; not missing physics); then the weights: what the residual should be
             (weights.py)
  select     the catalogue's instances screened on a grid, the best fitted jointly with the refit, each tested
             (BIC on the fit bins, likelihood ratio on the held-out bins, its change to the replay above the
             model's fidelity); forward selection, at most two
  polish     the chosen effects and the refit together
Every stage is a function of the one before; the result is a Selection (the named instances with their tests and
the final parameters), reported by result.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rig.config import Config
from rig.diagnose.machine import effects as fx
from rig.diagnose.machine.fitting import FitResult, Slot, compare, fit, grid_search, put
from rig.diagnose.machine.residual import Evaluation, Replay
from rig.diagnose.machine.rigmodel import ACT_KEYS, Base, copy_theta, neutral
from rig.recordings.runfile import RunRecording
from rig.diagnose.machine.spectra import BANDS_HZ, Spectra, spectra_of
from rig.diagnose.machine.spool import Spools
from rig.diagnose.machine.weights import expected, inflated, inflation

MAX_EFFECTS = 2
FULL_FITS = 4                   # candidates fitted jointly with the refit after the screen
MAX_FITS = 2 * FULL_FITS        # with those refused below their least size (effects.Effect.least) fitted in place
EXPLAINED = 1.25                # held-out whitened residual power over what the right model leaves, in every
                                # channel and band (spectra.BANDS_HZ): below it nothing is left to explain
VALVES_DRIVEN_V = 0.05          # rms of the commands' part above 1 Hz: below it the valves are not excited
OVER_FIDELITY = 2.0             # an effect's change to the replay over the model's own error (residual.own_error:
                                # a floor held between samples or continuous): below twice it the change cannot
                                # be told from that error


PASSIVE_KEYS = ("K_L", "K_C")    # what the mounts show with the valves at null (their stiffness and its leak)
MODAL_ZETA = Slot("modal_zeta", 0, "log", 0.5, 2.0, prior=True)   # the modes' common damping: 0.015-0.06


def refit_slots(dt: float, valves_driven: bool = True) -> tuple[Slot, ...]:
    """The refit's slots: the actuators' common parameters (with the valves not driven only the passive ones;
    the valve's and the latency are then not seen), the modes' common damping, the commands' latency."""
    acts = tuple(Slot("act", i, "log", 0.5, 2.0, prior=True) for i, k in enumerate(ACT_KEYS)
                 if valves_driven or k in PASSIVE_KEYS)
    out = acts + (MODAL_ZETA,)
    return out + ((Slot("latency_s", 0, "lin", 0.0, 4 * dt),) if valves_driven else ())


@dataclass
class Context:
    run: RunRecording
    sp: Spectra
    base: Base
    rp: Replay
    spools: Spools
    floor: bool
    valves_driven: bool
    s2_expected: np.ndarray | None = None      # the weights before any inflation (weights.expected)

    @property
    def modal(self):
        return self.base.modal


@dataclass
class Tried:
    instance: fx.Instance
    th: dict
    rss_fit: float
    rss_hold: float
    tests: dict
    step: int


@dataclass
class Selection:
    ctx: Context
    th_nominal: dict
    th_refit: dict
    th_final: dict
    chosen: list                   # [Tried], in the order named
    tried: list                    # every candidate fitted, [Tried]
    screened: list                 # [(instance key, best grid value, fit rss)]
    evals: dict = field(default_factory=dict)      # "nominal"/"refit"/"augmented" -> Evaluation on all bins
    dropped: list = field(default_factory=list)    # [Tried] chosen, then found not needed beside the others


def prepare(run: RunRecording, cfg: Config) -> Context:
    sp = spectra_of(run)
    base = Base.of(cfg, 1.0 / run.fs_hz)
    th = nominal_theta(base)
    rp = Replay(sp, base, expected(sp, base, th))
    spools = Spools(run.valve_cmd_V, sp.bin_index, base, sp.U)
    return Context(run, sp, base, rp, spools, sp.G is not None, valves_driven(run))


def valves_driven(run: RunRecording) -> bool:
    """Whether the valves were driven beyond the slow centring (feedback or feedforward at some point)."""
    u = run.valve_cmd_V
    f = np.fft.rfftfreq(len(u), 1.0 / run.fs_hz)
    U = np.fft.rfft(u - u.mean(axis=0), axis=0)
    above = np.sum(np.abs(U[f > 1.0]) ** 2, axis=0) * 2 / len(u) ** 2
    return bool(np.sqrt(above.max()) > VALVES_DRIVEN_V)


def nominal_theta(base: Base) -> dict:
    th = neutral(base.n_flex)
    th["latency_s"][0] = base.dt          # this rig's loop writes a command one period after its sample
    return th


def u_of(ctx: Context):
    return ctx.spools.effective


def reweigh(ctx: Context, th: dict) -> None:
    """The weights raised where theta's residual says (weights.inflation), from what the right model would
    leave (never from an earlier inflation): what the named effects explain is no longer taken for noise. A
    strong effect (a valve's deadband) inflates every band before it is named; weights kept from then hide
    what is left beside it (a machine mode moved by 5 %)."""
    if ctx.s2_expected is None:
        ctx.s2_expected = ctx.rp.s2
    ev = ctx.rp.evaluate(th, None, U=u_of(ctx)(th))
    ctx.rp = ctx.rp.with_noise(inflated(ctx.s2_expected, inflation(ev, ctx.sp.f_hz), ctx.sp.f_hz))


def refit(ctx: Context) -> tuple[dict, Replay]:
    """The refit, then the weights raised where its residual says (reweigh); (theta, replay)."""
    th0 = nominal_theta(ctx.base)
    res = fit(ctx.rp, th0, refit_slots(ctx.base.dt, ctx.valves_driven), ctx.sp.fit)
    reweigh(ctx, res.th)
    res = fit(ctx.rp, res.th, refit_slots(ctx.base.dt, ctx.valves_driven), ctx.sp.fit, max_nfev=12)   # the weights set
    return res.th, ctx.rp


def worst_cell(ev, f_hz: np.ndarray) -> float:
    """The largest mean whitened residual power over a channel's bins in one band (over what the right model
    leaves there)."""
    f = f_hz[ev.mask]
    p = np.abs(ev.r) ** 2 / np.maximum(ev.keep, 0.05)
    out = 0.0
    for lo, hi in BANDS_HZ:
        sel = (f >= lo) & (f < hi)
        if sel.sum() >= 8:
            out = max(out, float(np.max(np.mean(p[sel], axis=0))))
    return out


def dof(ctx: Context, mask) -> float:
    """The real numbers the residual on mask's bins carries: two per bin and channel, less what the floor's
    projection takes without floor accelerometers (the weighted share it leaves, rigmodel's floor span)."""
    ev = ctx.rp.evaluate(nominal_theta(ctx.base), mask)
    return 2.0 * float(ev.keep.sum())


def _rss(ctx: Context, th: dict, mask) -> float:
    return ctx.rp.evaluate(th, mask, U=u_of(ctx)(th)).rss


def _rss_near(ctx: Context, th: dict, at, exact: bool = False) -> float:
    """theta's fit-bin rss with the nuisance terms of `at` (an Evaluation): the screen's cheap estimate; exact:
    with its own (a machine mode moved without floor accelerometers moves the end terms the floor's
    projection leaves most of)."""
    if exact:
        return _rss(ctx, th, at.mask)
    return float(np.sum(np.abs(ctx.rp.linear(th, at, U=u_of(ctx)(th))) ** 2))


def screen(ctx: Context, th: dict, exclude=()) -> list[tuple[fx.Instance, float, float]]:
    """Each instance's first slot searched alone (the others held at theta, the nuisance terms of theta):
    its grid and the vertex of a parabola through theta's value and two neighbours (a gain also with its sign
    reversed); (instance, best value, fit rss), best first. The extra mode starts from the residual's worst
    peak with a few mode shapes."""
    out = []
    at = ctx.rp.evaluate(th, ctx.sp.fit, U=u_of(ctx)(th))
    for inst in fx.instances(ctx, valves_driven=ctx.valves_driven):
        if inst.key in exclude:
            continue
        if inst.effect.started:
            start, rss = extra_mode_start(ctx, th, at)
            out.append((inst, start, rss))
            continue
        exact = not ctx.floor and inst.effect.where == "mode"
        best = (None, math.inf)
        for v in _screen_values(ctx, th, inst, at, exact):
            rss = _rss_near(ctx, _start(th, inst, v), at, exact)
            if rss < best[1]:
                best = (v, rss)
        out.append((inst, best[0], best[1]))
    return sorted(out, key=lambda x: x[2])


def _screen_values(ctx: Context, th: dict, inst: fx.Instance, at, exact: bool = False) -> list[float]:
    """The grid, and the parabola's vertex through theta's value and its neighbours (smooth slots). A gain's
    values are signed: the grid's relative to the gain's present sign (-1: reversed)."""
    slot = inst.slots[0]
    sgn = float(np.sign(th[slot.key][slot.index]) or 1.0) if slot.scale == "signed" else 1.0
    vals = [sgn * v for v in inst.effect.grid]
    if inst.effect.nonlinear:
        return vals
    x0 = slot.to_x(slot.get(th))
    h = 0.05 if slot.scale != "lin" else 0.02 * (slot.hi - slot.lo)
    lo, hi = slot.bounds_x()
    xs = [x0 - h, x0, x0 + h]
    if xs[0] < lo:
        xs = [x0, x0 + h, x0 + 2 * h]
    elif xs[2] > hi:
        xs = [x0 - 2 * h, x0 - h, x0]
    rs = [_rss_near(ctx, _start(th, inst, sgn * slot.from_x(x)), at, exact) for x in xs]
    a, b, _ = np.polyfit(xs, rs, 2)
    if a > 0:
        vals.append(sgn * slot.from_x(min(max(-b / (2 * a), lo), hi)))
    vals.append(sgn * slot.from_x(xs[int(np.argmin(rs))]))
    return vals


def extra_mode_start(ctx: Context, th: dict, ev) -> tuple[tuple, float]:
    """(frequency, damping, shape) to start an extra mode from, and its fit rss: the frequency where the
    whitened residual stands highest over the model (smoothed over a mode's width), the shape the best of
    the four rigid patterns there."""
    f = ctx.sp.f_hz[ctx.sp.fit]
    p = np.sum(np.abs(ev.r) ** 2, axis=1)
    k = max(3, int(len(f) / 200))
    sm = np.convolve(p, np.ones(k) / k, mode="same")
    f0 = float(f[int(np.argmax(sm))])
    best = (None, math.inf)
    for pat in ((1, 1, 1, 1), (1, 1, -1, -1), (1, -1, 1, -1), (1, -1, -1, 1), (1, 0, 0, 0), (0, 1, 0, 0),
                (0, 0, 1, 0), (0, 0, 0, 1)):
        x = np.array([f0, 0.03] + [0.1 * v for v in pat])
        th1 = copy_theta(th)
        th1["extra"] = x
        rss = _rss_near(ctx, th1, ev, exact=not ctx.floor)
        if rss < best[1]:
            best = (tuple(x), rss)
    return best


def _start(th: dict, inst: fx.Instance, value) -> dict:
    """theta with the instance's first slot at value (a gain: the signed gain itself), or all its slots at a
    tuple of values (an extra mode's start)."""
    out = copy_theta(th)
    for slot, v in zip(inst.slots, value if isinstance(value, tuple) else (value,)):
        out[slot.key][slot.index] = v
    return out


def fit_candidate(ctx: Context, th: dict, inst: fx.Instance, value, base_slots) -> FitResult:
    return fit(ctx.rp, _start(th, inst, value), tuple(inst.slots) + tuple(base_slots), ctx.sp.fit,
               U_of=u_of(ctx), max_nfev=10 + 6 * len(inst.slots))


AT_BOUND = 1e-3                 # of a slot's range (its scale): an estimate this near a bound sits on it


def at_bound(th: dict, slots) -> str:
    """The first of the slots whose value sits on a bound of its physical range ("" if none): the data asks
    for more than the effect can be (a mode the model lacks damped as broadly as allowed is no resonance,
    a delay at zero no delay), so the estimate measures something else."""
    for s in slots:
        lo, hi = s.bounds_x()
        x = s.to_x(s.get(th))
        if min(x - lo, hi - x) <= AT_BOUND * (hi - lo):
            return f"{s.key}[{s.index}] = {s.get(th):.4g}"
    return ""


def over_fidelity(ctx: Context, at: Evaluation, th: dict, inst: fx.Instance) -> float:
    """How far the instance moves theta's prediction (theta against theta without it), over what two faithful
    models of the rig differ by (Replay.faithful: the model's own error, from the floor's part per bin): the
    largest over channels and bands of the rms change over the rms own error on the held-out bins, both with the
    nuisance terms of at (the round's base there; without floor accelerometers both what the floor's projection
    leaves).
    Below OVER_FIDELITY the effect moves the replay about as much as the model's own error: a statistically sure
    but physically empty change (an accelerometer at x1.002 taking up what another effect's model leaves), whatever its
    likelihood ratio over thousands of bins."""
    wo = without_effect(th, inst, ctx.base)
    change = np.abs((ctx.rp.linear(th, at, U=u_of(ctx)(th)) - ctx.rp.linear(wo, at, U=u_of(ctx)(wo))) * at.sd) ** 2
    faithful = ctx.rp.faithful(th, at, U=u_of(ctx)(th)) ** 2
    f = ctx.sp.f_hz[ctx.sp.hold]
    out = 0.0
    for lo, hi in BANDS_HZ:
        sel = (f >= lo) & (f < hi)
        if sel.sum() >= 8:
            out = max(out, float(np.max(np.sum(change[sel], axis=0) / np.sum(faithful[sel], axis=0))))
    return math.sqrt(out)


def select(ctx: Context, th_refit: dict, progress=None, prior: Selection | None = None) -> Selection:
    """Forward selection over the catalogue's instances (at most MAX_EFFECTS named). Each round fits the screen's
    best FULL_FITS candidates (and the extra mode: its start is the screen's roughest) with the command's
    latency, and tests them against the round's base. prior: a polished selection to go on from (its effects
    kept, the ones polish dropped not tried again)."""
    say = progress or (lambda s: None)
    latency = tuple(s for s in refit_slots(ctx.base.dt, ctx.valves_driven) if s.key == "latency_s")
    th = prior.th_final if prior else th_refit
    chosen, tried, screened_all = ([], [], []) if prior is None else (list(prior.chosen), list(prior.tried),
                                                                       list(prior.screened))
    dropped = {t.instance.key for t in prior.dropped} if prior else set()
    if prior:
        reweigh(ctx, th)                # the weights from what is named now, as after each round
    n_fit, n_hold = dof(ctx, ctx.sp.fit), dof(ctx, ctx.sp.hold)
    step = 1 + max((t.step for t in tried), default=-1)
    while len(chosen) < MAX_EFFECTS:
        base_fit, base_hold = _rss(ctx, th, ctx.sp.fit), _rss(ctx, th, ctx.sp.hold)
        at_hold = ctx.rp.evaluate(th, ctx.sp.hold, U=u_of(ctx)(th))
        worst = worst_cell(at_hold, ctx.sp.f_hz)
        if worst < EXPLAINED:
            say(f"round {step + 1}: held-out residual at most {worst:.2f} x expected in every channel and band: "
                "nothing left to explain")
            break
        exclude = {t.instance.key for t in chosen} | dropped
        ranked = screen(ctx, th, exclude)
        screened_all += [(i.key, v, r, step) for i, v, r in ranked]
        say(f"round {step + 1}: screened {len(ranked)} candidates; best {ranked[0][0].key if ranked else '-'}")
        slots = list(latency) + [s for t in chosen for s in t.instance.slots]
        best = None
        counted = fits = 0
        for inst, value, _ in ranked:
            if (counted >= FULL_FITS or fits >= MAX_FITS) and not inst.effect.started:
                continue
            fits += 1
            mode_like = inst.effect.where in ("mode", "machine")     # the modes' common damping trades with it
            res = fit_candidate(ctx, th, inst, value, slots + ([MODAL_ZETA] if mode_like else []))
            rf, rh = res.ev.rss, _rss(ctx, res.th, ctx.sp.hold)
            t = Tried(inst, res.th, rf, rh, compare(base_fit, base_hold, rf, rh, n_fit, n_hold, len(inst.slots)), step)
            pinned = at_bound(res.th, inst.slots)
            if pinned:
                t.tests.update(passed=False, at_bound=pinned)
            t.tests["over_fidelity"] = over_fidelity(ctx, at_hold, res.th, inst)
            faint = t.tests["passed"] and t.tests["over_fidelity"] < OVER_FIDELITY
            if faint:
                t.tests["passed"] = False
            small = fx.shortfall(inst.effect, fx.parameters(inst, res.th, ctx))
            if small:                   # not a full fit spent: the next candidate is fitted in its place
                t.tests.update(passed=False, below_least=small)
            else:
                counted += 1
            tried.append(t)
            say(f"  {inst.key}: held-out residual cut {100 * t.tests['holdout_gain']:.1f} %, LR "
                f"{t.tests['lr_holdout']:.0f} (needs {t.tests['lr_needed']:.0f}), change "
                f"{t.tests['over_fidelity']:.2g} x the model's fidelity{' - passes' if t.tests['passed'] else ''}"
                + (f" (its {pinned} at the bound of its range: not a measurement)" if pinned else "")
                + (" (it moves the replay by less than twice the model's own fidelity: not told from it)" if faint else "")
                + (f" ({small}: not a fault)" if small else ""))
            if t.tests["passed"] and (best is None or t.tests["lr_holdout"] > best.tests["lr_holdout"]):
                best = t
        if best is None:
            break
        chosen.append(best)
        th = best.th
        step += 1
        if len(chosen) < MAX_EFFECTS:
            # the refit again beside what is chosen: a strong effect at one mount drives the common parameters
            # to their bounds before it is named (a valve's delay took K_L to x0.5), and the next round's
            # candidates would be judged on what they make up for there rather than on their own evidence. It
            # starts from the model's values: a factor the unnamed effect drove onto its bound barely moves from
            # there (the trust region's steps shrink with the distance to a bound; the modes' common damping
            # left at x2 let every mode-like candidate of the next round win by freeing it)
            slots = list(refit_slots(ctx.base.dt, ctx.valves_driven)) + [s for t in chosen for s in t.instance.slots]
            th = fit(ctx.rp, refit_from_model(th, ctx.base), tuple(slots), ctx.sp.fit, U_of=u_of(ctx)).th
            reweigh(ctx, th)
            say("  refit beside it: " + ", ".join(f"{k} x{v:.3f}" for k, v in zip(ACT_KEYS, th["act"]))
                + f", modal damping x{th['modal_zeta'][0]:.2f}, latency {1e3 * th['latency_s'][0]:.3f} ms")
    return Selection(ctx, nominal_theta(ctx.base), th_refit, th, chosen, tried, screened_all,
                     dropped=list(prior.dropped) if prior else [])


def polish(sel: Selection, progress=None) -> Selection:
    """The chosen effects and the refit fitted together from the selection's end point; then each effect
    left out in turn (its slots back at the model's values, the rest refitted): one that the others and the
    refit can do without, by the same tests, is dropped (what a second effect explains may have been half
    taken up by the first one's fit)."""
    if not sel.chosen:
        return sel
    say = progress or (lambda s: None)
    ctx = sel.ctx
    base_slots = list(refit_slots(ctx.base.dt, ctx.valves_driven))
    n_fit, n_hold = dof(ctx, ctx.sp.fit), dof(ctx, ctx.sp.hold)

    def polished(chosen, th):
        slots = base_slots + [s for t in chosen for s in t.instance.slots]
        return fit(ctx.rp, th, slots, ctx.sp.fit, U_of=u_of(ctx), max_nfev=20).th
    th = polished(sel.chosen, sel.th_final)
    for t in sel.chosen:                # polished below its least size or onto a bound: as refused when chosen
        pinned = at_bound(th, t.instance.slots)
        small = fx.shortfall(t.instance.effect, fx.parameters(t.instance, th, ctx)) or (
            f"{pinned} at the bound of its range" if pinned else "")
        if small:
            say(f"{t.instance.key}: polished, {small}: dropped")
            sel.chosen = [c for c in sel.chosen if c is not t]
            sel.dropped.append(t)
            th = polished(sel.chosen, without_effect(th, t.instance, ctx.base))
            break
    if len(sel.chosen) > 1:
        full_fit, full_hold = _rss(ctx, th, ctx.sp.fit), _rss(ctx, th, ctx.sp.hold)
        for t in list(sel.chosen):
            rest = [c for c in sel.chosen if c is not t]
            th_wo = polished(rest, without_effect(th, t.instance, ctx.base))
            tests = compare(_rss(ctx, th_wo, ctx.sp.fit), _rss(ctx, th_wo, ctx.sp.hold), full_fit, full_hold,
                            n_fit, n_hold, len(t.instance.slots))
            if not tests["passed"]:
                say(f"{t.instance.key}: not needed beside the others (held-out cut "
                    f"{100 * tests['holdout_gain']:.1f} %): dropped")
                sel.chosen = rest
                sel.dropped.append(t)
                th = th_wo
                break
            t.tests = tests | {k: t.tests[k] for k in ("over_fidelity",) if k in t.tests}
    sel.th_final = th
    return sel


def refit_from_model(th: dict, base: Base) -> dict:
    """theta with the refit's parameters (the actuators' common factors, the modes' common damping, the
    latency) back at the model's values, the effects' kept."""
    out = copy_theta(th)
    ref = nominal_theta(base)
    for k in ("act", "modal_zeta", "latency_s"):
        out[k] = ref[k].copy()
    return out


def without_effect(th: dict, inst: fx.Instance, base: Base) -> dict:
    """theta with the instance's slots back at the model's values."""
    out = copy_theta(th)
    ref = nominal_theta(base)
    for s in inst.slots:
        out[s.key][s.index] = ref[s.key][s.index]
    return out


def evaluate_all(sel: Selection) -> Selection:
    ctx = sel.ctx
    for name, th in (("nominal", sel.th_nominal), ("refit", sel.th_refit), ("augmented", sel.th_final)):
        sel.evals[name] = ctx.rp.evaluate(th, None, U=u_of(ctx)(th))
    return sel


def diagnose_run(run: RunRecording, cfg: Config, progress=None) -> Selection:
    say = progress or (lambda s: None)
    ctx = prepare(run, cfg)
    say(f"replay of {run.duration_s:.0f} s at {run.fs_hz:g} Hz on {len(ctx.sp.f_hz)} bins "
        f"({'floor measured' if ctx.floor else 'floor not measured: projected out bin by bin'})")
    th_ref, _ = refit(ctx)
    say("refit: " + ", ".join(f"{k} x{v:.3f}" for k, v in zip(ACT_KEYS, th_ref["act"]))
        + f", modal damping x{th_ref['modal_zeta'][0]:.2f}, latency {1e3 * th_ref['latency_s'][0]:.3f} ms")
    sel = polish(select(ctx, th_ref, say), say)
    if sel.dropped and len(sel.chosen) < MAX_EFFECTS:
        # a round spent on an effect the later ones made unneeded (a torsion's frequency standing in for a mode
        # the model lacks, before that mode was named) does not count: the rounds go on beside what is left
        say("selection goes on beside " + (", ".join(t.instance.key for t in sel.chosen) or "nothing"))
        sel = polish(select(ctx, th_ref, say, prior=sel), say)
    return evaluate_all(sel)

"""The search for missing physics (docs/DIAGNOSIS.md): each catalogue effect that applies to the plant fitted on
top of the current model, tested (rig.diagnose.problem.compare) and the best one taken, at most MAX_EFFECTS; on
a plant file's axis left above the noise, pairs of effects fitted jointly (the pair step, docs/PLANT.md).

What an effect is -- its bounds, where its fit starts, whether it is slow, nonlinear or a projected line -- comes
from its definition (rig.diagnose.catalogue); nothing here asks an effect's name."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from rig.diagnose import catalogue, locate
from rig.diagnose.problem import ModelFit, Problem, compare, n_eff
from rig.diagnose.verdict import VERDICT_AT_NOISE      # the search stops at the verdict's own bar

MAX_EFFECTS = 2
EXPLAINED = 1.01                   # held-out residual rms / noise below which no further effect is sought
EXPLAINED_SLOW = 1.02              # the same once a reduced (deadband/friction) model is in
SLOW_RTOL = 1e-4                   # a slow (reduced) model's fit stops when an iteration gains < 0.01 % of the rss
POLISH_GAIN = 0.05                 # the polish stops when an iteration gains < 0.05 of one sample's share of the rss
POLISH_MAX_ITER = 20               # ... or after this many iterations of a slow model (~1 s each on 30 s at 5 kHz)


@dataclass(frozen=True)
class Selection:
    """What the search chose: the augmented model (the refit when nothing was named), the effects named with the
    test statistics each passed, confounded groups, every candidate tried, and each candidate alone (round 1)."""
    current: ModelFit
    chosen: tuple[str, ...] = ()
    stats: dict = field(default_factory=dict)
    groups: tuple[tuple[str, ...], ...] = ()
    tried: tuple[dict, ...] = ()
    round1: dict = field(default_factory=dict)


@dataclass
class _Search:
    """The working state of one search (local to select)."""
    pb: Problem
    refit: ModelFit
    nominal_lin: dict
    band: tuple
    lines: list
    say: Callable[[str], None]
    current: ModelFit
    chosen: list = field(default_factory=list)
    tried: list = field(default_factory=list)
    groups: list = field(default_factory=list)
    stats_of: dict = field(default_factory=dict)
    round1: dict = field(default_factory=dict)


def _init_candidate(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines,
                    y_clean: np.ndarray, coarse: bool) -> tuple[dict, dict] | None:
    """The start of an effect's fit, as its definition's start says (rig/diagnose/starts.py); coarse: nothing
    calls for a nonlinearity (a short grid)."""
    return catalogue.get(name).start.initial(pb, name, lins, fx_base, band, lines, y_clean,
                                             catalogue.slow_in(fx_base), coarse)


def _with_prior(pb: Problem, name: str, init, fx_base: dict, prior: dict | None):
    """The better start of two: the fresh one, or the effect's parameters from the first round (an effect found
    alone is often easier to find again from where it was)."""
    if prior is None or init is None:
        return init
    lin0, fx0 = init
    alt = {n: dict(v) for n, v in fx_base.items()}
    alt[name] = dict(prior)
    r0, _, _ = pb.residual(lin0, fx0)
    r1, _, _ = pb.residual(lin0, alt)
    return (lin0, alt) if np.sum(r1[pb.mfit] ** 2) < np.sum(r0[pb.mfit] ** 2) else init


def _fit_candidate(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean, second=False,
                   skip_above: float | None = None, prior: dict | None = None,
                   coarse: bool = False) -> ModelFit | None:
    if second and not catalogue.get(name).slow and catalogue.slow_in(fx_base):
        return _fit_by_proxy(pb, name, lins, fx_base, band, lines, y_clean, prior, coarse)
    init = _with_prior(pb, name, _init_candidate(pb, name, lins, fx_base, band, lines, y_clean, coarse), fx_base,
                       prior)
    if init is None:
        return None
    lin0, fx0 = init
    slow = catalogue.slow_in(fx0)
    if (slow or catalogue.get(name).costly_start) and skip_above is not None:
        # another candidate already reached the noise, or nothing calls for this one: refine only a start
        # that is already competitive
        st = pb.evaluate(lin0, fx0, k=0)
        if st.rss_fit > skip_above:
            return ModelFit(lin=lin0, fx=fx0, rss_fit=st.rss_fit, rss_hold=st.rss_hold, k=pb.n_params(fx0), coef=st.coef,
                            state=st.state, tau=st.tau)
    if slow and second:   # on a slow model: the effects with the gain and lag; the polish frees all
        return pb.fit(lin0, fx0, free_lin=pb.plant.slow_second_lin, max_iter=6,
                      rtol=SLOW_RTOL)
    if slow:
        return pb.fit(lin0, fx0, max_iter=6, rtol=SLOW_RTOL)
    return pb.fit(lin0, fx0, max_iter=10)


def _fit_by_proxy(pb: Problem, name: str, lins: list[dict], fx_base: dict, band, lines, y_clean,
                  prior: dict | None = None, coarse: bool = False) -> ModelFit | None:
    """A fast effect added to a slow (deadband/friction) model: fit it on the superposition proxy (one slow
    simulation), then score the result with the exact slow model."""
    lin_c = lins[0]
    y_cur = pb.model(lin_c, fx_base)
    base_c = pb.simulate(lin_c, catalogue.fast(fx_base))
    proxy = pb.with_(proxy=(y_cur, base_c))
    init = _with_prior(proxy, name, _init_candidate(proxy, name, lins, fx_base, band, lines, y_clean, coarse),
                       fx_base, prior)
    if init is None:
        return None
    lin0, fx0 = init
    free_fx = {n: proxy.spec_keys(n) for n in catalogue.fast(fx0)}
    f = proxy.fit(lin0, fx0, free_fx=free_fx, max_iter=12)
    return pb.evaluate(f.lin, f.fx, k=pb.n_params(f.fx))


def _active(pb: Problem, f: ModelFit, name: str) -> bool:
    """Does the fitted effect itself carry the gain? The candidate with the effect taken out (everything else as
    fitted) must be worse on the held-out blocks by the same likelihood-ratio margin; a deadband of width 0 that
    passed a test would be the linear parameters' extra iterations, not the effect."""
    if catalogue.get(name).projected:
        return True
    without = {k: v for k, v in f.fx.items() if k != name}
    r, _, _ = pb.residual(f.lin, without)
    nh = n_eff(int(pb.mhold.sum()), f)
    rss_wo = float(np.sum(r[pb.mhold] ** 2))
    return nh * math.log(max(rss_wo, 1e-300) / max(f.rss_hold, 1e-300)) > len(pb.spec_keys(name)) * math.log(nh)


def _at_edge(pb: Problem, f: ModelFit, name: str) -> bool:
    """A stand mode pinned at the edge of its physical range (its frequency at the excited band's edge, its
    damping ratio or the base's mass at a bound) is three free parameters spent on what is not a mode: a clean
    closed-loop run's fed-back noise fitted by a 161 Hz mode of damping 0.003 on a base of 100 x the axis's mass.
    Only the stand mode: a one-parameter effect at its bound is inactive or a real extreme."""
    if not catalogue.get(name).edge_test:
        return False
    for key, (lo, hi) in zip(pb.spec_keys(name), pb.effect_bounds(name)):
        v = f.fx[name][key]
        if min(abs(math.log(v / lo)), abs(math.log(hi / v))) < 0.01:
            return True
    return False


def _polish(pb: Problem, f: ModelFit) -> ModelFit:
    """All linear and effect parameters together (the disturbance frequency refined after), to the minimum: an
    iteration gaining less than POLISH_GAIN of one sample's share of the sum stops it (a chi-square of 0.05 at
    the noise). SLOW_RTOL stops a search's fit 7.5 short on 75,000 samples: on the stand with 400 N of friction the
    polish stopped at 403.2 N, 1.6 standard errors below its minimum, and the interval, centred on the minimum,
    sat lopsided around it (issue 29). A fast model's fit converges in a few steps: its rule is unchanged."""
    slow = catalogue.slow_in(f.fx)
    rtol = POLISH_GAIN / max(int(pb.mfit.sum()), 1)
    pol = _refine_disturbance(pb, pb.fit(f.lin, f.fx, max_iter=POLISH_MAX_ITER if slow else 15,
                                          rtol=rtol if slow else 1e-5))
    return pol if pol.rss_fit < f.rss_fit else f


def _refine_disturbance(pb: Problem, f: ModelFit) -> ModelFit:
    line = catalogue.projected(f.fx)
    if line is None:
        return f
    fx = {n: {k: v for k, v in d.items()} for n, d in f.fx.items()}
    r = pb.y - pb.model(f.lin, fx) - pb.basis.B @ f.coef - (f.state if f.state is not None else 0.0)
    fx[line]["frequency_hz"] = locate.refine_line(r * pb.use, pb.fs, fx[line]["frequency_hz"])
    out = pb.evaluate(f.lin, fx, f.k)
    return out if out.rss_fit <= f.rss_fit else f


def select(pb: Problem, refit: ModelFit, nominal_lin: dict, band, lines: list, *, nonlinear_hint: bool | None,
           stop_at_noise: bool, distortion: Callable, say: Callable[[str], None]) -> Selection:
    """Forward selection of at most MAX_EFFECTS catalogue effects on top of the refit (the protocol in
    rig/diagnose/engine.py). nonlinear_hint: the command's own structure shows distortion (None: it cannot tell);
    stop_at_noise: a round is skipped once the held-out residual is at the noise (not for a broadband command,
    whose distortion counts in its noise floor); distortion(r) -> (key, measurement, above the screen) of a
    residual."""
    R = _Search(pb, refit, nominal_lin, band, lines, say, current=refit)
    screen = [n for n, e in pb.plant.effects.items() if not e.projected or R.lines]
    harmonic_now = True if nonlinear_hint is None else nonlinear_hint
    round1: dict[str, dict] = {}
    rss0 = R.current.rss_hold
    for step in range(MAX_EFFECTS):
        over = math.sqrt(R.current.rss_hold / max(pb.mhold.sum(), 1)) / pb.noise
        explained = EXPLAINED_SLOW if catalogue.slow_in(R.current.fx) else EXPLAINED
        # progress as a share of the refit's own held-out residual: the search's x-noise figure uses its weights and
        # the first noise estimate, not the summary's, and printed beside it read as a contradiction
        share = f" (held-out residual {100 * math.sqrt(R.current.rss_hold / rss0):.0f} % of the linear refit's)"
        R.say(f"round {step + 1}: searching for an effect{share if step and rss0 > 0 else ''}")
        results = _round(R, screen, harmonic_now, stop_at_noise and over < explained, explained, round1)
        if not R.chosen:
            round1 = {n_: dict(g.fx[n_]) for n_, g, _ in results if n_ in g.fx}
            R.round1 = {n_: g for n_, g, _ in results if n_ in g.fx}
        ok = sorted((r for r in results if r[2]["passed"]), key=lambda r: r[1].rss_hold)
        if not ok:
            break
        name, f, st = ok[0]
        nh = n_eff(int(pb.mhold.sum()), f)
        conf = [n_ for n_, g, s in ok[1:] if nh * math.log(g.rss_hold / f.rss_hold) < math.log(nh)]
        if conf:
            R.groups.append([name] + conf)
        R.chosen.append(name)
        R.stats_of[name] = st
        R.say(f"polishing {'+'.join(R.chosen)}")
        R.current = _polish(pb, f)
        r_cur = pb.y - pb.series(R.current)
        key, _, now = distortion(r_cur)       # distortion the current model leaves
        if key:
            harmonic_now = bool(now)
        if catalogue.get(name).projected and name in screen:
            screen.remove(name)         # one line at a time
    if getattr(pb.plant, "axis_search", False):
        # the polish frees everything at once: an effect it made inactive (a deadband polished to width 0 once
        # friction came in beside it) is no longer a finding
        for name in list(R.chosen):
            if not _active(pb, R.current, name):
                fx = {k: v for k, v in R.current.fx.items() if k != name}
                R.current = pb.evaluate(R.current.lin, fx, pb.n_params(fx))
                R.chosen.remove(name)
                R.stats_of.pop(name, None)
                R.groups = [g for g in R.groups if g[0] != name]
    return Selection(R.current, tuple(R.chosen), dict(R.stats_of), tuple(tuple(g) for g in R.groups),
                     tuple(R.tried), dict(R.round1))


def pairs(pb: Problem, sel: Selection, say: Callable[[str], None]) -> tuple[Selection, bool]:
    """The pair step: a second chance for a recording the forward selection leaves above the noise (its verdict
    would not be "explained"). Two effects can hide each other: Coulomb friction and a deadband both stop
    the motion near zero force, friction and a saturation or a delay both bend the closed loop's moves, so each
    alone takes part of the other's share and the first one chosen spoils the start of the second. Every pair of
    the one-parameter candidates is therefore fitted jointly from the two effects' own first-round fits. A pair
    replaces the selection's model only when it passes the same tests as any effect: it beats that model (BIC on
    the fit blocks, likelihood ratio and gain on the held-out blocks), and EACH of its effects beats the pair's
    other effect alone, refitted (and is active: taking it out of the pair loses the margin). The selection (the
    pairs tried added), and True when a pair was taken."""
    if not getattr(pb.plant, "axis_search", False) or len(sel.round1) < 2:
        return sel, False
    nh = max(int(pb.mhold.sum()), 1)
    if math.sqrt(sel.current.rss_hold / nh) / pb.noise <= VERDICT_AT_NOISE:
        return sel, False
    tried = list(sel.tried)
    names = [n for n, e in pb.plant.effects.items() if n in sel.round1 and not e.projected
             and len(pb.spec_keys(n)) == 1]
    fits = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            fa, fb = sel.round1[a], sel.round1[b]
            fx0 = {a: dict(fa.fx[a]), b: dict(fb.fx[b])}
            slow = catalogue.slow_in(fx0)
            say(f"pair {a}+{b}")
            f = pb.fit(min((fa, fb), key=lambda g: g.rss_fit).lin, fx0, max_iter=10,
                       rtol=SLOW_RTOL if slow else 1e-5)
            st = compare(pb, sel.current, f)
            tried.append({"effects": [a, b], "step": "pair", "rss_fit": f.rss_fit, "rss_holdout": f.rss_hold,
                            **st})
            if st["passed"]:
                fits.append((f.rss_hold, a, b, f))
    for _, a, b, f in sorted(fits, key=lambda x: x[0]):
        stats = {}
        for x, other in ((a, b), (b, a)):
            check = catalogue.get(x).check
            if not _active(pb, f, x) or (check is not None and not check(pb, f, x)):
                break
            slow = catalogue.get(other).slow
            alone = pb.fit(f.lin, {other: dict(f.fx[other])}, max_iter=6 if slow else 10,
                           rtol=SLOW_RTOL if slow else 1e-5)
            st = compare(pb, alone, f)
            if not st["passed"]:
                break
            stats[x] = st
        if len(stats) == 2:
            say(f"pair {a}+{b} taken")
            return Selection(f, (a, b), stats, tuple(g for g in sel.groups if set(g) <= {a, b}), tuple(tried),
                             sel.round1), True
    return Selection(sel.current, sel.chosen, sel.stats, sel.groups, tuple(tried), sel.round1), False


def _round(R: _Search, screen: list[str], harmonic_now: bool, at_noise: bool, explained: float,
           round1: dict) -> list[tuple[str, ModelFit, dict]]:
    """One round of the forward selection: each screened candidate on top of the current model, tested."""
    pb, current, chosen = R.pb, R.current, R.chosen
    results: list[tuple[str, ModelFit, dict]] = []
    # the measurement without its sensor terms and without the fitted disturbance's response
    y_clean = pb.y - pb.basis.B @ current.coef - (pb.physics(current) - pb.model(current.lin, current.fx))
    base, null = current, None
    for name in screen:
        if name in chosen:
            continue
        effect = catalogue.get(name)
        if not effect.projected and at_noise and not (harmonic_now and effect.nonlinear):
            continue        # the held-out residual is already at the noise: nothing left to explain
        R.say(f"candidate {'+'.join(chosen + [name])}")
        lins = [current.lin] if chosen else [R.refit.lin, R.nominal_lin]
        floor_ = [g.rss_fit for _, g, _ in results if math.sqrt(g.rss_hold / pb.mhold.sum()) / pb.noise < explained]
        slow_name = effect.slow
        if floor_ and slow_name and not harmonic_now:
            continue        # a cheap candidate already reached the noise and nothing calls for these
        skip = None
        if slow_name and results:  # a slow model is refined only when its best start rivals the best
            skip = 2.0 * min(g.rss_fit for _, g, _ in results)
        if floor_:
            skip = 2.0 * min(floor_)
        if not harmonic_now:       # without distortion a nonlinearity must at least show in its start
            skip = min(skip or np.inf, (0.95 if slow_name else 0.999) * current.rss_fit)
        prior = round1.get(name) if chosen else None
        f = _fit_candidate(pb, name, lins, current.fx, R.band, R.lines, y_clean, second=bool(chosen),
                           skip_above=skip, prior=prior if not effect.projected else None, coarse=not harmonic_now)
        if f is None:
            continue
        f = _refine_disturbance(pb, f)
        st = compare(pb, base, f)
        if st["passed"] and chosen and catalogue.slow_in(current.fx) and null is None:
            # a slow model's polish may stop short: a candidate must beat the current model given the same
            # extra iterations, not the extra iterations themselves (fitted once, when needed)
            null = pb.fit(current.lin, current.fx, max_iter=6, rtol=SLOW_RTOL)
            if null.rss_fit < base.rss_fit:
                base = null
                st = compare(pb, base, f)
        if st["passed"] and not _active(pb, f, name):
            st = {**st, "passed": False, "inactive": True}
        if st["passed"] and getattr(pb.plant, "axis_search", False) and _at_edge(pb, f, name):
            st = {**st, "passed": False, "at_edge": True}
        if st["passed"] and effect.check is not None and not effect.check(pb, f, name):
            st = {**st, "passed": False, "not_in_the_data": True}
        R.tried.append({"effects": chosen + [name], "rss_fit": f.rss_fit, "rss_holdout": f.rss_hold, **st})
        results.append((name, f, st))
    return results

"""The verdict (docs/DIAGNOSIS.md, "Odd recordings and their answers", "A verdict for real data"): does the
augmented model describe the recording (explained, partly), does it stay incomplete far above the noise with the
effects that passed every held-out test named, does it not describe it at all, or does the recording allow no claim;
and what the evidence suggests when the model does not describe it (a different plant or units, closed-loop data,
a rate too low). The sentences of the verdict itself are the report's (rig.diagnose.report.verdict_text)."""
from __future__ import annotations

import math

import numpy as np

from rig.recordings import command as command_mod
from rig.diagnose.plants import at_bounds
from rig.diagnose.problem import LIN_BOUNDS, ModelFit, Problem
from rig.diagnose.results import Fit, Verdict

MIN_CLAIM_S = 5.0                  # shorter recordings get no claim
VERDICT_AT_NOISE = 1.15            # augmented residual / noise: "explains the recording"
VERDICT_NOT_DESCRIBED = 3.0        # above: the model stays incomplete (the effects that passed named), or does not
                                   # describe the recording at all (nothing passed, or the refit says another plant)


def no_claim_reason(rec, cmd_info: command_mod.Command) -> str:
    if rec.duration_s < MIN_CLAIM_S:
        return (f"the recording is {rec.duration_s:.3g} s long, too short for a claim (at least {MIN_CLAIM_S:g} s "
                f"of excitation are needed)")
    if cmd_info.kind in ("flat", "sine"):
        return (f"the command is a {'constant' if cmd_info.kind == 'flat' else 'single sine'}: too poorly excited "
                f"for a claim (a sweep, multisine, noise or steps are needed)")
    lo, hi = cmd_info.band_hz
    if hi <= 0 or hi < 2.0 * max(lo, 1e-3):
        return f"the command excites only {lo:.3g}-{hi:.3g} Hz: too poorly excited for a claim"
    return ""


def file_bound_hints(pb, refit) -> list[str]:
    """A plant file's free parameters the refit left at a bound of their range. A bound of zero reached is the data
    asking for no such term (a pure integrator has no den[-1]), not a different plant: said so."""
    hints = []
    for k, edge in at_bounds(pb.plant.bounds_lin, refit.lin, pb.lin_keys, pb.plant.log_scale).items():
        lo, hi = pb.plant.bounds_lin[k]
        v = refit.lin[k]
        if edge == 0.0:
            hints.append(f"The refit took {k} to 0, the bound of its range in the plant file ({lo:g}..{hi:g}): the "
                         f"data ask for no such term; fix {k} = 0 in the plant file if that is the physics.")
        else:
            hints.append(f"The refit pushed {k} to {v:.4g}, the {'lower' if edge == lo else 'upper'} bound of its "
                         f"range in the plant file ({lo:g}..{hi:g}): widen the range if that value is plausible, "
                         f"else the plant (or its units) differs from the file's.")
    return hints


def verdict(pb: Problem, no_claim: str, named: bool, fit: Fit, refit: ModelFit, check) -> Verdict:
    """Say whether the models describe the recording, and if not, what the evidence suggests. Closed-loop data
    is named whatever the verdict: the fits assume the command is independent of the noise."""
    sugg = []
    loop = pb.loop
    if loop.closed and pb.plant.family == "eha":
        sugg.append(f"Closed-loop data: {loop.reason}; a fit of the open-loop plant from command to position does "
                    "not apply (identify the plant from an open-loop run, e.g. `rig chirp`).")
    elif loop.closed:
        sugg.append(f"Closed-loop data: {loop.reason}. The plant is simulated from the recorded command (what the "
                    "drive received), so the claims stand, but the command carries the position's noise back in: "
                    "the linear parameters can lean toward the controller's inverse, and only effects that predict "
                    "the held-out blocks are named.")
    if no_claim:
        return Verdict("no_claim", no_claim=no_claim, suggestions=tuple(sugg))
    over = fit.augmented.residual_over_noise_holdout
    over_ref = fit.refit.residual_over_noise_holdout
    if over <= VERDICT_AT_NOISE:
        return Verdict("explained", over, over_ref, named, suggestions=tuple(sugg))
    if pb.plant.family == "eha":
        at_edge = [k for k in pb.lin_keys
                   if min(abs(math.log(refit.lin[k] / pb.nominal[k]) - math.log(b)) for b in LIN_BOUNDS) < 0.02]
        if at_edge:
            sugg.append("The refit pushed " + ", ".join(at_edge) + " to the edge of the physical range: a "
                        "different plant (or different units) than the configured model.")
    else:
        sugg += file_bound_hints(pb, refit)
    if fit.refit.nrmse > 0.5:
        sugg.append(f"Even the refit leaves {100 * fit.refit.nrmse:.0f} % of the motion unexplained: the "
                    "position does not follow the command as this plant would.")
    if check is not None and not check.usable:
        sugg.append(check.note[0].upper() + check.note[1:] + ".")
    if pb.fs < 500.0 and pb.plant.family == "eha":
        sugg.append(f"The recording is sampled at {pb.fs:g} Hz, too slowly for the valve's dynamics.")
    lag = alignment_lag(pb)
    if lag:
        sugg.append(f"The position fits the nominal model best shifted by {abs(lag)} sample{'s' * (abs(lag) > 1)} "
                    f"({abs(lag) / pb.fs * 1e3:.3g} ms): the position leads the command by that, which no plant "
                    "does. Check the time alignment of the logged columns (the position stamped early, or the "
                    "command late) before reading the effects.")
    if over <= VERDICT_NOT_DESCRIBED:
        status = "partly"
    else:
        # far above the noise the effects that passed every held-out test are still named (the model stays
        # incomplete), unless the refit says the plant is another one: its differences are no findings
        status = "incomplete" if named and not _other_plant(pb, refit) else "not_described"
    return Verdict(status, over, over_ref, named, suggestions=tuple(sugg))


MAX_LAG = 3                        # samples of misalignment looked for
LAG_GAIN = 0.7                     # a shift must cut the refit's residual rms below this share of the unshifted


def alignment_lag(pb: Problem) -> int:
    """The lead k < 0 (|k| <= MAX_LAG, samples) of the recorded position against the nominal model's response to the
    recorded command (y[i] against model[i - k], each shift with its own least-squares gain and offset) that cuts
    the residual rms below LAG_GAIN of the unshifted one; 0 when none does. The nominal model, not the refit: a
    refit bends its parameters (a valve's bandwidth to the edge of its range) to absorb a shift. A logger that
    stamps the position a sample early (k = -1) leaves a residual of the motion's derivative that no physics in
    the catalogue removes."""
    try:
        yhat = pb.model(pb.nominal, {})
    except Exception:              # noqa: BLE001 - a hint only: a model that cannot be evaluated gives none
        return 0
    y, n = pb.y, len(pb.y)
    if n <= 4 * MAX_LAG or not np.all(np.isfinite(yhat)):
        return 0
    core = slice(MAX_LAG, n - MAX_LAG)

    def rms(k: int) -> float:
        m = yhat[MAX_LAG - k:n - MAX_LAG - k]
        A = np.column_stack([m, np.ones_like(m), np.linspace(-1.0, 1.0, m.size)])
        coef, *_ = np.linalg.lstsq(A, y[core], rcond=None)
        return float(np.sqrt(np.mean((y[core] - A @ coef) ** 2)))
    r0 = rms(0)
    best = min((k for k in range(-MAX_LAG, MAX_LAG + 1) if k), key=rms)
    # only a lead is said: a position cannot answer a command before it came; a lag may be the plant's own delay
    return best if best < 0 and r0 > 0 and rms(best) < LAG_GAIN * r0 else 0


def _other_plant(pb: Problem, refit: ModelFit) -> bool:
    """The refit pushed a linear parameter to the edge of its range (the paper's 0.7-1.4 x, a plant file's bounds;
    a bound of zero is the data asking for no such term, not another plant)."""
    if pb.plant.family == "eha":
        return any(min(abs(math.log(refit.lin[k] / pb.nominal[k]) - math.log(b)) for b in LIN_BOUNDS) < 0.02
                   for k in pb.lin_keys)
    return any(edge != 0.0 for edge in at_bounds(pb.plant.bounds_lin, refit.lin, pb.lin_keys,
                                                  pb.plant.log_scale).values())

"""Diagnosis engine (issues 7 and 12): refit the linear model first, locate the mismatch, choose missing physics
from the catalogue, fit the augmented model and prove each effect on a held-out segment; the sensors' own terms
ride along in every model as nuisance parameters and are reported apart from the physics.

`diagnose(rec, plant)` is the one entry: a recording and a plant in, a typed Diagnosis (rig.diagnose.results)
out (`diagnose_reading(r)` takes what the reading stage read: `rig diagnose` reads its files first). It runs the
stages in order, each a function from one typed value to the next (rig.diagnose.stages,
rig.diagnose.search, rig.diagnose.conclude); rig.diagnose.report writes what it found.

Protocol
  * The recording is read and checked first (rig.diagnose.reading), the recorded command with it
    (rig.recordings.command): sweep, multisine, steps, noise, one level or several. The evidence follows from
    it, never from an assumed linear chirp.
  * Samples left out of every fit: flat tops at a converter's range (clipped), and, when the recording does not
    start at rest, the plant's start transient.
  * Fit/holdout split: interleaved blocks (even blocks fit, odd blocks held out), so both cover the whole run.
  * Every model (nominal, refit, augmented) = physics + sensor terms. The sensor terms (offset, drift, slow
    wander, pickup lines; rig.diagnose.sensor) are linear in their coefficients and are projected out on the fit
    blocks inside each evaluation (variable projection), so they never compete with the physics as effects.
  * Lines in the refit residual are sorted by the two sensors: in position but not in acceleration at the
    (2 pi f)^2-predicted amplitude = pickup (a sensor term); in both = a force (the periodic_disturbance
    candidate).
  * Refit: the identified parameters K_L, K_C, K_Q, w_nv, zeta within physical bounds (0.7-1.4 x nominal; C is
    not identifiable from position below w_h and stays nominal). A parameter change is not missing physics.
  * Candidates: each catalogue effect fitted jointly with the linear parameters (exact fast models, models.py).
    An effect counts only when it passes BOTH: BIC on the fit blocks (noise variance from the data) and a
    likelihood-ratio test on the held-out blocks with the parameters frozen from the fit blocks.
  * Forward selection: best single effect, then the best second effect on top of it, max two; a round is
    skipped once the held-out residual is at the noise. Each chosen model is polished (all parameters).
  * Pair step (plant files' axes only): when the selection leaves the recording above the noise, pairs of
    one-parameter effects fitted jointly from their first-round fits, under the same tests (search.pairs).
  * Screening for speed: the disturbance only with a force line; slow nonlinear models (deadband, friction) are
    refined only when their best grid start rivals the best candidate so far (and, without a sign of
    nonlinearity in the command's own terms -- harmonics of a sweep, empty lines of a multisine -- improves the
    current fit). A fast effect added to a slow model is fitted on a superposition proxy.
  * Confounded groups: other passing candidates whose held-out likelihood is statistically indistinguishable
    from the chosen one's (log-likelihood ratio below ln n) are reported as a group.
  * Verdict: "explained" only when the augmented residual is at the noise. Otherwise the summary says plainly
    that the model does not describe the recording, and what the evidence suggests.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable

from rig.diagnose import conclude, reading, search, stages
from rig.diagnose.results import Diagnosis
from rig.plant.model import Plant
from sim_backend.linear import ActuatorParams


def diagnose(rec, plant: ActuatorParams | Plant, *, progress: Callable[[str], None] | None = None,
             seed: int = 0) -> Diagnosis:
    """Diagnose a recording (rig.recordings.Recording) against a plant: the nominal ActuatorParams of the eha plant,
    or a Plant of any family (rig.plant, a plant file). progress(message) hears each stage. The result is typed
    and frozen (rig.diagnose.results): e.g. `d.names()`, `d.effects[0].parameters`, `d.verdict.status`,
    `d.fit.augmented.residual_over_noise_holdout`; rig.diagnose.report.summary(d) says it in words and
    rig.diagnose.report.write_outputs(folder, d, rec) writes diagnosis.json, fit.csv and report.md.

    A notebook:
        from rig.diagnose import report
        from rig.diagnose.engine import diagnose
        from rig.recordings import load_recording
        from sim_backend.linear import ActuatorParams
        d = diagnose(load_recording("run.csv.gz"), ActuatorParams())
        print(report.summary(d), d.effects)
    """
    return diagnose_reading(reading.read(rec, plant, progress), progress=progress, seed=seed)


def diagnose_reading(r: reading.Reading, *, progress: Callable[[str], None] | None = None,
                     seed: int = 0) -> Diagnosis:
    """Diagnose what the reading stage read and checked (rig.diagnose.reading: `rig diagnose` reads its files
    there first)."""
    with reading.one_blas_thread():
        return _run(r, progress or (lambda msg: None))


def _run(r: reading.Reading, say: Callable[[str], None]) -> Diagnosis:
    """The stages in order."""
    t_start = time.perf_counter()
    prepared = stages.prepare(r)
    refitted = stages.refit(prepared, say)
    screened = stages.screen(refitted, say)
    selection = _select(screened, say)
    settled = stages.settle(screened, selection)
    if not screened.no_claim:
        paired, taken = search.pairs(settled.pb, settled.sel, say)
        settled = stages.settle(screened, paired, settled) if taken else replace(settled, sel=paired)
    located = stages.locate_mismatch(settled)
    return conclude.conclude(located, t_start, time.perf_counter)


def _select(S: stages.Screened, say: Callable[[str], None]) -> search.Selection:
    """The search for missing physics on top of the refit (nothing when the recording allows no claim)."""
    R = S.fitted
    if S.no_claim:
        say(f"no claim: {S.no_claim}")
        return search.Selection(R.refit)
    return search.select(R.pb, R.refit, dict(R.pb.nominal), R.prep.band, list(R.lines),
                         nonlinear_hint=S.nonlinear_hint,
                         # a broadband command's nonlinear distortion is not coherent with it and counts in its
                         # noise floor: there, no round is skipped for having reached "the noise"
                         stop_at_noise=R.prep.cmd_info.kind not in ("noise", "steps"),
                         distortion=lambda r: stages.distortion(R, R.pb, r, r), say=say)

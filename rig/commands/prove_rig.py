"""`rig prove --rig`: the blind proof on the four-mount rig (issue 28). Each case is a closed-loop run of the
simulated rig hiding its effects (the session `rig run --sim-time --record` builds: the same loop, controllers,
recorder and file), diagnosed as `rig diagnose` does with the model's config (the run's sensors and floor, no
errors), and graded (rig/diagnose/machine/prove.py).
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")     # (before numpy loads: see diagnose_rig.py)


def record_case(case, path: Path) -> None:
    """The case's closed-loop run of the simulated rig, recorded to path as rig run --sim-time --record does."""
    from rig.config import config_from_dict
    from rig.runtime.clock import SimClock
    from rig.runtime.session import Session

    truth = config_from_dict(case.sections(), source=f"<rig prove case {case.name}>")
    attrs = {"command": "rig prove --rig", "layout": "machine", "isolation_at_start": case.mode}
    with Session(truth, "sim", clock=SimClock(), record=str(path), record_attrs=attrs,
                 isolation=case.mode != "off", feedforward=case.mode == "feedback_feedforward") as s:
        s.run(seconds=case.duration_s, activate_after_s=0.05)


def run_case(case_dict: dict, keep_dir: str | None = None) -> dict:
    """One case: run, record, diagnose with the model's config, grade (in a worker process); with keep_dir its
    recording and its graded row (JSON) are kept there."""
    from rig.config import config_from_dict
    from rig.diagnose.machine.prove import RigCase, grade
    from rig.diagnose.machine.report import summary_text
    from rig.diagnose.machine.result import diagnose_rig
    from rig.recordings.runfile import read_run

    case = RigCase(**case_dict)
    model = config_from_dict(case.model_sections(), source="<the model>")
    with tempfile.TemporaryDirectory(prefix="rig-prove-") as tmp:
        path = Path(keep_dir or tmp) / f"{case.name}.h5"
        record_case(case, path)
        rec = read_run(path)
        t0, c0 = time.perf_counter(), time.process_time()
        diag = diagnose_rig(rec, model)
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
        diag.summary = summary_text(diag)
        row = grade(case, diag, elapsed_s=elapsed, cpu_s=cpu)
    if keep_dir:                # beside its recording: a proof stopped half-way keeps what it graded
        (Path(keep_dir) / f"{case.name}.json").write_text(json.dumps(row, indent=1, default=float))
    return row


def cases_and_rows(args, progress) -> tuple[list, list]:
    """(cases, rows) of `rig prove --rig` (args: n, seed, duration, workers, keep)."""
    from rig.diagnose.machine.prove import draw_cases
    from rig.diagnose.prove import run_jobs

    cases = draw_cases(args.n, args.seed, duration_s=args.duration)
    keep = str(args.keep) if getattr(args, "keep", None) else None
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
    jobs = [(run_case, (asdict(c), keep), c.name) for c in cases]
    return cases, run_jobs(jobs, args.workers, progress)



def run(args) -> int:
    """`rig prove --rig` from the parsed options of `rig prove`."""
    import sys

    from rig.diagnose.machine import prove

    from rig.errors import RigError
    if args.cases is not None or args.plant is not None or args.habits or getattr(args, "scheduler", None):
        raise RigError("--rig: not with --cases, --plant, --habits or --scheduler (it makes runs of the four-mount "
                       "rig on --workers processes)")
    if args.duration is None:
        args.duration = 60.0
    if not 5.0 <= args.duration <= 1000.0:
        raise RigError(f"--duration: expected 5 to 1000 s for a run of the rig, got {args.duration:g}")
    title = f"rig prove --rig --n {args.n} --seed {args.seed} --duration {args.duration:g}"
    print(f"rig prove: {args.n} closed-loop runs of {args.duration:g} s of the simulated four-mount rig from seed "
          f"{args.seed} on {args.workers} processes", file=sys.stderr, flush=True)

    def progress(done: int, total: int, label: str) -> None:
        print(f"[{done}/{total}] diagnosed {label}", file=sys.stderr, flush=True)
    cases, rows = cases_and_rows(args, progress)
    result = {"title": title, "rows": rows, "confusion": prove.confusion(rows), "score": prove.score(rows),
              "cases": [asdict(c) for c in cases]}
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "proof.md").write_text(prove.report_markdown(rows, title))
        (args.out / "proof.json").write_text(json.dumps(result, indent=1, default=float))
    if args.json:
        print(json.dumps(result, indent=1, default=float))
    else:
        print(prove.table_markdown(rows))
        print("confusion matrix (rows: truth, columns: named)\n")
        print(prove.confusion_markdown(result["confusion"]))
        print(prove.score_text(result["score"]))
        if args.out is not None:
            print(f"\nwritten: {args.out / 'proof.md'}, {args.out / 'proof.json'}")
    return 0

"""`rig diagnose REC --out DIR`: where the recording and the configured model differ, which physics is missing,
the augmented fit, and the proof it is better (outputs: rig/diagnose/report.py).

`rig diagnose REC... --out DIR` (several files, a folder or a glob): a batch (rig/batch/): each recording in
DIR/<name>/ as above, on --workers processes or a Dask cluster (--scheduler), with DIR/summary.{csv,md,json}
and the trends of the recordings' effects and parameters over their dates."""
from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path

from rig import cliargs
from rig.batch import command as batch
from rig.batch.run import Job, file_identity
from rig.errors import RigError
from rig.runtime.signals import off_the_main_thread


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="REC", type=Path, nargs="+",
                   help="chirp recording (CSV, CSV.gz, HDF5 or .mat; columns time_s,valve_cmd_V,position_m,accel_mps2), "
                        "or a run of the four-mount rig (rig run --record, rig hil: docs/RUN_RECORDING.md)"
                        "; several, a folder or a quoted glob ('runs/**/*.h5'): a batch")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write diagnosis.json, fit.csv, report.md and the PNG plots to DIR (default: the "
                            "summary only; a batch needs it: one folder per recording in it, and the summary; run "
                            "again into it, a batch resumes)")
    p.add_argument("--seed", type=cliargs.seed(), default=0, help="seed of the engine's random choices (default 0)")
    p.add_argument("--json", action="store_true",
                   help="print only diagnosis.json on stdout (a batch: its summary rows and trends as JSON)")
    p.add_argument("--plant", metavar="FILE", type=Path, default=None,
                   help="plant file (TOML, docs/PLANT.md): the model family and its parameters (default: the eha "
                        "actuator of --config or Table 1), and [signals] naming REC's own columns or variables "
                        "and their units")
    batch.add_arguments(p)


def is_machine_run(path, plant) -> bool:
    """The route's one rule, for one file alone and for each of a batch's: a run of the four-mount rig
    (docs/RUN_RECORDING.md) gets the machine's diagnosis, unless a plant file asks for another model."""
    from rig.recordings.runfile import is_run_recording
    return plant is None and Path(path).is_file() and is_run_recording(Path(path))


def diagnose_one(plant: Path | None, config: str | None, seed: int, path: str, out: str) -> dict:
    """A batch's work on one recording (in a worker): diagnose it into out, as `rig diagnose` does; its row."""
    if is_machine_run(path, plant):
        from rig.commands import diagnose_rig
        return diagnose_rig.batch_work(config, path, out)
    from rig.batch.rows import diagnosis_row
    from rig.diagnose import report
    from rig.diagnose.engine import diagnose_reading
    from rig.diagnose.reading import read_files

    r = read_files(Path(path), plant, config)
    diag = diagnose_reading(r, seed=seed)
    try:
        report.write_outputs(Path(out), diag, r.rec)
    except OSError as e:
        raise RigError(f"{out}: cannot write ({e.strerror or e})") from None
    return diagnosis_row(diag, r.rec)


def run(args) -> int:
    """The route of REC, chosen here once: a batch, a run of the four-mount rig, or a recording against its plant."""
    cliargs.log_to_stderr("diagnose")          # the readers' warnings: `rig diagnose: warning: ...`
    if batch.wanted(args):
        options = {"seed": args.seed, "plant": file_identity(args.plant), "config": file_identity(args.config)}
        return batch.run_job(Job("diagnose", options, partial(diagnose_one, args.plant, args.config, args.seed)), args)
    args.recording = args.recording[0]
    if is_machine_run(args.recording, args.plant):
        from rig.commands import diagnose_rig
        return off_the_main_thread("diagnose", diagnose_rig.run, args)
    return off_the_main_thread("diagnose", _one, args)


def _one(args) -> int:
    """A recording against its plant: everything read and checked first (rig.diagnose.reading), then the engine."""
    from rig.diagnose import report
    from rig.diagnose.engine import diagnose_reading
    from rig.diagnose.reading import read_files

    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    r = read_files(args.recording, args.plant, args.config, progress)   # one line naming file and key, exit 2
    rec = r.rec
    if rec.gaps:
        print(f"note: {rec.gaps}", file=sys.stderr)
    progress(f"diagnosing {rec.source}: {rec.n} samples at {rec.fs_hz:g} Hz against {r.against}")
    if rec.closed_loop:
        from rig.recordings.recording import CLOSED_LOOP_NOTE
        progress(f"note: {CLOSED_LOOP_NOTE if rec.reference_m is not None else 'closed-loop recording: ' + rec.closed_loop}")
    diag = diagnose_reading(r, progress=progress, seed=args.seed)
    paths = {}
    if args.out is not None:
        progress("writing outputs")
        try:
            paths = report.write_outputs(args.out, diag, rec)
        except OSError as e:
            raise RigError(f"--out {args.out}: cannot write ({e.strerror or e})") from None
    progress(f"done in {time.perf_counter() - t0:.1f} s")
    if args.json:
        print(json.dumps(report.diagnosis_dict(diag, rec), indent=1))
    else:
        print(report.summary_text(diag, rec))
        print("written: " + ", ".join(str(p) for p in paths.values()) if paths else
              "(add --out DIR for diagnosis.json, fit.csv, report.md and the plots)")
    return 0

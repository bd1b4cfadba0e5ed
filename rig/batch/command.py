"""The command line's part of a batch, shared by `rig diagnose` and `rig identify`: the options (--workers,
--scheduler), the progress of the whole batch on stderr (one line rewritten in place on a terminal; a line per
recording otherwise), and what is printed at the end (the summary's table, or its JSON with --json).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from rig import cliargs
from rig.batch import inputs, pool, trends
from rig.batch.run import MANIFEST, Job, Outcome, open_folder, run_batch
from rig.errors import RigError


def add_arguments(p) -> None:
    p.add_argument("--workers", type=cliargs.count(1, 256), default=None, metavar="N",
                   help="a batch (several recordings, a folder or a glob): N processes of this machine (default: "
                        "its cores)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                   help="a batch on the Dask cluster of this scheduler instead (docs/BATCH.md: the workers must "
                        "run this rig and see the recordings and --out at the same paths)")
    p.set_defaults(resumes=resumes)


def wanted(args) -> bool:
    """Several recordings, a folder, a glob, or --workers/--scheduler given: a batch; one file: as before."""
    return inputs.is_batch(args.recording) or args.workers is not None or args.scheduler is not None


def resumes(args, folder: Path) -> bool:
    """A batch given its own output folder again (the folder holds a batch's manifest): it resumes there (the
    batch refuses it in one line if it was made by another command or with other options)."""
    return wanted(args) and (Path(folder) / MANIFEST).is_file()


class Progress:
    """The batch's progress: finished / total, failed, the last one, and the time left at the rate so far."""

    def __init__(self, command: str, total: int, stream=None) -> None:
        self.command, self.total, self.stream = command, total, stream or sys.stderr
        self.tty = self.stream.isatty()
        self.t0 = time.perf_counter()
        self.failed = 0
        self.resumed = 0

    def __call__(self, row: dict, finished: int, total: int, resumed: bool) -> None:
        self.resumed += resumed
        self.failed += row["status"] != "ok"
        el = time.perf_counter() - self.t0
        now = finished - self.resumed
        left = (total - finished) * el / now if now else float("nan")
        what = "failed: " + row["error"] if row["status"] != "ok" else (row.get("verdict") or "done")
        if row["status"] == "ok" and row.get("effects"):
            what += " (" + ", ".join(row["effects"]) + ")"
        bar = "#" * int(20 * finished / total)
        line = (f"rig {self.command}: [{bar:<20}] {finished}/{total} ({self.failed} failed) {el:6.0f} s"
                f"{f', ~{left:.0f} s left' if left == left else ''} | {row['recording']}: {what}")
        if self.tty:
            self.stream.write("\r" + line[:160].ljust(160) + ("\n" if finished == total else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def _out(args) -> Path:
    if args.out is None:
        raise RigError("--out: a batch needs an output folder (each recording gets its own folder in it)")
    return args.out


def run_job(job: Job, args) -> int:
    """Run the batch the arguments name; print its summary (or its JSON); exit status 1 if any recording failed."""
    out = _out(args)
    paths = inputs.expand(args.recording, exclude=out)
    if args.scheduler is not None:
        pool.check_address(args.scheduler)
        where = f"on the Dask cluster at {args.scheduler}"
        workers = 1
    else:
        workers = args.workers or pool.cores()
        where = f"on {min(workers, len(paths))} process(es)"
    open_folder(out, job, args.overwrite)           # a folder of another batch: refused before anything runs
    print(f"rig {job.command}: {len(paths)} recording(s) -> {out} {where}", file=sys.stderr, flush=True)
    progress = Progress(job.command, len(paths))
    res: Outcome = run_batch(job, paths, out, workers=workers, scheduler=args.scheduler,
                             overwrite=args.overwrite, on_row=progress)
    trend = trends.write(out, res.rows)
    if args.json:
        print(json.dumps({"command": job.command, "rows": res.rows, "trends": trend.get("changed")}, indent=1))
    else:
        print(res.paths["markdown"].read_text())
        if trend.get("line"):
            print(trend["line"])
        written = [*res.paths.values(), *(p for k, p in trend.items() if k in ("plot", "csv"))]
        print("written: " + ", ".join(str(p) for p in written))
    print(f"rig {job.command}: {res.done} done now, {res.skipped} done before (resumed), {res.failed} failed, "
          f"in {res.wall_s:.1f} s", file=sys.stderr)
    return 1 if any(r["status"] != "ok" for r in res.rows) else 0


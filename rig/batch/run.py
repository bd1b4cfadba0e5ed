"""A batch: one piece of work (a `Job`: diagnose or identify one recording) done to many recordings, each in its own
output folder, on a local process pool or a Dask cluster (rig.batch.pool), with a summary that is current after
every recording (rig.batch.summary).

The rules:
  * a recording that fails is one row (status "failed", the error in one line; an unexpected exception's
    traceback in its folder's error.txt) and never stops the batch; a worker process that dies takes only the
    recording it was on (the others are handed to a fresh pool);
  * each recording's folder gets batch_row.json last, atomically: the row and the file it was made from (path,
    size, modification time). A batch run again into the same folder skips every recording done with the same
    file (an interrupted batch resumes; a folder that grew gets only its new recordings); a failed one is tried
    again;
  * the output folder's batch.json names the command and the options the results depend on: a run with other
    options into it is refused in one line (a new folder, or --overwrite to start afresh);
  * a worker holds one recording at a time, and only rows come back: the batch never holds its recordings.
"""
from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import os
import resource
import socket
import time
import traceback
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from rig.batch import inputs, pool, summary
from rig.errors import RigError
from rig.runtime.libc import LIBC
from rig.runtime.signals import Terminated

MANIFEST = "batch.json"
MARKER = "batch_row.json"         # written last: the recording is done
STARTED = "batch_started"         # written first: a worker is on it (who died on it, if its pool breaks)
ERROR_FILE = "error.txt"


@dataclass(frozen=True)
class Job:
    """What a batch does to each recording: `work(recording path, output folder) -> row content`
    (rig.batch.rows; RigError for a recording it cannot take), the command's name, and the options its results
    depend on (the same options into the same folder resume; others are refused). `work` must be picklable: a
    module-level function, or a functools.partial of one."""
    command: str
    options: dict
    work: Callable[[str, str], dict]


@dataclass
class Outcome:
    rows: list[dict]                         # every recording of the batch, done before or now, in input order
    done: int = 0                            # done by this run
    skipped: int = 0                         # done before (resumed)
    failed: int = 0
    wall_s: float = 0.0
    paths: dict = field(default_factory=dict)   # the summary's files


def file_identity(path) -> dict | None:
    """An option that is a file (a plant file, a configuration): its path and a hash of its content."""
    if path is None:
        return None
    p = Path(path)
    try:
        digest = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
    except OSError as e:
        raise RigError(f"{p}: cannot read ({e.strerror or e})") from None
    return {"path": str(p.resolve()), "sha256": digest}


def _utc_now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")


def _peak_rss_mb() -> float:
    """This process's peak resident memory since it started its program. Linux's VmHWM: getrusage's ru_maxrss
    would carry the parent's resident size at the fork into a spawned worker."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0                       # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0      # elsewhere: kB on Linux, best effort


def _write_json(path: Path, doc: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, path)                   # atomic: a kill leaves the old file or the new, never half


def _give_back_freed_memory() -> None:
    """Return the heap a recording's analysis freed to the system (glibc keeps it otherwise): the next recording's
    peak then starts from the worker's resident size, not from the last one's high-water mark."""
    try:
        LIBC.malloc_trim(0)
    except AttributeError:        # not glibc: its allocator decides
        pass


def run_one(work, path: str, out: str, name: str, key: dict, run_id: str) -> dict:
    """One recording, in a worker: the work, timed, any failure caught as one line; batch_row.json last."""
    folder = Path(out)
    row = {"recording": name, "path": path, "status": "ok", "error": "", "date_utc": "", "date_source": "",
           "verdict": "", "effects": {}, "parameters": {}, "std": {}, "units": {}, "figures": {}, "notes": [],
           "recording_info": {}}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / STARTED).write_text(f"{socket.gethostname()}:{os.getpid()} {_utc_now()}\n")
        row["date_utc"], row["date_source"] = inputs.recording_date(Path(path))
        content = work(path, out)
        content["recording_info"] = content.pop("recording", {})
        row.update(content)
    except RigError as e:
        row.update(status="failed", error=str(e))
    except Exception as e:                  # noqa: BLE001 -- one line here, the traceback kept in its folder
        row.update(status="failed", error=f"{type(e).__name__}: {e}".splitlines()[0][:300])
        try:
            (folder / ERROR_FILE).write_text(traceback.format_exc())
        except OSError:
            pass
    _give_back_freed_memory()
    row.update(wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0,
               worker=f"{socket.gethostname()}:{os.getpid()}", worker_peak_rss_mb=round(_peak_rss_mb(), 1),
               run=run_id)
    try:
        _write_json(folder / MARKER, {"key": key, "row": row})
        (folder / STARTED).unlink(missing_ok=True)
    except OSError as e:
        row.update(status="failed", error=f"{folder}: cannot write ({e.strerror or e})")
    return row


def _failed_row(name: str, path: str, error: str, run_id: str) -> dict:
    return {"recording": name, "path": path, "status": "failed", "error": error, "date_utc": "",
            "date_source": "", "verdict": "", "effects": {}, "parameters": {}, "std": {}, "units": {},
            "figures": {}, "notes": [], "recording_info": {}, "wall_s": 0.0, "cpu_s": 0.0, "worker": "",
            "worker_peak_rss_mb": 0.0, "run": run_id}


def open_folder(out_root: Path, job: Job, overwrite: bool) -> None:
    """The batch's folder: new, or one of the same command and options (resumed); else one line."""
    try:
        out_root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RigError(f"--out {out_root}: cannot create folder ({e.strerror or e})") from None
    man = out_root / MANIFEST
    if man.is_file() and not overwrite:
        try:
            old = json.loads(man.read_text())
        except (OSError, ValueError):
            raise RigError(f"--out {out_root}: {MANIFEST} is not readable: give another folder or --overwrite") \
                from None
        if old.get("command") != job.command:
            raise RigError(f"--out {out_root}: holds a batch of rig {old.get('command')}, not rig {job.command}: "
                           "give another folder (or --overwrite to start afresh)")
        if old.get("options") != job.options:
            diff = sorted(k for k in set(old.get("options", {})) | set(job.options)
                          if old.get("options", {}).get(k) != job.options.get(k))
            raise RigError(f"--out {out_root}: holds a batch made with other options ({', '.join(diff)} differ): "
                           "run it with the same options to resume, or give another folder (or --overwrite)")
    _write_json(man, {"command": job.command, "options": job.options, "updated_utc": _utc_now()})


def _done_before(folder: Path, key: dict) -> dict | None:
    try:
        doc = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    row = doc.get("row", {})
    return row if doc.get("key") == key and row.get("status") == "ok" else None


def run_batch(job: Job, paths: list[Path], out_root: Path, *, workers: int = 1, scheduler: str | None = None,
              client=None, overwrite: bool = False,
              on_row: Callable[[dict, int, int, bool], None] | None = None) -> Outcome:
    """Do job to every recording of paths into out_root/<name>/; on_row(row, finished, total, resumed) hears
    each one finished (resumed: skipped, done before). The summary (rig.batch.summary) is rewritten after each."""
    out_root = Path(out_root)
    open_folder(out_root, job, overwrite)
    names = inputs.output_names(paths)
    run_id = _utc_now()
    t0 = time.perf_counter()
    rows: list[dict | None] = [None] * len(paths)
    todo = []
    for i, (p, name) in enumerate(zip(paths, names)):
        key = inputs.file_key(p)
        before = None if overwrite else _done_before(out_root / name, key)
        if before is not None:
            rows[i] = before
        else:
            todo.append((i, key))
    res = Outcome(rows=[], skipped=len(paths) - len(todo))
    finished = 0
    for i, r in enumerate(rows):
        if r is not None:
            finished += 1
            if on_row:
                on_row(r, finished, len(paths), True)

    def record(i: int, row: dict) -> None:
        nonlocal finished
        rows[i] = row
        finished += 1
        res.done += 1
        res.failed += row["status"] != "ok"
        summary.write(out_root, job.command, [r for r in rows if r is not None])
        if on_row:
            on_row(row, finished, len(paths), False)

    own = pool.connect(scheduler) if scheduler is not None and client is None else None
    client = client or own
    try:
        if client is not None:
            _check_shared(client, out_root, paths)
        _run_all(todo, job, paths, names, out_root, run_id, workers, client, record)
    except (KeyboardInterrupt, Terminated):      # the rows done so far: a current summary
        summary.write(out_root, job.command, [r for r in rows if r is not None])
        raise
    finally:
        if own is not None:
            own.close()
    res.rows = [r for r in rows if r is not None]
    res.wall_s = time.perf_counter() - t0
    res.paths = summary.write(out_root, job.command, res.rows, final=True)
    return res


def _run_all(todo, job: Job, paths, names, out_root: Path, run_id: str, workers: int, client, record) -> None:
    """The recordings not done yet, longest first (the last to finish are short ones: the workers end together),
    again on a fresh pool for those a dead worker process took down with it. The pool is closed before an
    interrupt goes on up: its workers are stopped then, not when the interpreter exits."""
    todo = sorted(todo, key=lambda ik: -ik[1]["size"])
    for _attempt in range(len(todo) + 1):
        if not todo:
            return
        tasks = [(run_one, (job.work, str(paths[i]), str(out_root / names[i]), names[i], key, run_id))
                 for i, key in todo]
        broken = []
        with contextlib.closing(pool.run_tasks(tasks, workers=workers, client=client)) as outcomes:
            for k, outcome in outcomes:
                i, key = todo[k]
                if isinstance(outcome, BrokenProcessPool):
                    broken.append((i, key))
                elif isinstance(outcome, BaseException):
                    record(i, _failed_row(names[i], str(paths[i]), _died(outcome), run_id))
                else:
                    record(i, outcome)
        todo = _after_break(broken, out_root, names, paths, run_id, record)


def _died(e: BaseException) -> str:
    text = f"{type(e).__name__}: {e}".splitlines()[0][:300]
    if type(e).__name__ == "KilledWorker":
        return f"the Dask workers running it died ({text})"
    return text


def _after_break(broken, out_root: Path, names, paths, run_id: str, record) -> list:
    """A local worker process died: the recording(s) it was on (started, never finished) fail; the others go to
    a fresh pool."""
    if not broken:
        return []
    on_it = [(i, key) for i, key in broken if (out_root / names[i] / STARTED).is_file()]
    for i, _ in on_it or broken:           # nobody on record: all fail rather than loop
        (out_root / names[i] / STARTED).unlink(missing_ok=True)
        record(i, _failed_row(names[i], str(paths[i]), "the worker process died while on it (killed, or out of "
                                                       "memory?)", run_id))
    return [ik for ik in broken if ik not in on_it] if on_it else []


def _check_shared(client, out_root: Path, paths: list[Path]) -> None:
    """On a cluster the workers read the recordings and write the outputs themselves: one line when a worker
    does not see the folders at the same path."""
    folders = [(out_root, "the output folder")]
    folders += [(f, "the recordings' folder") for f in sorted({p.resolve().parent for p in paths})]
    for folder, what in folders:
        blind = pool.workers_see(client, folder)
        if blind:
            raise RigError(f"--scheduler: the Dask worker(s) {', '.join(blind)} do not see {what} "
                           f"{folder.resolve()}: the recordings and --out must be on storage every worker mounts "
                           "at the same path (docs/BATCH.md)")

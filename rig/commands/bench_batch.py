"""`rig bench batch`: a batch of simulated recordings diagnosed four ways, with the figures of docs/BATCH.md.

The recordings: Table 1's actuator on its stand (rig.diagnose.prove's simulation), a linear chirp each, a day
apart, with a concealed transport delay growing from 0 to 3 ms over them. The batch is run
  1. one by one (one process, `--workers 1`): the reference rows and the CPU time;
  2. on the local pool of `--workers` processes: the rows must equal (1)'s exactly (names and values); wall time
     against the CPU time of (2) divided by the workers;
  3. on a Dask LocalCluster of `--workers` processes on 127.0.0.1 (dashboard off): the rows must equal (1)'s;
     the overhead per recording against (2);
  4. as `rig diagnose DIR --out OUT` in a process killed (SIGKILL) when half the recordings are done, then run
     again: the recordings the second run did and skipped.
Memory: each worker's peak RSS after its first recording and after its last (a batch that held its recordings
would grow), against the size of one recording's arrays. The trend over the batch names what changed.

`--memory` runs only the pool, for its memory: the recordings are made and one of them diagnosed alone, each in a
process of its own, so that the batch's own process holds only what the batch needs. The batch's peak (its own
process and every worker's) against that of two recordings per worker: twice the peak of one diagnosed alone.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from multiprocessing import get_context
from pathlib import Path

from rig.batch import trends
from rig.batch import inputs
from rig.batch.run import Job, _peak_rss_mb, run_batch, run_one
from rig.commands.diagnose import diagnose_one
from rig.diagnose.prove import Case, simulate_case
from rig.recordings.rigformat import save_recording_h5
from sim_backend.linear import IDENTIFIED, ActuatorParams

DELAY_S = 0.003
RUN_FIELDS = ("wall_s", "cpu_s", "worker", "worker_peak_rss_mb", "run")     # where and when, not what


def make_recordings(folder: Path, n: int, duration_s: float, fs_hz: float = 1000.0,
                    delay_s: float = DELAY_S) -> list[Path]:
    """n recordings of Table 1's actuator a day apart (rig's HDF5, `created_utc` set), the concealed delay growing
    linearly from 0 to delay_s."""
    folder.mkdir(parents=True, exist_ok=True)
    p0 = ActuatorParams()
    lin = {k: getattr(p0, k) for k in IDENTIFIED}
    paths = []
    for i in range(n):
        d = delay_s * i / max(n - 1, 1)
        case = Case(name=f"day{i:03d}", effects={"transport_delay": {"delay_s": d}} if d else {}, linear=lin,
                    fs_hz=fs_hz, duration_s=duration_s, seed=i)
        day = time.strftime("%Y-%m-%dT03:00:00+00:00", time.gmtime(1_790_000_000 + 86400 * i))
        paths.append(save_recording_h5(simulate_case(case, p0), folder / f"day{i:03d}.h5",
                                       attrs={"created_utc": day}))
    return paths


def what(rows: list[dict]) -> list[dict]:
    """The rows without where and when they were made: what a batch must give wherever it runs."""
    return [{k: v for k, v in r.items() if k not in RUN_FIELDS} for r in rows]


def _timed(job, paths, out, **kw) -> tuple[dict, list[dict]]:
    t0 = time.perf_counter()
    res = run_batch(job, paths, out, **kw)
    wall = time.perf_counter() - t0
    cpu = sum(r["cpu_s"] for r in res.rows)
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "failed": res.failed}, res.rows


def _memory(rows: list[dict], n_samples: int) -> dict:
    by_worker: dict[str, list[float]] = {}
    for r in rows:
        by_worker.setdefault(r["worker"], []).append(r["worker_peak_rss_mb"])
    # the peak only grows, so sorted a worker's figures are its peak after its 1st, 2nd, ... recording. A worker
    # that held its recordings would grow by at least one recording's arrays with each after its second (the
    # first's peak comes before the libraries its plots and reports load lazily)
    after = [sorted(v) for v in by_worker.values()]
    second = [v[min(1, len(v) - 1)] for v in after]
    arrays_mb = 4 * 8 * n_samples / 2 ** 20
    return {"recording_arrays_mb": round(arrays_mb, 2),
            "worker_peak_rss_mb_after_first": [v[0] for v in after],
            "worker_peak_rss_mb_after_second": second,
            "worker_peak_rss_mb_after_last": [v[-1] for v in after],
            "worker_growth_mb_per_recording_after_second": [round((v[-1] - s) / max(len(v) - 2, 1), 2)
                                                             for v, s in zip(after, second)],
            "holds_no_recording": all(v[-1] - s < arrays_mb * max(len(v) - 2, 1) for v, s in zip(after, second)),
            "recordings_per_worker": [len(v) for v in by_worker.values()],
            "parent_peak_rss_mb": round(_peak_rss_mb(), 1)}


def _killed_then_resumed(job, src: Path, out: Path, n: int, workers: int) -> dict:
    """`rig diagnose src --out out` killed when half are done; then the batch again (in this process)."""
    cmd = [sys.executable, "-m", "rig.cli", "diagnose", str(src), "--out", str(out), "--workers", str(workers)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    for line in proc.stderr:
        if f" {n // 2}/{n} " in line:
            break
    os.killpg(proc.pid, signal.SIGKILL)            # the command and its pool's processes
    proc.wait()
    t0 = time.perf_counter()
    res = run_batch(job, sorted(src.glob("*.h5")), out, workers=workers)
    return {"killed_after": n // 2, "done_before_kill": res.skipped, "done_on_resume": res.done,
            "resume_wall_s": round(time.perf_counter() - t0, 2)}, res.rows


def measure(root: Path, n: int, duration_s: float, fs_hz: float, workers: int, say) -> dict:
    from distributed import Client, LocalCluster          # lazy: Dask loaded only for this benchmark

    src = root / "recordings"
    paths = make_recordings(src, n, duration_s, fs_hz)
    job = Job("diagnose", {"seed": 0, "plant": None, "config": None}, partial(diagnose_one, None, None, 0))
    say(f"{n} recordings of {duration_s:g} s at {fs_hz:g} Hz in {src}; load {os.getloadavg()[0]:.1f}")
    serial, ref = _timed(job, paths, root / "one_by_one", workers=1)
    say(f"one by one: {serial}")
    local, rows_pool = _timed(job, paths, root / "pool", workers=workers)
    say(f"pool of {workers}: {local}")
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        dask, rows_dask = _timed(job, paths, root / "dask", client=client)
    say(f"LocalCluster of {workers}: {dask}")
    resume, rows_resumed = _killed_then_resumed(job, src, root / "resumed", n, workers)
    say(f"killed and resumed: {resume}")
    judged = trends.write(root / "pool", rows_pool)
    return {"recordings": n, "duration_s": duration_s, "fs_hz": fs_hz, "workers": workers,
            "load_1min": round(os.getloadavg()[0], 2),
            "one_by_one": serial, "pool": local, "dask_local_cluster": dask,
            "pool_wall_over_cpu_per_worker": round(local["wall_s"] / (local["cpu_s"] / workers), 3),
            "dask_overhead_s_per_recording": round((dask["wall_s"] - local["wall_s"]) / n, 3),
            "pool_rows_equal_one_by_one": what(rows_pool) == what(ref),
            "dask_rows_equal_one_by_one": what(rows_dask) == what(ref),
            "resumed_rows_equal_one_by_one": what(rows_resumed) == what(ref),
            "resume": resume, "memory": _memory(rows_pool, int(round(duration_s * fs_hz))),
            "trends": judged.get("line", "")}


def _alone(fn, *args):
    """fn(*args) in a fresh spawned process of its own (its memory not this one's)."""
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as ex:
        return ex.submit(fn, *args).result()


def measure_memory(root: Path, n: int, duration_s: float, fs_hz: float, workers: int, say) -> dict:
    src = root / "recordings"
    paths = _alone(make_recordings, src, n, duration_s, fs_hz)
    job = Job("diagnose", {"seed": 0, "plant": None, "config": None}, partial(diagnose_one, None, None, 0))
    say(f"{n} recordings of {duration_s:g} s at {fs_hz:g} Hz in {src}; load {os.getloadavg()[0]:.1f}")
    alone = _alone(run_one, job.work, str(paths[-1]), str(root / "alone"), "alone", inputs.file_key(paths[-1]), "")
    say(f"one recording diagnosed alone: peak {alone['worker_peak_rss_mb']} MB")
    local, rows = _timed(job, paths, root / "pool", workers=workers)
    say(f"pool of {workers}: {local}")
    mem = _memory(rows, int(round(duration_s * fs_hz)))
    own = round(_peak_rss_mb(), 1)
    batch_peak = own + sum(mem["worker_peak_rss_mb_after_last"])
    two_per_worker = 2 * alone["worker_peak_rss_mb"] * workers
    mem.update(parent_peak_rss_mb=own, one_alone_peak_rss_mb=alone["worker_peak_rss_mb"],
               batch_peak_rss_mb=round(batch_peak, 1), two_recordings_per_worker_mb=round(two_per_worker, 1),
               batch_within_two_recordings_per_worker=batch_peak <= two_per_worker)
    return {"recordings": n, "duration_s": duration_s, "fs_hz": fs_hz, "workers": workers,
            "load_1min": round(os.getloadavg()[0], 2), "pool": local, "memory": mem}


def run(args) -> int:
    say = (lambda m: None) if args.json else (lambda m: print(f"rig bench batch: {m}", file=sys.stderr, flush=True))
    how = measure_memory if args.memory else measure
    if args.keep is not None:
        res = how(args.keep, args.n, args.duration, args.fs, args.workers, say)
    else:
        with tempfile.TemporaryDirectory(prefix="rig-bench-batch-") as d:
            res = how(Path(d), args.n, args.duration, args.fs, args.workers, say)
    print(json.dumps(res, indent=1))
    return 0

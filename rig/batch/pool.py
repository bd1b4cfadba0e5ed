"""Where the work runs: a local process pool, or a Dask distributed cluster given its scheduler's address.

`run_tasks(tasks, workers=N)` runs (function, arguments) tasks on N processes of this machine (spawned: no forked
numba or BLAS thread state; one BLAS thread each, so that N workers fit N cores; one process: in this one);
`run_tasks(tasks, scheduler="tcp://HOST:PORT")` hands them to that cluster as Dask futures. Either way the
outcomes come back as they finish, as (index, result), or (index, the exception) for a task that raised or whose
process died: the caller decides what a failure means. Tasks are handed out in the order given (the caller puts
the longest first) and every process holds one task at a time.

A cluster must run the same rig as this machine (`check_cluster` compares a fingerprint of rig's source on each
worker) and see the same files at the same paths (the caller checks its folders with `workers_see`).
"""
from __future__ import annotations

import hashlib
import logging
import os
import re
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from multiprocessing import get_context
from pathlib import Path
from typing import Callable, Iterator

from rig.errors import RigError
from rig.runtime.libc import LIBC

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
ADDRESS = re.compile(r"^(tcp|tls)://[^\s:/]+:\d{1,5}$")
CONNECT_TIMEOUT_S = 15.0
WORKERS_TIMEOUT_S = 30.0
PACKAGES = ("rig", "controllers", "sim_backend", "drivers")     # the source that makes the results

Task = tuple[Callable, tuple]
PR_SET_PDEATHSIG = 1               # linux/prctl.h


def cores() -> int:
    """The cores this process may run on (the default number of workers)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:                 # not Linux
        return max(1, os.cpu_count() or 1)


@contextmanager
def _one_thread_each():
    """Spawned workers inherit one BLAS/OpenMP/numba thread each (set around the pool's start)."""
    saved = {k: os.environ.get(k) for k in THREAD_VARS}
    os.environ.update({k: "1" for k in THREAD_VARS})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _die_with_parent(parent_pid: int) -> None:
    """A pool worker ends when the batch's process does (Linux: PR_SET_PDEATHSIG): a batch killed by the operator
    or a scheduler leaves no worker analysing recordings nobody will collect. Elsewhere, the pool's own pipes."""
    try:
        LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() != parent_pid:               # it died before the line above: nobody to work for
            os._exit(1)
    except (OSError, AttributeError):
        pass


def _log_format() -> logging.Formatter | None:
    """The batch's own log line format (`rig COMMAND: warning: ...`, rig.cliargs.log_to_stderr), for its workers."""
    return next((h.formatter for h in logging.getLogger().handlers if h.formatter is not None), None)


def _start_worker(parent_pid: int, log_format: logging.Formatter | None) -> None:
    """A spawned worker: it ends with the batch, and its log lines (a reader's warning) take the batch's form."""
    _die_with_parent(parent_pid)
    if log_format is not None and not logging.getLogger().handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(log_format)
        logging.basicConfig(level=logging.WARNING, handlers=[handler])


def _local(tasks: list[Task], workers: int) -> Iterator[tuple[int, object]]:
    if workers <= 1 or len(tasks) == 1:
        for i, (fn, args) in enumerate(tasks):
            try:
                yield i, fn(*args)
            except Exception as e:              # noqa: BLE001 -- handed to the caller, who decides
                yield i, e
        return
    # spawned processes start at a submit (and again after one died), not with the pool: the setting holds
    # while the pool lives
    with _one_thread_each():
        pool = ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=get_context("spawn"),
                                   initializer=_start_worker, initargs=(os.getpid(), _log_format()))
        whole = False
        try:
            futs = {pool.submit(fn, *args): i for i, (fn, args) in enumerate(tasks)}
            for fut in as_completed(futs):
                try:
                    yield futs[fut], fut.result()
                except Exception as e:              # noqa: BLE001 -- a task's exception, or its process died
                    yield futs[fut], e
            whole = True
        finally:
            if not whole:       # Ctrl-C, SIGTERM, or the caller stopped reading: no recording goes on (nor one
                for proc in list(pool._processes.values()):   # already queued starts) that nobody will collect
                    proc.terminate()
            pool.shutdown(wait=True, cancel_futures=True)


def check_address(address: str) -> str:
    if not ADDRESS.match(address):
        raise RigError(f"--scheduler {address}: expected tcp://HOST:PORT (a Dask scheduler's address, e.g. "
                       "tcp://10.0.0.5:8786)")
    return address


def connect(address: str):
    """A Dask client of the scheduler at address, with at least one worker, all running this rig."""
    from distributed import Client          # lazy: Dask is loaded only for a cluster
    check_address(address)
    try:
        client = Client(address, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise RigError(f"--scheduler {address}: no Dask scheduler answered within {CONNECT_TIMEOUT_S:g} s "
                       f"({type(e).__name__}; start one with `dask scheduler`: docs/BATCH.md)") from None
    try:
        client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
    except (OSError, TimeoutError):
        client.close()
        raise RigError(f"--scheduler {address}: the scheduler has no worker after {WORKERS_TIMEOUT_S:g} s "
                       f"(start them with `dask worker {address} --nthreads 1`: docs/BATCH.md)") from None
    try:
        check_cluster(client)
    except BaseException:
        client.close()
        raise
    return client


def source_fingerprint() -> str:
    """A hash of the source of rig and its sibling packages as installed here."""
    root = Path(__file__).resolve().parents[2]
    h = hashlib.sha256()
    for pkg in PACKAGES:
        for p in sorted((root / pkg).rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def check_cluster(client) -> None:
    """Every worker runs the rig this machine runs (else the same batch would give other results)."""
    mine = source_fingerprint()
    try:
        theirs = client.run(source_fingerprint)
    except Exception as e:                      # noqa: BLE001 -- e.g. rig not installed there
        raise RigError(f"--scheduler: the Dask workers cannot run rig ({type(e).__name__}: {e}): install the same "
                       "rig on every worker (docs/BATCH.md)") from None
    other = sorted(w for w, f in theirs.items() if f != mine)
    if other:
        raise RigError(f"--scheduler: the Dask worker(s) {', '.join(other)} run another version of rig than this "
                       f"machine (source {theirs[other[0]]} there, {mine} here): install the same rig on every "
                       "worker (docs/BATCH.md)")


def workers_see(client, folder: Path) -> list[str]:
    """The workers that do not see folder (the recordings and the outputs must be on storage every worker
    mounts at the same path)."""
    seen = client.run(os.path.isdir, str(Path(folder).resolve()))
    return sorted(w for w, ok in seen.items() if not ok)


def _dask(tasks: list[Task], client) -> Iterator[tuple[int, object]]:
    from distributed import as_completed as dask_completed    # lazy: Dask is loaded only for a cluster
    futs = [client.submit(fn, *args, pure=False, priority=len(tasks) - i) for i, (fn, args) in enumerate(tasks)]
    index = {f.key: i for i, f in enumerate(futs)}
    try:
        for fut in dask_completed(futs, loop=client.loop):
            try:
                out = fut.result()
            except Exception as e:              # noqa: BLE001 -- a task's exception, or its worker died
                out = e
            i = index[fut.key]
            fut.release()                       # the worker may drop the result now
            yield i, out
    finally:
        client.cancel([f for f in futs if not f.done()])


def run_tasks(tasks: list[Task], *, workers: int = 1, scheduler: str | None = None,
              client=None) -> Iterator[tuple[int, object]]:
    """(index, result or exception) of each task as it finishes: on `workers` local processes, or on the Dask
    cluster of `scheduler` (or an open `client` of one)."""
    if client is not None:
        yield from _dask(tasks, client)
    elif scheduler is not None:
        with connect(scheduler) as c:
            yield from _dask(tasks, c)
    else:
        yield from _local(tasks, workers)

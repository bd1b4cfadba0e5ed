"""`rig bench recorder`: what compression costs the recording writer, and what a recording weighs per hour.

The rows are a `rig run` of the simulated rig (four mounts, isolation on under the configured floor
vibration), in simulated time so that the data do not depend on the machine's load (a loaded machine's
late periods and faults change what the controller states do, and with them the size; the two timing
columns are then zero): recorded once without compression, then replayed into fresh recordings, compressed
and not, in alternating rounds (the machine may be shared: the same conditions for both). The replay pushes as fast as
the ring takes rows, so the writer's CPU time per row is its cost; the writer runs in its own process, and
its CPU time is that child's resource usage.
"""
from __future__ import annotations

import resource
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from rig.runtime.clock import SimClock
from rig.runtime.recorder import Recorder, read_recording
from rig.runtime.session import Session

MODES = {"none": None, "gzip": "gzip"}


def record_source(cfg, seconds: float, rate_hz: float, path: Path) -> tuple[list, np.ndarray]:
    """A `rig run` recording (sim backend, simulated time, isolation on); returns (channels, rows)."""
    with Session(cfg, "sim", clock=SimClock(), rate_hz=rate_hz, stop_on_fault=False, record=path) as s:
        s.run(seconds=seconds, activate_after_s=0.05)
        chans = list(s.recorder.channels)
    d = read_recording(path)
    cols = [d[c.name].reshape(len(d[c.name]), -1) for c in chans]
    return chans, np.ascontiguousarray(np.hstack(cols), dtype="<f8")


def replay(chans, rows: np.ndarray, path: Path, rate_hz: float, cfg, compression) -> dict:
    """Push rows into a new recording as fast as the ring takes them; the writer's CPU time and the size."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    rec = Recorder(path, chans, rate_hz=rate_hz, flush_s=cfg.recording.flush_s, ring_s=cfg.recording.ring_s,
                   chunk_rows=cfg.recording.chunk_rows, compression=compression).start()
    for row in rows:
        while rec.free_rows() == 0:
            time.sleep(0.001)
        rec.push_row(row)
    rec.close()
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)      # the writer was reaped by close()
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    size = path.stat().st_size
    path.unlink()
    return {"cpu_s": cpu, "wall_s": wall, "bytes": size, "rows": rec.rows_written, "dropped": rec.dropped_rows}


def bench_recorder(cfg, seconds: float, rate_hz: float, rounds: int, progress=lambda s: None) -> dict:
    with tempfile.TemporaryDirectory(prefix="rig-bench-rec-") as tmp:
        tmp = Path(tmp)
        progress(f"recording {seconds:g} s of `rig run` (sim backend, simulated time) at {rate_hz:g} Hz")
        chans, rows = record_source(cfg, seconds, rate_hz, tmp / "source.h5")
        runs = {m: [] for m in MODES}
        for r in range(rounds):
            for m, comp in MODES.items():
                runs[m].append(replay(chans, rows, tmp / f"{m}.h5", rate_hz, cfg, comp))
                progress(f"round {r + 1}/{rounds} {m}: writer cpu {runs[m][-1]['cpu_s']:.2f} s for "
                         f"{len(rows)} rows, {runs[m][-1]['bytes'] / 1e6:.1f} MB")
    n = len(rows)
    state_cols = sum(c.width for c in chans if c.name == "controller_state")
    out = {"rate_hz": rate_hz, "rows": n, "columns": int(rows.shape[1]), "controller_state_columns": state_cols,
           "rounds": rounds, "modes": {}}
    for m, rs in runs.items():
        cpu = statistics.median(r["cpu_s"] for r in rs)
        size = statistics.median(r["bytes"] for r in rs)
        out["modes"][m] = {
            "writer_cpu_s_per_1e5_rows": round(cpu / n * 1e5, 3),
            "writer_rows_per_cpu_s": round(n / cpu) if cpu > 0 else None,
            "writer_cpu_percent_at_rate": round(100 * cpu / n * rate_hz, 1),
            "bytes_per_row": round(size / n, 1),
            "MB_per_s_at_rate": round(size / n * rate_hz / 1e6, 3),
            "GB_per_hour_at_rate": round(size / n * rate_hz * 3600 / 1e9, 2),
            "rows_lost": int(sum(n - r["rows"] for r in rs)),
        }
    g, z = out["modes"]["gzip"], out["modes"]["none"]
    out["gzip_size_ratio"] = round(g["bytes_per_row"] / z["bytes_per_row"], 3)
    out["gzip_cpu_ratio"] = round(g["writer_cpu_s_per_1e5_rows"] / z["writer_cpu_s_per_1e5_rows"], 2)
    return out

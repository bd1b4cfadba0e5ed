"""The recorder's compressed chunks (issue 17): standard HDF5 filters any reader undoes, every value exact, each
chunk at most half a flush interval, a kill -9 of loop and writer at any moment leaving only intact rows; an
existing file replaced only by a recording with rows; in simulated time a full ring waits instead of dropping."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from rig.runtime.recorder import Channel, Recorder, chunk_rows_for, read_recording

CHANNELS = [Channel("time_s", "s"), Channel("x", "m", 4, ("a", "b", "c", "d")), Channel("state", "", 20)]


def _rows(n: int, k0: int = 0) -> np.ndarray:
    rng = np.random.default_rng(k0 + 1)
    k = np.arange(k0, k0 + n, dtype=float)
    return np.column_stack([k / 5000, k[:, None] + rng.standard_normal((n, 4)), np.cumsum(
        rng.standard_normal((n, 20)), axis=0)])


def test_compressed_chunks_read_back_exactly_with_the_standard_filters(tmp_path):
    rows = _rows(7777)                                      # not a multiple of the chunk length
    with_gzip = tmp_path / "gz.h5"
    rec = Recorder(with_gzip, CHANNELS, rate_hz=5000.0, flush_s=0.05).start()
    for r in rows:
        assert rec.push(*r)
    rec.close()
    with h5py.File(with_gzip) as f:
        d = f["state"]
        assert d.compression == "gzip" and d.shuffle and d.chunks == (125, 20)      # half of 50 ms at 5 kHz
        assert np.array_equal(d[()], rows[:, 5:])                                  # lossless, bit for bit
        assert np.array_equal(f["x"][()], rows[:, 1:5]) and np.array_equal(f["time_s"][()], rows[:, 0])
        assert f["time_s"].id.get_storage_size() < 0.8 * rows[:, 0].nbytes        # and it did compress
    raw = tmp_path / "raw.h5"
    rec = Recorder(raw, CHANNELS, rate_hz=5000.0, compression=None).start()
    for r in rows:
        rec.push(*r)
    rec.close()
    with h5py.File(raw) as f:
        assert f["state"].compression is None and np.array_equal(f["state"][()], rows[:, 5:])


def test_chunk_length_is_at_most_half_a_flush_interval():
    assert chunk_rows_for(5000.0, 0.05, 1024) == 125
    assert chunk_rows_for(100000.0, 0.05, 1024) == 1024
    assert chunk_rows_for(10.0, 0.05, 1024) == 1


_CHILD = """
import sys, time
import numpy as np
from rig.runtime.recorder import Channel, Recorder
chans = [Channel("time_s", "s"), Channel("x", "", 4), Channel("state", "", 20)]
rec = Recorder(sys.argv[1], chans, rate_hz=5000.0).start()
print("ready", flush=True)
k, t0 = 0, time.perf_counter()
while True:
    while k < int((time.perf_counter() - t0) * 5000):
        rec.push(k / 5000, *([k + 0.5] * 4), *([k * 0.25] * 20))
        k += 1
    time.sleep(0.001)
"""


@pytest.mark.parametrize("after_s", [0.23, 0.41, 0.6, 0.77])
def test_kill_9_of_loop_and_writer_leaves_only_intact_rows(tmp_path, after_s):
    """Letting HDF5 compress the growing last chunk rewrote (and moved) it at every flush: a kill between two
    flushes left garbage where the flushed index still pointed (2 of 12 kills)."""
    path = tmp_path / "killed.h5"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(path)], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(after_s)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    end = time.monotonic() + 30
    while True:                            # the writer, killed too, may hold the file lock a moment longer
        try:
            d = read_recording(path)
            break
        except Exception:                  # noqa: BLE001
            if time.monotonic() > end:
                raise
            time.sleep(0.2)
    k = np.arange(len(d["time_s"]))
    assert len(k) > 0
    assert np.array_equal(np.round(d["time_s"] * 5000), k)
    assert np.array_equal(d["x"], np.repeat(k[:, None] + 0.5, 4, axis=1))
    assert np.array_equal(d["state"], np.repeat(k[:, None] * 0.25, 20, axis=1))


def test_an_existing_file_is_replaced_only_by_rows(tmp_path):
    old = tmp_path / "old.h5"
    old.write_bytes(b"yesterday")
    Recorder(old, CHANNELS, rate_hz=5000.0).start().close()                      # nothing recorded
    assert old.read_bytes() == b"yesterday"
    rec = Recorder(old, CHANNELS, rate_hz=5000.0).start()
    rec.push(*_rows(1)[0])
    rec.close()
    assert len(read_recording(old)["time_s"]) == 1
    new = tmp_path / "new.h5"
    Recorder(new, CHANNELS, rate_hz=5000.0).start().close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.h5"]              # no empty file, no partial


def test_simulated_time_waits_for_the_writer_instead_of_dropping(tmp_path):
    rows = _rows(20 * 1024)
    rec = Recorder(tmp_path / "sim.h5", CHANNELS, rate_hz=500.0, ring_s=0.1, chunk_rows=64,
                   wait_when_full=True).start()
    for r in rows:                                          # far faster than the writer drains a 1024-row ring
        assert rec.push(*r)
    rec.close()
    assert rec.dropped_rows == 0 and rec.rows_written == len(rows)
    assert np.array_equal(read_recording(tmp_path / "sim.h5")["state"], rows[:, 5:])

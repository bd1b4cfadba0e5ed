"""Recording that never blocks the loop: a preallocated ring drained by a writer into HDF5 (h5py).

The loop's compiled period writes one row of floats per period straight into the ring (rig/runtime/ring.py: the
producer's rule over the ring's header, the same functions Recorder.push runs; no allocation, no lock,
single producer and single consumer). The writer appends the rows to
chunked, resizable datasets, one per channel (width 1 -> shape (n,), width w -> (n, w)), with the unit as
an attribute, and flushes the file every flush_s (<= 0.1 s): a kill -9 loses at most the last flush
interval and the file still opens. A full ring drops the row and counts it (`dropped_rows`), never waits.

The writer is a thread of its own process (`python -m rig.recorder WRITER`), the ring a shared memory map.
In real-time runs it raises itself to SCHED_FIFO `priority` (WRITER_PRIORITY: below the loop and the drivers,
above everything else), so a loaded machine does not leave rows in the ring for long: what a kill -9 of the
whole process group loses is what is not yet flushed.
Why not a thread of the loop's process: h5py holds the GIL for each call, and a GIL-holding writer delays the
loop's wake-up by up to the interpreter's switch interval.
If the loop's process dies (even by kill -9) the writer sees its command pipe close, drains what is in the
ring and closes the file properly (attribute complete stays False).

Compression (gzip level 1 after a byte shuffle: HDF5's standard shuffle and deflate filters, so any HDF5 tool
reads the files). A chunk holds at most half a flush interval of rows; the writer drains the ring every half
flush interval, compresses each chunk once, when it is complete, and writes it with write_direct_chunk. A
chunk is never written twice, so no chunk moves in the file and a kill -9 finds the flushed chunks where the
flushed index says they are; it loses the rows of the last, incomplete chunk and the ones not yet drained: at
most flush_s. (Letting HDF5 compress a growing last chunk re-compresses it at every flush, and moves it; a
kill between two flushes then left garbage where the index still pointed.) The direct write also skips
h5py's selection path, which costs more than the compression. `rig bench recorder` measures both.

Existing files: a recording never replaces a file with nothing. When the path exists (the command line asked
for --overwrite), the writer records beside it (NAME.partial-PID) and replaces the old file at close if at
least one row was recorded; a recording without a single row is not kept.

Generic: a chirp run records Channel("time_s","s"), Channel("valve_cmd_V","V"), Channel("position_m","m"),
Channel("accel_mps2","m/s^2"); a rig run records per-mount channels of width 4 with labels = MOUNTS.
"""
from __future__ import annotations

import datetime
import json
import logging
import mmap
import os
import select
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rig.runtime import ring as rr
from rig.errors import RecordingError
from rig.runtime.rt import raise_priority

log = logging.getLogger("rig.recorder")

WRITER_PRIORITY = 20             # SCHED_FIFO of the writer in real-time runs (loop 80, drivers 55, HIL devices 50)
COMPRESSION = ("gzip", None, "none")   # gzip: shuffle + deflate level 1 (see the module docstring); None, "none": raw
_GZIP_LEVEL = 1                  # higher levels gain little on float data for much more CPU (rig bench recorder)


@dataclass(frozen=True)
class Channel:
    name: str                 # dataset name, unit in the name at the boundary (e.g. stroke_m)
    unit: str                 # also stored as the dataset's "unit" attribute
    width: int = 1            # values per row (4 for per-mount channels)
    labels: tuple[str, ...] = ()   # names of the columns (e.g. the mounts)
    description: str = ""


class Recorder:
    def __init__(self, path: str | Path, channels: list[Channel], *, rate_hz: float, flush_s: float = 0.05,
                 ring_s: float = 2.0, chunk_rows: int = 1024, attrs: dict | None = None,
                 compression: str | None = "gzip", wait_when_full: bool = False, priority: int = 0) -> None:
        if not channels:
            raise ValueError("a recording needs at least one channel")
        if compression not in COMPRESSION:
            raise ValueError(f"compression: expected one of {', '.join(map(str, COMPRESSION))}, got {compression!r}")
        self.compression = None if compression == "none" else compression
        # simulated time: nothing is late, so a full ring waits for the writer instead of dropping the row (a
        # loop in simulated time outruns the writer; on the real clock the loop must never wait)
        self.wait_when_full = wait_when_full
        self.path = Path(path)
        self.channels = list(channels)
        self.ncols = sum(c.width for c in self.channels)
        self.rate_hz = float(rate_hz)
        self.priority = int(priority)
        self.flush_s = min(float(flush_s), 0.1)
        self.chunk_rows = int(chunk_rows)
        self.attrs = {k: _jsonable(v) for k, v in (attrs or {}).items()}
        self._cap = max(int(ring_s * rate_hz), 4 * chunk_rows, 1024)
        self._rowbytes = 8 * self.ncols
        self._pack = struct.Struct(f"<{self.ncols}d").pack_into
        self._hdr: np.ndarray | None = None      # ring_header(): the producer's state, on the shared map
        self._dropped_final = 0
        self.rows_written = 0
        self.error: str | None = None
        self._proc: subprocess.Popen | None = None
        self._mm: mmap.mmap | None = None
        self._ring: np.ndarray | None = None     # ring_rows() view
        self._final_attrs: dict = {}
        self._death_reported = False         # writer_died() said so: close() does not raise it again

    # ---- as a context manager: started on entry, closed (with the final attributes) on exit -------------
    def __enter__(self) -> "Recorder":
        return self.start() if self._proc is None else self

    def __exit__(self, *exc) -> None:
        self.close(**self._final_attrs)

    def set_final_attrs(self, **attrs) -> None:
        """Attributes written at close by the context manager (stop reason, counters)."""
        self._final_attrs.update(attrs)

    # ---- set-up and tear-down (not in the period) ----------------------------------------------------
    def start(self, timeout_s: float = 60.0) -> "Recorder":
        shm_dir = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
        fd, ring_path = tempfile.mkstemp(prefix="rig-ring-", dir=shm_dir)
        try:
            size = rr.map_bytes(self._cap, self.ncols)
            os.ftruncate(fd, size)
            self._mm = mmap.mmap(fd, size)
            self._hdr = rr.header(self._mm)
        finally:
            os.close(fd)
        spec = {"path": str(self.path), "ring": ring_path, "cap": self._cap, "ncols": self.ncols,
                "channels": [asdict(c) for c in self.channels], "rate_hz": self.rate_hz,
                "flush_s": self.flush_s, "chunk_rows": self.chunk_rows, "attrs": self.attrs,
                "compression": self.compression, "priority": self.priority}
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", "rig.runtime.recorder"], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, text=True, bufsize=1,
                                          start_new_session=False)
            self._proc.stdin.write(json.dumps(spec) + "\n")
            self._proc.stdin.flush()
            ready, _, _ = select.select([self._proc.stdout], [], [], timeout_s)
            line = self._proc.stdout.readline().strip() if ready else ""
        finally:
            try:
                os.unlink(ring_path)              # both sides have it mapped; nothing leaks on a crash
            except OSError:
                pass
        if line != "ready":
            self._kill()
            msg = line[len("error "):] if line.startswith("error ") else (line or "writer did not start")
            raise RecordingError(f"{self.path}: cannot create recording ({msg})")
        return self

    def close(self, **final_attrs) -> None:
        """Drain everything, write final attributes, close. Raises RecordingError if writing failed."""
        if self._proc is None:
            return
        rr.publish(self._hdr)                  # the last row claimed (the loop's stop period)
        try:
            self._send({"close": True, "attrs": {k: _jsonable(v) for k, v in final_attrs.items()},
                        "dropped_rows": self.dropped_rows})
            out, _ = self._proc.communicate(timeout=120)
        except (OSError, ValueError, subprocess.TimeoutExpired) as e:
            self._kill()
            out = f"error writer: {e}"
        for line in (out or "").splitlines():
            if line.startswith("closed "):
                self.rows_written = int(line.split()[1])
            elif line.startswith("error "):
                self.error = line[len("error "):]
        if self._proc.returncode not in (0, None) and not self.error:
            self.error = f"writer exited with code {self._proc.returncode}"
        self._proc = None
        if self._mm is not None:
            self._dropped_final = self.dropped_rows
            self._ring = self._hdr = None
            try:
                self._mm.close()
            except BufferError:                # a ring_rows() view is still held: unmapped with it
                pass
            self._mm = None
        if self.error and not self._death_reported:
            raise RecordingError(f"{self.path}: recording failed: {self.error}")

    def _kill(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()

    def _send(self, msg: dict) -> None:
        self._proc.stdin.write(json.dumps(msg) + "\n")
        self._proc.stdin.flush()

    # ---- the period -----------------------------------------------------------------------------------
    def ring_rows(self) -> np.ndarray:
        """The ring as a (rows, ncols) float64 array on the shared map (rows claimed by rig/runtime/ring.py claim)."""
        if self._ring is None:
            self._ring = rr.rows(self._mm, self._cap, self.ncols)
        return self._ring

    def ring_header(self) -> np.ndarray:
        """The ring's header (rig/runtime/ring.py HEADER, int64 on the shared map): the producer's state. The loop's
        compiled period claims, writes and publishes its rows through it."""
        return self._hdr

    def wait_room(self) -> None:
        """Simulated time (wait_when_full): wait until the writer has made room for one more row, instead of
        the row being dropped (nothing is late there). On the real clock: nothing, the row is dropped."""
        if self.wait_when_full:
            while rr.room(self._hdr, self._cap) <= 0 and self._proc is not None and self._proc.poll() is None:
                time.sleep(0.0005)

    @property
    def committed(self) -> int:
        """Rows published to the ring so far (its head): another reader of the ring (a console) follows it."""
        return int(self._hdr[rr.HEAD]) if self._hdr is not None else self.rows_written

    @property
    def dropped_rows(self) -> int:
        """Rows dropped because the ring was full (counted by the producer, in the ring's header)."""
        return int(self._hdr[rr.DROPPED]) if self._hdr is not None else self._dropped_final

    def push(self, *values: float) -> bool:
        """Append one row (ncols floats, in channel order). Never blocks on the real clock; False if dropped
        (ring full)."""
        self.wait_room()
        r = rr.claim(self._hdr, self._cap)
        if r < 0:
            return False
        self._pack(self._mm, rr.HEADER_BYTES + r * self._rowbytes, *values)
        rr.publish(self._hdr)
        return True

    def push_row(self, row) -> bool:
        """push() for a row already packed in a float64 buffer of ncols values (one copy, no argument
        unpacking). Never blocks on the real clock; False if dropped (ring full)."""
        self.wait_room()
        r = rr.claim(self._hdr, self._cap)
        if r < 0:
            return False
        off = rr.HEADER_BYTES + r * self._rowbytes
        self._mm[off:off + self._rowbytes] = row      # exact size or IndexError: the layout must match
        rr.publish(self._hdr)
        return True

    def event(self, t_s: float, text: str) -> None:
        """A rare text event (lifecycle change, fault reason), written to events/time_s and events/text."""
        if self._proc is not None:
            try:
                self._send({"event": [float(t_s), str(text)]})
            except (OSError, ValueError) as e:
                self.error = self.error or f"writer gone: {e}"

    def free_rows(self) -> int:
        """Rows the ring can take now without dropping (for producers that may wait, not the loop)."""
        return rr.room(self._hdr, self._cap)

    @property
    def rows_committed(self) -> int:
        """Rows the producer has committed (published) to the ring so far."""
        return self.committed

    @property
    def pid(self) -> int | None:
        """The writer process's pid (None when not started)."""
        return self._proc.pid if self._proc is not None else None

    def writer_died(self) -> str | None:
        """None while the writer runs (or before start / after close); else, once reported, what happened.
        A waitpid without blocking: the loop asks at 10 Hz."""
        if self._proc is None or self._proc.poll() is None:
            return None
        self._death_reported = True
        rc = self._proc.returncode
        how = f"killed by signal {-rc}" if rc < 0 else f"exit code {rc}"
        return (f"the writer process of {self.path} ended ({how}) while recording: the rows it had not flushed "
                f"are lost, the file keeps the ones before")

    def written(self) -> int:
        """Rows the writer has taken from the ring so far."""
        return rr.taken(self._hdr) if self._hdr is not None else self.rows_written


def _jsonable(v):
    if isinstance(v, (np.generic,)):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


# ---- the writer process --------------------------------------------------------------------------------
def chunk_rows_for(rate_hz: float, flush_s: float, chunk_rows: int) -> int:
    """Rows per HDF5 chunk: chunk_rows, but at most half a flush interval (a kill -9 loses <= flush_s)."""
    return max(1, min(int(chunk_rows), int(rate_hz * flush_s / 2)))


class _Column:
    """One dataset appended chunk by chunk: rows collect here until their chunk is complete, which is then
    shuffled and deflated (HDF5's filters, done here) and written once with write_direct_chunk."""

    def __init__(self, dset, chunk_rows: int, width: int, compress: bool) -> None:
        self.d = dset
        self.cr = chunk_rows
        self.width = width
        self.buf = np.zeros((chunk_rows, width) if width > 1 else (chunk_rows,), dtype="<f8")
        self.start = 0                 # first row of the chunk in buf
        self.fill = 0                  # rows of it filled
        self.compress = compress
        self.extent = dset.shape[0]    # the dataset's rows (kept here: h5py's shape asks the library each time)

    def append(self, block: np.ndarray) -> None:
        i, n = 0, len(block)
        while i < n:
            k = min(self.cr - self.fill, n - i)
            self.buf[self.fill:self.fill + k] = block[i:i + k]
            self.fill += k
            i += k
            if self.fill == self.cr:
                self._write()
                self.start += self.cr
                self.fill = 0

    def finish(self) -> None:
        """The last, incomplete chunk (at close only: the rows after it in the dataset's extent are none)."""
        if self.fill:
            self.buf[self.fill:] = 0.0
            self._write()

    def _write(self) -> None:
        offset = (self.start,) if self.width == 1 else (self.start, 0)
        if self.compress:
            shuffled = self.buf.view(np.uint8).reshape(-1, 8).T.tobytes()    # the shuffle filter, 8-byte items
            self.d.id.write_direct_chunk(offset, zlib.compress(shuffled, _GZIP_LEVEL), 0)
        else:
            self.d.id.write_direct_chunk(offset, self.buf.tobytes(), 0)


class _Writer:
    def __init__(self, spec: dict) -> None:
        import h5py
        self.spec = spec
        fd = os.open(spec["ring"], os.O_RDWR)
        try:
            self.mm = mmap.mmap(fd, 0)
        finally:
            os.close(fd)
        self.cap, self.ncols = spec["cap"], spec["ncols"]
        self.hdr = rr.header(self.mm)
        self.view = rr.rows(self.mm, self.cap, self.ncols)
        self.channels = [Channel(**{**c, "labels": tuple(c["labels"])}) for c in spec["channels"]]
        path = self.path = Path(spec["path"])
        path.parent.mkdir(parents=True, exist_ok=True)
        # an existing file (--overwrite) is replaced at close, and only by a recording with rows in it
        self.tmp = path.with_name(f"{path.name}.partial-{os.getpid()}") if path.exists() else path
        f = h5py.File(self.tmp, "w")
        f.attrs["rate_hz"] = spec["rate_hz"]
        f.attrs["created_utc"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        f.attrs["channels"] = [c.name for c in self.channels]
        f.attrs["complete"] = False
        for k, v in spec["attrs"].items():
            f.attrs[k] = v
        cr = chunk_rows_for(spec["rate_hz"], spec["flush_s"], spec["chunk_rows"])
        gz = spec.get("compression") == "gzip"
        filters = {"compression": "gzip", "compression_opts": _GZIP_LEVEL, "shuffle": True} if gz else {}
        self.dsets = []
        self.cols = []
        for c in self.channels:
            shape, maxshape, chunks = ((0,), (None,), (cr,)) if c.width == 1 else \
                ((0, c.width), (None, c.width), (cr, c.width))
            d = f.create_dataset(c.name, shape=shape, maxshape=maxshape, chunks=chunks, dtype="<f8", **filters)
            self.cols.append(_Column(d, cr, c.width, gz))
            d.attrs["unit"] = c.unit
            if c.labels:
                d.attrs["labels"] = list(c.labels)
            if c.description:
                d.attrs["description"] = c.description
            self.dsets.append(d)
        self.ev_t = f.create_dataset("events/time_s", shape=(0,), maxshape=(None,), chunks=(64,), dtype="f8")
        self.ev_t.attrs["unit"] = "s"
        self.ev_x = f.create_dataset("events/text", shape=(0,), maxshape=(None,), chunks=(64,),
                                     dtype=h5py.string_dtype())
        f.flush()
        self.f = f
        self.tail = 0
        self.rows = 0

    def drain(self) -> None:
        head = rr.published(self.hdr)
        n = head - self.tail
        if n <= 0:
            return
        i0 = self.tail % self.cap
        if i0 + n <= self.cap:
            rows = self.view[i0:i0 + n].copy()
        else:
            rows = np.concatenate([self.view[i0:], self.view[:n - (self.cap - i0)]])
        self.tail = head
        rr.release(self.hdr, head)              # the slots are free again
        col, total = 0, self.rows + n
        for c, d, w in zip(self.channels, self.dsets, self.cols):
            # the extent covers the complete chunks only until close: a kill -9 then leaves no row unwritten
            done = total - (total % w.cr)
            if done != w.extent:
                d.resize((done,) if c.width == 1 else (done, c.width))
                w.extent = done
            w.append(rows[:, col] if c.width == 1 else rows[:, col:col + c.width])
            col += c.width
        self.rows = total

    def events(self, evs: list) -> None:
        if not evs:
            return
        k = self.ev_t.shape[0]
        self.ev_t.resize((k + len(evs),))
        self.ev_x.resize((k + len(evs),))
        self.ev_t[k:] = [e[0] for e in evs]
        self.ev_x[k:] = [e[1] for e in evs]

    def finish(self, msg: dict | None) -> None:
        self.drain()
        for c, d, w in zip(self.channels, self.dsets, self.cols):
            d.resize((self.rows,) if c.width == 1 else (self.rows, c.width))
            w.finish()
        if msg is not None:
            for k, v in msg.get("attrs", {}).items():
                self.f.attrs[k] = v
            self.f.attrs["dropped_rows"] = msg.get("dropped_rows", 0)
            self.f.attrs["complete"] = True
        else:
            self.f.attrs["ended"] = "the recording process ended without closing (crash or kill)"
        self.f.close()
        if not self.rows:
            self.tmp.unlink()                 # nothing recorded: nothing kept, nothing replaced
        elif self.tmp != self.path:
            os.replace(self.tmp, self.path)


def _say(text: str) -> None:
    """One status line to the loop's process; if it is gone, say nothing (and let exit not complain)."""
    try:
        print(text, flush=True)
    except OSError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())


def _writer_main() -> int:
    import signal
    # Ctrl-C / SIGTERM to the process group are the loop's to handle; the writer ends on its pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    stdin = sys.stdin
    spec = json.loads(stdin.readline())
    raise_priority(spec.get("priority", 0))
    try:
        w = _Writer(spec)
    except Exception as e:   # noqa: BLE001 - one line back to the loop's process
        _say(f"error {e.__class__.__name__}: {e}")
        return 1
    _say("ready")
    fd = stdin.fileno()
    buf = b""
    flush_s = spec["flush_s"]
    last_flush = time.monotonic()
    try:
        while True:
            r, _, _ = select.select([fd], [], [], flush_s / 2)
            msgs, closed = [], False
            if r:
                chunk = os.read(fd, 65536)
                if not chunk:
                    closed = True                 # the loop's process is gone
                buf += chunk
                *lines, buf = buf.split(b"\n")
                msgs = [json.loads(x) for x in lines if x.strip()]
            close_msg = next((m for m in msgs if m.get("close")), None)
            w.events([m["event"] for m in msgs if "event" in m])
            if close_msg is not None or closed:
                w.finish(close_msg)
                _say(f"closed {w.rows}")
                return 0
            now = time.monotonic()
            if now - last_flush >= flush_s * 0.5 or not r:
                w.drain()
                w.f.flush()
                last_flush = now
    except Exception as e:   # noqa: BLE001
        _say(f"error {e.__class__.__name__}: {e}")
        try:
            w.f.flush()
        except Exception:    # noqa: BLE001
            pass
        return 1


def read_recording(path: str | Path) -> dict:
    """Open a recording (also one cut short by a crash): {"attrs": {...}, "units": {...}, name: array, ...,
    "events": [(t_s, text), ...]}."""
    import h5py
    p = Path(path)
    try:
        f = h5py.File(p, "r")
    except (OSError, FileNotFoundError) as e:
        raise RecordingError(f"{p}: cannot open recording ({e})") from None
    with f:
        out: dict = {"attrs": {k: _plain(v) for k, v in f.attrs.items()}, "units": {}}
        for name, obj in f.items():
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
                out["units"][name] = _plain(obj.attrs.get("unit", ""))
        # a crash between two datasets' appends leaves them one block apart: keep the common rows
        names = [n for n in out if n not in ("attrs", "units")]
        single = [k for k in names if np.ndim(out[k]) == 0]
        if single:
            raise RecordingError(f"{p}: dataset {single[0]}: a single value, expected one value per row")
        if names:
            n = min(len(out[k]) for k in names)
            if any(len(out[k]) != n for k in names) and out["attrs"].get("complete") is True:
                ref = "time_s" if "time_s" in names else max(names, key=lambda k: len(out[k]))
                k = next(k for k in names if len(out[k]) != len(out[ref]))
                raise RecordingError(f"{p}: dataset {k} has {len(out[k])} rows, {ref} {len(out[ref])}, in a recording "
                                     f"its writer closed: changed since it was written")
            if any(len(out[k]) != n for k in names):
                out["attrs"]["truncated_to_rows"] = n
                for k in names:
                    out[k] = out[k][:n]
        if "events" in f:
            t = f["events/time_s"][()]
            x = [s.decode() if isinstance(s, bytes) else s for s in f["events/text"][()]]
            n = min(len(t), len(x))
            out["events"] = list(zip(t[:n].tolist(), x[:n]))
        else:
            out["events"] = []
    return out


def _plain(v):
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray):
        return [x.decode() if isinstance(x, bytes) else x for x in v.tolist()]
    if isinstance(v, np.generic):
        return v.item()
    return v


if __name__ == "__main__":
    sys.exit(_writer_main())

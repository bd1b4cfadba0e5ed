"""The one reader of recording files: format detection, gzip, CSV and text tables, MATLAB .mat (v5 with scipy, v7.3
with h5py) and HDF5. It returns what the file holds (named columns, variables, datasets), never a Recording:
rig's own formats (rig/recordings/rigformat.py) and a plant file's signal map (rig/recordings/signalmap.py) each
pick their signals from it. Every problem with a file is one RecordingError line naming the file; an HDF5 file
its writer did not close is read as it is, and said in one warning line (`warn_if_incomplete`)."""
from __future__ import annotations

import gzip
import io
import logging
import os
import stat
import zlib
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.errors import RecordingError

GZIP_MAGIC = b"\x1f\x8b"
HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
MAT_MAGIC = b"MATLAB"
FORMATS = ("csv", "mat", "hdf5")                 # what a plant file may declare
FOUND = {None: "neither HDF5 nor MATLAB", "mat": "a MATLAB v5 file", "mat73": "a MATLAB v7.3 file",
         "hdf5": "an HDF5 file"}


def read_bytes(path: Path) -> bytes:
    """A recording file's content; missing, not a regular file, unreadable or empty: RecordingError."""
    source = str(path)
    check_file(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:            # gone since check_file
        raise RecordingError(f"{source}: no such file") from None
    except OSError as e:
        raise RecordingError(f"{source}: cannot read ({e.strerror or e})") from None
    if not raw:
        raise RecordingError(f"{source}: empty file")
    return raw


def check_file(path, missing: str = "no such file") -> None:
    """The one rule for a recording's path, before any reader opens it: a regular file, else one RecordingError
    line saying what it is (`missing`: the words for a path that does not exist). A named pipe or device is
    refused, not opened: reading it waits for a writer."""
    try:
        mode = Path(path).stat().st_mode
    except FileNotFoundError:
        raise RecordingError(f"{path}: {missing}") from None
    except OSError as e:
        raise RecordingError(f"{path}: cannot read ({e.strerror or e})") from None
    if stat.S_ISDIR(mode):
        raise RecordingError(f"{path}: is a directory, expected a recording file")
    if not stat.S_ISREG(mode):
        raise RecordingError(f"{path}: {_kind(mode)}, expected a regular file (a recording)")


def _kind(mode: int) -> str:
    return ("a named pipe" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else
            "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")


def file_format(raw: bytes, path: Path, declared: str | None = None, where: str = "") -> str:
    """csv, mat, mat73 (HDF5 behind MATLAB's 512-byte header) or hdf5: the content's magic bytes, checked against
    a declared format (one of FORMATS; `where` names the declaration) when given, else the name's suffix."""
    mat73 = raw.startswith(MAT_MAGIC) and raw[512:520] == HDF5_MAGIC
    found = ("mat73" if mat73 else "hdf5" if raw.startswith(HDF5_MAGIC) else
             "mat" if raw.startswith(MAT_MAGIC) else None)
    if declared is not None:
        fits = {"csv": (None,), "mat": (None, "mat", "mat73"), "hdf5": ("hdf5", "mat73")}[declared]
        if found not in fits:
            raise RecordingError(f"{path}: not a {declared} file ({where}): it is {FOUND[found]}")
        return found or declared
    if found:
        return found
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        raise RecordingError(f"{path}: not an HDF5 file (no HDF5 signature)")
    return "mat" if suffix == ".mat" else "csv"


def gunzip(raw: bytes, source: str) -> bytes:
    try:
        return gzip.decompress(raw)
    except EOFError:
        raise RecordingError(f"{source}: truncated gzip file (compressed stream ends early)") from None
    except (gzip.BadGzipFile, zlib.error, OSError) as e:
        raise RecordingError(f"{source}: corrupt gzip file ({e})") from None


def csv_text(raw: bytes, source: str, path: Path | None = None) -> str:
    """A CSV or text file's content as text (gunzipped when compressed: the magic bytes or a .gz name); binary
    data: RecordingError."""
    if raw.startswith(GZIP_MAGIC) or (path is not None and path.suffix.lower() == ".gz"):
        raw = gunzip(raw, source)
        if raw.startswith(GZIP_MAGIC):
            raise RecordingError(f"{source}: gzip inside gzip, expected one compressed CSV")
    if b"\x00" in raw:
        raise RecordingError(f"{source}: binary data, not a CSV recording")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise RecordingError(f"{source}: binary data, not a CSV recording (byte {e.start} is not text)") from None


def is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class Table:
    """A delimited text file: its column names (None without a header row), the cells of its first line, and its
    data rows as (line number, text)."""
    source: str
    delimiter: str | None            # None: runs of spaces and tabs
    names: list[str] | None
    first: list[str]
    rows: list[tuple[int, str]]
    quoted: bool

    def split(self, ln: str) -> list[str]:
        return [c.strip().strip('"').strip() for c in ln.split(self.delimiter)]

    def columns(self, use: list[int], every_row: int | None = None) -> np.ndarray:
        """The numbers of columns `use` (rows x len(use)); every_row: each row must have exactly that many
        fields. A bad row: one line naming it."""
        try:
            data = np.loadtxt(io.StringIO("\n".join(ln for _, ln in self.rows)), delimiter=self.delimiter,
                              usecols=None if every_row else use, ndmin=2, dtype=float, comments=None,
                              **({"quotechar": '"'} if self.quoted else {}))
            if every_row and data.shape[1] != every_row:
                raise ValueError("column count")
        except (ValueError, OverflowError):
            raise self._bad_row(use, every_row) from None
        return data[:, use] if every_row else data

    def _bad_row(self, use: list[int], every_row: int | None) -> RecordingError:
        for lineno, ln in self.rows:
            if every_row:
                cells = ln.split(self.delimiter)
                if len(cells) != every_row:
                    return RecordingError(f"{self.source}: line {lineno} has {len(cells)} fields, expected "
                                          f"{every_row}: {ln[:80]!r}")
                if not all(is_number(c) for c in cells):
                    return RecordingError(f"{self.source}: line {lineno} is not numeric: {ln[:80]!r}")
                continue
            cells = [c.strip().strip('"') for c in ln.split(self.delimiter)]
            if len(cells) <= max(use):
                return RecordingError(f"{self.source}: line {lineno} has {len(cells)} fields, expected at least "
                                      f"{max(use) + 1}: {ln[:80]!r}")
            for c in use:
                if not is_number(cells[c]):
                    return RecordingError(f"{self.source}: line {lineno}, column {c}: {cells[c][:30]!r} is not a "
                                          "number")
        return RecordingError(f"{self.source}: could not parse the numeric rows")


SEPARATORS = ("\t", ";", ",")
SEPARATOR_NAMES = {"\t": "tab", ";": "';'", ",": "','"}


def read_table(text: str, source: str, *, delimiter: str | None = ",", skip_rows: int = 0,
               comment: str | None = None, header: bool | None = None, quoted: bool = True,
               expected: str = "") -> Table:
    """A delimited text file: `delimiter` one character, "whitespace" (runs of spaces and tabs) or None (the first
    of tab, ";" and "," found in the first line, else whitespace); `skip_rows` lines of preamble; lines starting
    with `comment` and blank lines left out; `header`: the first line names the columns (None: when it is not all
    numbers). A header that is one field on the delimiter asked for but several on another separator is refused
    naming the separator the file looks to have (`expected`: what the caller wants, for the message)."""
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if i >= skip_rows]
    lines = [(i, ln) for i, ln in lines if ln.strip() and not (comment and ln.lstrip().startswith(comment))]
    if not lines:
        raise RecordingError(f"{source}: no data rows (after {skip_rows} skipped lines and comments)")
    delim = (None if delimiter == "whitespace" else      # None: any run of spaces and tabs
             delimiter or next((d for d in SEPARATORS if d in lines[0][1]), None))
    table = Table(source, delim, None, [], [], quoted)
    first = table.split(lines[0][1])
    # empty cells (a delimiter ending every line, as MATLAB's `save -ascii -tabs` and the DaISy files write)
    # say nothing: only a cell that is text makes the first line a header
    has_header = header if header is not None else not all(is_number(c) for c in first if c)
    if has_header and delimiter in SEPARATORS and len(first) == 1:
        other = next((d for d in SEPARATORS if len(lines[0][1].split(d)) > 1), None)
        if other is not None:
            raise RecordingError(f"{source}: the header is one field on {SEPARATOR_NAMES[delimiter]} but "
                                 f"{len(lines[0][1].split(other))} on {SEPARATOR_NAMES[other]}: the file looks "
                                 f"{SEPARATOR_NAMES[other]}-separated; expected {SEPARATOR_NAMES[delimiter]}-separated"
                                 + (f" {expected}" if expected else ""))
    rows = lines[1:] if has_header else lines
    if not rows:
        raise RecordingError(f"{source}: no data rows after the header")
    return Table(source, delim, first if has_header else None, first, rows, quoted)


def read_mat(raw: bytes, source: str) -> dict:
    """A MATLAB v5/v7 file's variables (scipy.io.loadmat, arrays as stored)."""
    import scipy.io      # lazy: scipy.io is loaded only for .mat files
    try:
        return scipy.io.loadmat(io.BytesIO(raw), squeeze_me=False)
    except Exception as e:   # scipy raises MatReadError/ValueError/TypeError/... on damaged files
        raise RecordingError(f"{source}: not a readable MATLAB file ({type(e).__name__}: {e})"[:300]) from None


@contextmanager
def open_hdf5(path: Path, source: str, what: str = "file"):
    """An HDF5 file (or MATLAB v7.3) open for reading; a damaged one: one RecordingError line (`what` the file
    should have been)."""
    import h5py          # lazy: h5py is loaded only for HDF5 files
    try:
        with h5py.File(path, "r") as f:
            warn_if_incomplete(f, path, source)
            yield f
    except RecordingError:
        raise
    except Exception as e:   # h5py raises OSError/KeyError/ValueError/TypeError for damaged files
        raise RecordingError(f"{source}: not a readable HDF5 {what} ({type(e).__name__}: {e})"[:300]) from None


log = logging.getLogger("rig.recordings")
_warned: set = set()


def warn_if_incomplete(f, path: Path, source: str) -> None:
    """A file whose writer did not close it (rig.runtime.recorder keeps the root attribute complete = False until
    the run closes its file: a crash, a kill or a run still going) may be cut short: the rig never uses such data
    silently. One warning line, once per file and version in a process, with what is known: why it ended (the
    recorder's `ended`), the rows every root dataset has (what the readers keep) and their time span."""
    if bool(f.attrs.get("complete", True)):
        return
    try:
        st = os.stat(path)
        key = (str(Path(path).resolve()), st.st_mtime_ns, st.st_size)
    except OSError:
        key = (source,)
    if key in _warned:
        return
    _warned.add(key)
    ended = f.attrs.get("ended", "")
    ended = ended.decode(errors="replace") if isinstance(ended, bytes) else str(ended)
    sets = [d for d in f.values() if getattr(d, "ndim", 0) >= 1 and getattr(d, "shape", None)]
    held = ""
    if sets:
        rows = min(d.shape[0] for d in sets)
        t = f.get("time_s")
        ends = (float(t[0]), float(t[rows - 1])) if rows and t is not None and getattr(t, "ndim", 0) == 1 else ()
        span = f" (t = {ends[0]:.6g} to {ends[1]:.6g} s)" if ends and ends[1] > ends[0] else ""
        held = f"; it holds {rows} rows{span}, used as they are"
    log.warning("%s: the run ended before the recording was closed (attribute complete = false%s): it may be cut "
                "short%s", source, f"; {ended}" if ended else "", held)


def vector(a) -> np.ndarray:
    """A variable as a vector when it is one in either orientation (MATLAB stores (n, 1) or (1, n))."""
    a = np.asarray(a)
    return a.ravel() if a.ndim == 2 and 1 in a.shape else a

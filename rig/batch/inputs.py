"""Which recordings a batch is given, the folder each one's outputs go to, and each one's date.

Arguments: files, folders (their recording files, not their subfolders) and globs (quoted, so that the shell
leaves them: `'runs/**/*.h5'` takes subfolders too). A file named outright must exist (one line before anything
runs); a folder or a glob that finds no recording is one line too. Files under the batch's own output folder are
never taken (its fit.csv are outputs, not recordings).
"""
from __future__ import annotations

import datetime as dt
import glob
import os
from pathlib import Path

from rig.errors import RecordingError, RigError
from rig.recordings.files import HDF5_MAGIC, open_hdf5

# what rig's readers take (rig/recordings/files.py); a folder is searched for these
SUFFIXES = (".csv", ".csv.gz", ".txt", ".txt.gz", ".tsv", ".dat", ".h5", ".hdf5", ".mat")
GLOB_CHARS = "*?["
DATE_ATTR = "created_utc"          # rig.runtime.recorder writes it into every HDF5 recording


def is_glob(arg: str) -> bool:
    return any(c in arg for c in GLOB_CHARS)


def is_batch(args: list) -> bool:
    """Several recordings, a folder or a glob make a batch; one file is the one-recording command of old."""
    return len(args) != 1 or is_glob(str(args[0])) or Path(args[0]).is_dir()


def _recording_name(p: Path) -> bool:
    return p.is_file() and p.name.lower().endswith(SUFFIXES)


def expand(args: list, *, exclude: Path | None = None) -> list[Path]:
    """The recordings named by the arguments, each once, in the order given (a folder's and a glob's sorted)."""
    skip = exclude.resolve() if exclude is not None else None
    out: list[Path] = []
    for arg in args:
        text = str(arg)
        if is_glob(text):
            found = [Path(m) for m in sorted(glob.glob(text, recursive=True)) if Path(m).is_file()]
            if not found:
                raise RigError(f"{text}: no file matches")
        elif Path(text).is_dir():
            found = sorted(p for p in Path(text).iterdir() if _recording_name(p))
            if not found:
                raise RigError(f"{text}: no recording in the folder (looked for {', '.join(SUFFIXES)}; "
                               f"a glob such as '{text}/**/*.h5' takes subfolders)")
        elif Path(text).is_file():
            found = [Path(text)]
        else:
            raise RigError(f"{text}: no such file or folder")
        out += found
    seen, unique = set(), []
    for p in out:
        r = p.resolve()
        if r in seen or (skip is not None and r.is_relative_to(skip)):
            continue
        seen.add(r)
        unique.append(p)
    if not unique:
        raise RigError(f"no recording left: every file given is inside the output folder {exclude}")
    return unique


def _stem(p: Path) -> str:
    name = p.name
    for s in sorted(SUFFIXES, key=len, reverse=True):
        if name.lower().endswith(s):
            return name[: -len(s)] or name
    return p.stem or name


def output_names(paths: list[Path]) -> list[str]:
    """The output folder of each recording: its name without the suffix; where two share a name, the folders
    they sit in are put in front (runs/mar/a.h5, runs/apr/a.h5 -> mar__a, apr__a)."""
    stems = [_stem(p) for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    resolved = [p.resolve() for p in paths]
    root = Path(os.path.commonpath([str(r.parent) for r in resolved]))
    names = []
    for r, s in zip(resolved, stems):
        parts = r.parent.relative_to(root).parts
        names.append("__".join((*parts, s)))
    if len(set(names)) != len(names):          # the same stem twice in one folder: a.csv and a.h5
        names = ["__".join((*r.parent.relative_to(root).parts, r.name.replace(".", "_"))) for r in resolved]
    return names


def file_key(path: Path) -> dict:
    """What says a recording file is the one a result was made from: its path, size and modification time."""
    try:
        st = path.stat()
    except OSError:                      # gone since it was listed: its work says so, in one line
        return {"path": str(path.resolve()), "size": 0, "mtime_ns": 0}
    return {"path": str(path.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _utc(text: str) -> str:
    t = dt.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.timezone.utc)
    return t.astimezone(dt.timezone.utc).isoformat(timespec="seconds")


def recording_date(path: Path) -> tuple[str, str]:
    """(the date in UTC, ISO 8601; where it came from): an HDF5 recording's `created_utc` attribute (rig's
    recorder writes it when the run starts), else the file's modification time."""
    try:
        with path.open("rb") as f:
            hdf5 = f.read(8) == HDF5_MAGIC
        if hdf5:
            with open_hdf5(path, str(path)) as h:
                v = h.attrs.get(DATE_ATTR)
            if v is not None:
                return _utc(v.decode() if isinstance(v, bytes) else str(v)), DATE_ATTR
    except (OSError, ValueError, RecordingError):
        pass                              # unreadable or a malformed date: the file's own time says it
    mtime = dt.datetime.fromtimestamp(path.stat().st_mtime, dt.timezone.utc)
    return mtime.isoformat(timespec="seconds"), "file mtime"

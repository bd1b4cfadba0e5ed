"""The small text files an operator names: a config, a plant file, a calibration, a modal model, a --script, a
reference profile, the control file.

One rule for all of them: a regular file of UTF-8 text, else one line naming the file. A pipe or a device is
refused before it is opened: opening a FIFO for reading waits for a writer, and no signal ends that wait.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

from rig.errors import RigError


def read_text(path, what: str, error: type[RigError] = RigError, encoding: str = "utf-8") -> str:
    """The file's text; `error` naming the file and `what` it is for: missing, a folder, a pipe or device,
    unreadable, or not text in `encoding`."""
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        raise error(f"{p}: {what} not found") from None
    except OSError as e:
        raise error(f"{p}: cannot read the {what} ({e.strerror or e})") from None
    if not stat.S_ISREG(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a pipe or device"
        raise error(f"{p}: the {what} is {kind}, expected a regular file")
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise error(f"{p}: cannot read the {what} ({e.strerror or e})") from None
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as e:
        raise error(f"{p}: the {what} is not {encoding.upper().replace('-SIG', '')} text (byte {e.start} is "
                    f"{raw[e.start]:#04x}); expected a text file") from None

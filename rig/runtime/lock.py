"""One process per rig: a lock file per device the run drives, so a second process driving the same devices
is refused with one line naming the holder (pid, command line, since when) before it touches any of them.

flock(2) on a file in the lock directory (RIG_LOCK_DIR, else /run/lock/rig, else <tmp>/rig-locks): the kernel
releases it when the holder ends in any way (kill -9 included), so a lock left by a dead process is never in
the way; the holder's line in the file is only read while the lock is held. The descriptors are not inherited
by child processes (the recorder's writer, emulated devices), which could otherwise outlive the holder.
"""
from __future__ import annotations

import errno
import fcntl
import os
import re
import sys
import tempfile
import time
from pathlib import Path

from rig.errors import ConfigError


def lock_dir() -> Path:
    env = os.environ.get("RIG_LOCK_DIR")
    if env:
        return Path(env)
    run = Path("/run/lock")
    if run.is_dir() and os.access(run, os.W_OK):
        return run / "rig"
    return Path(tempfile.gettempdir()) / "rig-locks"


def _file_name(device: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", device).strip("_")[:120] + ".lock"


class RigLock:
    """Locks `devices` (names such as `can:socketcan:can0`) on entry, releases them on exit."""

    def __init__(self, devices, command: str | None = None) -> None:
        self.devices = tuple(devices)
        self.command = command if command is not None else " ".join([Path(sys.argv[0]).name] + sys.argv[1:])
        self._fds: list[int] = []

    def __enter__(self) -> "RigLock":
        if not self.devices:
            return self
        d = lock_dir()
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ConfigError(f"lock directory {d}: cannot create it ({e.strerror}); set RIG_LOCK_DIR") from None
        try:
            for dev in self.devices:
                self._take(d / _file_name(dev), dev)
        except BaseException:
            self.__exit__()
            raise
        return self

    def _take(self, path: Path, dev: str) -> None:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as e:
            raise ConfigError(f"{dev}: cannot open the lock file {path} ({e.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = os.pread(fd, 4096, 0).decode(errors="replace").strip().replace("\n", ", ") or "unknown"
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise ConfigError(f"{dev} is in use by another process ({holder}): one process drives a rig at "
                                  f"a time (lock file {path})") from None
            raise ConfigError(f"{dev}: cannot lock {path} ({e.strerror})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}, {self.command!r}, since "
                      f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode(), 0)
        self._fds.append(fd)

    def __exit__(self, *exc) -> None:
        for fd in self._fds:
            try:
                os.ftruncate(fd, 0)
            except OSError:
                pass
            os.close(fd)                     # releases the flock
        self._fds.clear()

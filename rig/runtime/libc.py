"""The C library as the running process already has it, for the calls Python does not wrap (clock_nanosleep,
futex, mlockall).

Loaded once from the process itself, never through ctypes.util.find_library: that runs `ldconfig -p` in a
subprocess, and its fork and exec hold the real-time tasks of every CPU on a kernel without preemption
(drivers/README.md, the run's own stalls)."""
from __future__ import annotations

import ctypes

LIBC = ctypes.CDLL(None, use_errno=True)


class Timespec(ctypes.Structure):
    """struct timespec."""
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]

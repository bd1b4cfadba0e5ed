"""The C library as the running process already has it, for the calls Python does not wrap (clock_nanosleep,
futex, mlockall).

Loaded by name from the process itself, never through ctypes.util.find_library: that runs `ldconfig -p` in a
subprocess, and the fork and exec of it in a real-time process held every CPU's real-time tasks for about a
millisecond (a kernel without preemption) each time a clock was made, at the start of every run."""
from __future__ import annotations

import ctypes

LIBC = ctypes.CDLL(None, use_errno=True)


class Timespec(ctypes.Structure):
    """struct timespec."""
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]

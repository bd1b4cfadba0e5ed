"""Real-time hygiene for the loop thread, where the OS allows it.

SCHED_FIFO and CPU affinity apply to the calling thread only (Linux), so call `enter_realtime` from the loop
thread AFTER starting helper threads (recorder writer, status), which then keep the normal policy.
Anything not allowed gives one logged note and the run carries on.
"""
from __future__ import annotations

import ctypes
import gc
import logging
import os
import struct
import sys
from dataclasses import dataclass, field

from rig.runtime.idle_poll import IdlePollers
from rig.runtime.idle_poll import wanted as idle_poll_wanted
from rig.runtime.libc import LIBC

log = logging.getLogger("rig.rt")

MCL_CURRENT, MCL_FUTURE = 1, 2


@dataclass
class RtState:
    """What was applied, and how to undo it."""
    notes: list[str] = field(default_factory=list)
    fifo: bool = False
    cpu: int | None = None
    mlocked: bool = False
    gc_frozen: bool = False
    cpu_latency_us: int | None = None       # PM QoS request held (None: none)
    idle_pollers: int = 0                   # CPUs kept polling (rig/runtime/idle_poll.py)
    _pollers: object = None
    _qos_fd: int | None = None
    _old_sched: tuple | None = None
    _old_affinity: set | None = None
    _old_switch: float | None = None
    _gc_was_enabled: bool = True

    def summary(self) -> str:
        parts = [f"SCHED_FIFO={'yes' if self.fifo else 'no'}", f"cpu={self.cpu if self.cpu is not None else 'any'}",
                 f"mlockall={'yes' if self.mlocked else 'no'}", f"gc.freeze={'yes' if self.gc_frozen else 'no'}"]
        if self.cpu_latency_us is not None:
            parts.append(f"cpu_dma_latency={self.cpu_latency_us}us")
        if self.idle_pollers:
            parts.append(f"idle_poll={self.idle_pollers} CPUs")
        return " ".join(parts)


_fifo_noted = False


def raise_priority(priority: int) -> bool:
    """SCHED_FIFO(priority) for the calling thread (driver, emulator and helper threads each raise
    themselves when they start: on Linux it applies to the calling thread only); False and one log note where
    it is not allowed, and the thread carries on at normal priority."""
    global _fifo_noted
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (OSError, ValueError) as e:
        if not _fifo_noted:
            _fifo_noted = True
            log.info("threads: SCHED_FIFO %d not allowed (%s); normal priority", priority, e)
        return False


def freeze_heap() -> None:
    """The set-up's objects (the imported libraries: tens of thousands) to the permanent generation, for a
    device's or an I/O process's cycle: a full collection in the cycle then scans only what the cycle made,
    not the whole heap (a 50-70 ms pause with scipy and canopen loaded, measured here). Collection stays on."""
    gc.collect()
    gc.freeze()


def _note(state: RtState, text: str) -> None:
    state.notes.append(text)
    log.warning("real-time: %s; carrying on without it", text)


PM_QOS_DEVICE = "/dev/cpu_dma_latency"


def request_cpu_latency(st: RtState, us: int, device: str = PM_QOS_DEVICE) -> None:
    """Hold a PM QoS request: the kernel keeps CPUs out of idle states slower to leave than `us` for as long
    as the file stays open (closed by leave_realtime, or by the kernel when the process dies)."""
    try:
        fd = os.open(device, os.O_WRONLY)
    except OSError as e:
        _note(st, f"CPU wake-up latency request not allowed ({device}: {e.strerror})")
        return
    try:
        os.write(fd, struct.pack("i", int(us)))
    except OSError as e:
        os.close(fd)
        _note(st, f"CPU wake-up latency request refused ({device}: {e.strerror})")
        return
    st._qos_fd, st.cpu_latency_us = fd, int(us)


def enter_realtime(*, priority: int = 80, cpu: int | None = -1, lock_memory: bool = True,
                   freeze_gc: bool = True, switch_interval_s: float = 2e-4,
                   cpu_latency_us: int | None = None, idle_poll: str = "off") -> RtState:
    """Apply SCHED_FIFO(priority), pin to `cpu` (-1 = last CPU, None = leave), mlockall, gc.freeze, and with
    cpu_latency_us >= 0 a PM QoS wake-up latency request (process-wide; None or -1: leave it alone); idle_poll
    (auto, on, off): idle CPUs kept polling where the PM QoS request cannot keep them out of halt
    (rig/runtime/idle_poll.py).

    The GIL switch interval is shortened so a helper thread holding the GIL delays the loop by at most
    about switch_interval_s (default 5 ms otherwise).
    """
    st = RtState()
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        try:
            allowed = sorted(os.sched_getaffinity(0))
            target = allowed[-1] if cpu == -1 else cpu
            st._old_affinity = set(allowed)
            os.sched_setaffinity(0, {target})
            st.cpu = target
        except (OSError, ValueError) as e:
            _note(st, f"CPU affinity {cpu} not allowed ({e})")
    if priority > 0 and hasattr(os, "sched_setscheduler"):
        try:
            st._old_sched = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            st.fifo = True
        except (OSError, ValueError) as e:
            _note(st, f"SCHED_FIFO priority {priority} not allowed ({e})")
    if lock_memory:
        try:
            if LIBC.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
                _note(st, f"mlockall not allowed ({os.strerror(ctypes.get_errno())})")
            else:
                st.mlocked = True
        except OSError as e:
            _note(st, f"mlockall not available ({e})")
    if cpu_latency_us is not None and cpu_latency_us >= 0:
        request_cpu_latency(st, cpu_latency_us)
    if idle_poll_wanted(idle_poll):
        pollers = st._pollers = IdlePollers().start()
        st.idle_pollers = len(pollers.procs)
        if pollers.note:
            _note(st, pollers.note)
    st._old_switch = sys.getswitchinterval()
    sys.setswitchinterval(switch_interval_s)
    if freeze_gc:
        # Objects made during set-up go to the permanent generation; the hot path makes no reference
        # cycles, so collection is off for the run and restored by leave_realtime.
        gc.collect()
        gc.freeze()
        st._gc_was_enabled = gc.isenabled()
        gc.disable()
        st.gc_frozen = True
    return st


def leave_realtime(st: RtState) -> None:
    """Undo what enter_realtime applied (back to the normal policy, GC on, PM QoS request dropped, pollers
    ended)."""
    if st._pollers is not None:
        st._pollers.stop()
        st._pollers, st.idle_pollers = None, 0
    if st._qos_fd is not None:
        try:
            os.close(st._qos_fd)
        except OSError:
            pass
        st._qos_fd = None
    if st.gc_frozen:
        gc.unfreeze()
        if st._gc_was_enabled:
            gc.enable()
    if st._old_switch is not None:
        sys.setswitchinterval(st._old_switch)
    if st.mlocked:
        try:
            LIBC.munlockall()
        except OSError:
            pass
    if st.fifo and st._old_sched is not None:
        try:
            os.sched_setscheduler(0, st._old_sched[0], os.sched_param(st._old_sched[1]))
        except OSError:
            pass
    if st._old_affinity is not None:
        try:
            os.sched_setaffinity(0, st._old_affinity)
        except OSError:
            pass


def cpu_steal_ms(cpu: int | None) -> float | None:
    """Time the hypervisor ran something else while this guest's CPU `cpu` wanted to run (the steal column of
    /proc/stat, in ms since boot); None where unknown (not Linux, no such CPU)."""
    if cpu is None:
        return None
    try:
        with open("/proc/stat") as f:
            for line in f:
                if line.startswith(f"cpu{cpu} "):
                    return int(line.split()[8]) * 1000.0 / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    return None

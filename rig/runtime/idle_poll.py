"""Idle CPUs kept polling instead of halting while a real-time loop runs.

A halted CPU takes long to wake: on a virtual machine a halt leaves the guest, and the host must run the vCPU
again before the woken thread runs. A loop whose period's work hops between processes (the loop, the drivers'
I/O, the emulated devices) pays that wake-up at every hop. The PM QoS request (rt.request_cpu_latency) keeps
CPUs out of halt only where a cpuidle driver honours it; without one (`current_driver` none, as on many virtual
machines) the idle task halts regardless. There, one poller per CPU, at SCHED_IDLE, takes the idle time
instead: any other task preempts it at once, and the CPU it sits on is awake (docs/REALTIME.md: the measured
effect on `rig hil`).

A poller that finds it was kept off its CPU for long (real-time work saturating that CPU, and the kernel's fair
server now lending it time) sleeps instead of spending that lent time: nothing halts a CPU that busy.
"""
from __future__ import annotations

import os
import subprocess
import sys

CPUIDLE_DRIVER = "/sys/devices/system/cpu/cpuidle/current_driver"
MODES = ("auto", "on", "off")
STARVED_S = 0.02       # a poller kept off its CPU this long sleeps SLEEP_S (the CPU is busy: nothing halts it)
SLEEP_S = 0.005

# the poller: its own interpreter (no lock shared with the loop), a few microseconds per round; it ends with its
# parent
_POLLER = """\
import os, time
parent, now = os.getppid(), time.monotonic
t, k = now(), 0
while True:
    for _ in range(200):
        pass
    t1 = now()
    if t1 - t > STARVED_S:
        time.sleep(SLEEP_S)
        t1 = now()
    t, k = t1, k + 1
    if k % 4096 == 0 and os.getppid() != parent:
        break
"""


def driver(driver_file: str = CPUIDLE_DRIVER) -> str:
    """The cpuidle driver's name: "none" where there is none (or no cpuidle at all)."""
    try:
        with open(driver_file) as f:
            return f.read().strip() or "none"
    except OSError:
        return "none"


def halts_regardless(driver_file: str = CPUIDLE_DRIVER) -> bool:
    """True when no cpuidle driver honours a PM QoS request (the idle CPUs halt whatever is asked)."""
    return driver(driver_file) == "none"


def wanted(mode: str, driver_file: str = CPUIDLE_DRIVER) -> bool:
    """Whether [loop] idle_poll = mode starts pollers here."""
    return mode == "on" or (mode == "auto" and halts_regardless(driver_file))


class IdlePollers:
    """One SCHED_IDLE poller per CPU this process may run on; stop() ends them (they also end with it)."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []
        self.note = ""

    def start(self) -> "IdlePollers":
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        for cpu in cpus:
            try:
                p = subprocess.Popen([sys.executable, "-S", "-c",
                                      _POLLER.replace("STARVED_S", repr(STARVED_S)).replace("SLEEP_S", repr(SLEEP_S))], stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True)
            except OSError as e:
                self.note = f"idle pollers not started ({e})"
                break
            self.procs.append(p)
            try:
                os.sched_setaffinity(p.pid, {cpu})
                os.sched_setscheduler(p.pid, os.SCHED_IDLE, os.sched_param(0))
            except (OSError, AttributeError) as e:        # it would compete with normal work: not kept
                p.kill()
                p.wait()
                self.procs.pop()
                self.note = f"idle pollers not allowed ({e})"
                break
        return self

    def stop(self) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()
        self.procs.clear()

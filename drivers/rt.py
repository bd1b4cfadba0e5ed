"""Scheduling of driver and emulator threads: SCHED_FIFO at a given priority where the OS allows it.

On Linux sched_setscheduler(0, ...) applies to the calling thread only, so each driver thread raises itself
when it starts. Where it is not allowed the thread carries on at normal priority (noted once in the log).
"""
from __future__ import annotations

import logging
import os

log = logging.getLogger("rig.drivers")
_noted = False


def raise_priority(priority: int) -> bool:
    """SCHED_FIFO(priority) for the calling thread; False (and one log note) where not allowed."""
    global _noted
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (OSError, ValueError) as e:
        if not _noted:
            _noted = True
            log.info("driver threads: SCHED_FIFO %d not allowed (%s); normal priority", priority, e)
        return False

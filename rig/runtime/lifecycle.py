"""Lifecycle that gates actuation (after ros2_control's managed nodes).

  UNCONFIGURED --configure--> INACTIVE (communicating, reading; valve held at null)
  INACTIVE     --activate---> ACTIVE   (valve commands allowed)
  ACTIVE       --deactivate-> INACTIVE
  any          --fault------> FAULT    (valve to safe null; the reason is logged once)
  FAULT        --reset------> INACTIVE (explicit acknowledgement only)
"""
from __future__ import annotations

import enum
import logging

from rig.errors import RigError

log = logging.getLogger("rig.lifecycle")


class State(enum.IntEnum):
    UNCONFIGURED = 0
    INACTIVE = 1
    ACTIVE = 2
    FAULT = 3


_ALLOWED = {
    ("configure", State.UNCONFIGURED): State.INACTIVE,
    ("activate", State.INACTIVE): State.ACTIVE,
    ("deactivate", State.ACTIVE): State.INACTIVE,
    ("deactivate", State.INACTIVE): State.INACTIVE,
    ("reset", State.FAULT): State.INACTIVE,
}


class Lifecycle:
    def __init__(self) -> None:
        self.state = State.UNCONFIGURED
        self.fault_reason: str | None = None
        self.history: list[tuple[str, State]] = []

    @property
    def writes_allowed(self) -> bool:
        return self.state is State.ACTIVE

    def _go(self, event: str) -> State:
        new = _ALLOWED.get((event, self.state))
        if new is None:
            raise RigError(f"lifecycle: cannot {event} from {self.state.name}")
        self.state = new
        self.history.append((event, new))
        log.info("lifecycle: %s -> %s", event, new.name)
        return new

    def configure(self) -> State:
        return self._go("configure")

    def activate(self) -> State:
        return self._go("activate")

    def deactivate(self) -> State:
        return self._go("deactivate")

    def reset(self) -> State:
        self.fault_reason = None
        return self._go("reset")

    def fault(self, reason: str) -> bool:
        """Enter FAULT. Returns True the first time (the caller then makes the valve safe); the reason is
        logged once, later faults while in FAULT are ignored."""
        if self.state is State.FAULT:
            return False
        self.state = State.FAULT
        self.fault_reason = reason
        self.history.append(("fault", State.FAULT))
        log.error("FAULT: %s", reason)
        return True

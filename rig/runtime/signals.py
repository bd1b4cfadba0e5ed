"""Signals that arrive before a run exists. The command line installs `hold_early` first thing, before the
imports and the set-up of a run (1-2 s), so a SIGUSR1 sent meanwhile is held instead of taking the default
action (which ends the process: exit 138). A session takes the held toggles over when it installs its own
handlers (rig/runtime/session.py) and applies them at the loop's first period."""
from __future__ import annotations

import signal

_held = [0]                  # SIGUSR1 (isolation toggles) received while held


def _on_usr1(signum, frame) -> None:
    _held[0] += 1


def hold_early() -> None:
    """Hold SIGUSR1 from now on until a session takes it over (main thread only; elsewhere a no-op)."""
    try:
        signal.signal(signal.SIGUSR1, _on_usr1)
    except (ValueError, AttributeError):
        pass


def take_held() -> int:
    """The SIGUSR1 toggles held so far (and forget them)."""
    n, _held[0] = _held[0], 0
    return n

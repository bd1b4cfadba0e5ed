"""Signals that arrive while no run handles them. The command line installs `hold_early` first thing, before the
imports and the set-up of a run (1-2 s):
- a SIGUSR1 sent meanwhile is held instead of taking the default action (which ends the process: exit 138). A
  session takes the held toggles over when it installs its own handlers (rig/runtime/session.py) and applies
  them at the loop's first period;
- a SIGTERM raises `Terminated` in the main thread, as Ctrl-C raises KeyboardInterrupt, instead of the default
  action (the process gone at once, exit 143, not a word): the command unwinds (every file closed, a recording's
  rows kept) and the command line says so in one line, exit 143. This holds during the imports, the set-up and
  the closing figures; while a session's loop runs, the session's own handler stops it safely instead."""
from __future__ import annotations

import os
import signal

_held = [0]                  # SIGUSR1 (isolation toggles) received while held
_owner = [0]                 # the process that installed the handlers (a forked child keeps the default action)


class Terminated(BaseException):
    """SIGTERM where no run handles it: a BaseException, as KeyboardInterrupt is, so no `except Exception` takes
    it for an error, and not a KeyboardInterrupt, which a loop takes for a stop of its own and runs on from."""


def interrupt(signum: int) -> None:
    """Raise what the signal means outside a running loop: KeyboardInterrupt (SIGINT) or Terminated (SIGTERM)."""
    if signum == signal.SIGTERM:
        raise Terminated()
    raise KeyboardInterrupt


def _on_usr1(signum, frame) -> None:
    _held[0] += 1


def _on_term(signum, frame) -> None:
    if os.getpid() != _owner[0]:             # a forked helper: ends as it would have without us
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    interrupt(signum)


def hold_early() -> None:
    """Hold SIGUSR1 and turn SIGTERM into Terminated from now on, until a session takes them over (main thread
    only; elsewhere a no-op)."""
    try:
        _owner[0] = os.getpid()
        signal.signal(signal.SIGUSR1, _on_usr1)
        signal.signal(signal.SIGTERM, _on_term)
    except (ValueError, AttributeError):
        pass


def take_held() -> int:
    """The SIGUSR1 toggles held so far (and forget them)."""
    n, _held[0] = _held[0], 0
    return n

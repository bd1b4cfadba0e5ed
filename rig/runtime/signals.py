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
import sys
import threading

from rig.errors import EXIT_INTERRUPTED, EXIT_TERMINATED

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


def off_the_main_thread(command: str, work, *args):
    """work(*args) in a worker thread while the main thread waits for it. A signal's handler runs only in the
    main thread, between bytecodes, and a compiled (numba) call holds that thread until it returns: minutes on
    a long recording. So Ctrl-C or SIGTERM ends `rig COMMAND` at once: one line, exit 130 or 143, the work
    abandoned (it only reads its inputs; an --out folder being written is left as far as it got)."""
    done: dict = {}

    def target():
        try:
            done["value"] = work(*args)
        except BaseException as e:           # noqa: BLE001 - raised again in the main thread
            done["error"] = e

    th = threading.Thread(target=target, name="rig-work", daemon=True)
    th.start()
    try:
        while th.is_alive():
            th.join(0.1)
    except (KeyboardInterrupt, Terminated) as e:
        term = isinstance(e, Terminated)
        print(f"rig {command}: interrupted" + (" (SIGTERM)" if term else ""), file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(EXIT_TERMINATED if term else EXIT_INTERRUPTED)    # the simulators' pool threads are not waited for
    if "error" in done:
        raise done["error"]
    return done["value"]

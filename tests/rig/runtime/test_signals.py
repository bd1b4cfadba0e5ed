"""Ctrl-C and SIGTERM reach a command whose work is one long compiled call (rig/runtime/signals.py
off_the_main_thread): a signal's handler runs only in the main thread between bytecodes, so a numba call in the
main thread held `rig diagnose` for minutes after a SIGTERM (and SIGKILL was the only way out)."""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from tests.paths import REPO
from tests.rig.support import default_sigint

SPIN = """
import sys
import numpy as np
from rig.runtime.signals import hold_early, off_the_main_thread
from sim_backend.actuator import Effects, simulate_stand
from sim_backend.linear import ActuatorParams

def simulate(seconds):                  # one compiled call: 5000 N of friction, 4.5e6 inner steps a simulated second
    fs = 20.0
    cmd = 2.0 * np.sin(2 * np.pi * 0.5 * np.arange(int(seconds * fs)) / fs)
    return simulate_stand(ActuatorParams(), cmd, fs, Effects(friction_force_n=5000.0))

hold_early()
simulate(0.1)                           # compiled (or loaded from the cache) before the line below
print("busy", flush=True)
if sys.argv[1] == "worker":
    off_the_main_thread("spin", simulate, 1000.0)
else:
    simulate(1000.0)
"""


def _signal_a_busy_process(where: str, sig: int) -> tuple[int | None, float, str]:
    p = subprocess.Popen([sys.executable, "-c", SPIN, where], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint)
    try:
        assert p.stdout.readline().strip() == "busy"
        time.sleep(0.3)
        t0 = time.monotonic()
        p.send_signal(sig)
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            return None, time.monotonic() - t0, ""
        return p.returncode, time.monotonic() - t0, p.stderr.read()
    finally:
        p.kill()
        p.wait()


@pytest.mark.parametrize("sig, code, said", [(signal.SIGTERM, 143, "rig spin: interrupted (SIGTERM)"),
                                             (signal.SIGINT, 130, "rig spin: interrupted")])
def test_a_signal_ends_a_long_compiled_call_run_off_the_main_thread(sig, code, said):
    rc, took, err = _signal_a_busy_process("worker", sig)
    assert rc == code and took < 5 and said in err.strip().splitlines()[-1], (rc, took, err)


def test_the_check_can_fail_a_compiled_call_in_the_main_thread_holds_the_signal():
    rc, took, _ = _signal_a_busy_process("main", signal.SIGTERM)
    assert rc is None                    # still busy 10 s after the SIGTERM: what the off-thread call mends

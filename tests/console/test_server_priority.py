"""In a real-time run the console's web server is moved off the loop's CPU and ahead of ordinary work as soon as it
is started, before its seconds of imports (rig/console/link.py)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from rig.console.link import SERVER_NICE, _server_priority


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs CPU affinity and two CPUs")
def test_the_server_leaves_the_loops_cpu_and_runs_ahead():
    loop_cpu = min(os.sched_getaffinity(0))
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        _server_priority(child.pid, loop_cpu)
        assert loop_cpu not in os.sched_getaffinity(child.pid)
        if os.geteuid() == 0:                        # a raised priority needs the privilege
            assert os.getpriority(os.PRIO_PROCESS, child.pid) == SERVER_NICE
    finally:
        child.kill()
        child.wait()


def test_an_ordinary_run_leaves_the_server_as_it_is():
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        before = (os.sched_getaffinity(child.pid), os.getpriority(os.PRIO_PROCESS, child.pid))
        _server_priority(child.pid, None)
        assert (os.sched_getaffinity(child.pid), os.getpriority(os.PRIO_PROCESS, child.pid)) == before
    finally:
        child.kill()
        child.wait()

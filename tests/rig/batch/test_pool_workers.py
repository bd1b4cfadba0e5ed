"""A batch killed by the operator or a scheduler (SIGTERM, SIGKILL) leaves no pool worker behind: before, its
workers went on, blocked, for as long as the machine ran."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from tests.paths import REPO
from tests.rig.support import default_sigint

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")

BATCH = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from rig.batch.pool import run_tasks

    def nap(folder, s):
        Path(folder, str(os.getpid())).touch()
        time.sleep(s)

    if __name__ == "__main__":
        for _ in run_tasks([(nap, (sys.argv[1], 120))] * 4, workers=2):
            pass
""")


BATCH_HELD = BATCH.replace('if __name__ == "__main__":', 'if __name__ == "__main__":\n'
                                                             '    from rig.runtime.signals import hold_early\n'
                                                             '    hold_early()')


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][0] != "Z"     # a zombie has ended
    except FileNotFoundError:
        return False


@pytest.mark.parametrize("sig, held", [(signal.SIGTERM, False), (signal.SIGKILL, False), (signal.SIGTERM, True),
                                       (signal.SIGINT, True)])
def test_the_workers_end_with_the_batch(tmp_path, sig, held):
    """held: the signal turned into an exception, as `rig diagnose` does (rig/runtime/signals.py hold_early): was,
    the batch then waited for its workers' recordings to end (and started one already queued), 2 minutes here."""
    script = tmp_path / "batch.py"
    script.write_text(BATCH_HELD if held else BATCH)
    pids_dir = tmp_path / "pids"
    pids_dir.mkdir()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, str(script), str(pids_dir)], cwd=tmp_path, env=env,
                            preexec_fn=default_sigint)
    try:
        t0 = time.monotonic()
        while len(list(pids_dir.iterdir())) < 2 and time.monotonic() - t0 < 120:
            time.sleep(0.1)
        workers = [int(p.name) for p in pids_dir.iterdir()]
        assert len(workers) == 2, "the pool's two workers did not start"
        proc.send_signal(sig)
        proc.wait(timeout=30)
        t0 = time.monotonic()
        while any(_alive(w) for w in workers) and time.monotonic() - t0 < 10:
            time.sleep(0.1)
        left = [w for w in workers if _alive(w)]
        assert not left, f"workers {left} outlived the batch killed by {sig.name}"
    finally:
        proc.kill()
        for p in pids_dir.iterdir():
            try:
                os.kill(int(p.name), signal.SIGKILL)
            except ProcessLookupError:
                pass

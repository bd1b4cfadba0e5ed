"""A worker's peak memory is its own: a spawned worker of a parent that holds a large array reports what the worker
used, not the parent's resident size at the fork (getrusage's ru_maxrss carries that across the exec)."""
from __future__ import annotations

import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import numpy as np
import pytest

from rig.batch.run import _peak_rss_mb

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux's")


def _allocate_mb(mb: int) -> float:
    block = np.ones(mb * 2 ** 20 // 8)
    return _peak_rss_mb() + 0 * float(block[0])


def test_a_spawned_worker_reports_its_own_peak_not_its_parents():
    held = np.ones(400 * 2 ** 20 // 8)             # 400 MB resident in the parent while the worker starts
    assert _peak_rss_mb() > 400
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as ex:
        idle = ex.submit(_peak_rss_mb).result()
        busy = ex.submit(_allocate_mb, 200).result()
    assert float(held[-1]) == 1.0
    assert idle < 200, f"a fresh worker's peak {idle:.0f} MB includes the parent's 400 MB"
    assert busy > idle + 150, f"a worker that allocated 200 MB reports {busy:.0f} MB after {idle:.0f} MB"

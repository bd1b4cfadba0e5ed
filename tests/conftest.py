"""Shared test set-up. Layout: tests/<package>/ mirrors the packages (rig, controllers, drivers, sim_backend);
helpers live in non-test modules (tests/paths.py, tests/rig/support.py, tests/*/reference.py).

Markers (pyproject.toml, strict): `slow` (tens of seconds), `hil` (the real drivers against the emulated
devices, real time, loopback only), `shared` (needs the shared recordings in ../shared beside the repository;
skipped when they are not there). `make test` runs them all; e.g. `pytest -m "not slow and not hil"` for a
quick pass.

BLAS runs single-threaded unless the environment says otherwise (set before numpy is first imported): the
design and robustness checks solve hundreds of small eigenvalue problems, and on the shared 2-core machine
OpenBLAS threads only contend for them (8 ms per 110-state problem with one thread, ~120 ms with two)."""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402

from tests.hosttiming import host_line  # noqa: E402
from tests.paths import RECORDINGS  # noqa: E402


def pytest_collection_modifyitems(config, items):
    if RECORDINGS.exists():
        return
    skip = pytest.mark.skip(reason=f"shared recordings not present ({RECORDINGS})")
    for item in items:
        if item.get_closest_marker("shared"):
            item.add_marker(skip)


# A failure whose text shows the host did not keep a real-clock run's time (tests/hosttiming.py) is reported as
# a skip quoting that line; any other failure stays a failure.
@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.when != "call" or not rep.failed or call.excinfo is None:
        return
    line = host_line(str(call.excinfo.value) + "\n" + str(rep.longreprtext))
    if line is not None:
        rep.outcome = "skipped"
        rep.longrepr = (str(item.path), item.location[1] or 0, f"host timing, not judged: {line[:400]}")

"""Shared test set-up. Layout: tests/<package>/ mirrors the packages (rig, controllers, drivers, sim_backend);
helpers live in non-test modules (tests/paths.py, tests/rig/support.py, tests/*/reference.py).

Markers (pyproject.toml, strict): `slow` (tens of seconds), `hil` (the real drivers against the emulated
devices, real time, loopback only), `shared` (needs the shared recordings in ../shared beside the repository;
skipped when they are not there). `make test` runs them all; e.g. `pytest -m "not slow and not hil"` for a
quick pass."""
from __future__ import annotations

import pytest

from tests.paths import RECORDINGS


def pytest_collection_modifyitems(config, items):
    if RECORDINGS.exists():
        return
    skip = pytest.mark.skip(reason=f"shared recordings not present ({RECORDINGS})")
    for item in items:
        if item.get_closest_marker("shared"):
            item.add_marker(skip)

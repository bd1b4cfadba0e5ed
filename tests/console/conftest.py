"""Browser tests (marker `browser`) run Debian's chromium through Playwright; without them here (no root to
install chromium, or Playwright missing) they are skipped with one line saying why."""
from __future__ import annotations

import pytest

from rig.console import browser


def pytest_collection_modifyitems(config, items):
    why = browser.missing()
    if why is None:
        return
    skip = pytest.mark.skip(reason=f"no browser to test the console page with: {why}")
    for item in items:
        if item.get_closest_marker("browser"):
            item.add_marker(skip)


@pytest.fixture(scope="module")
def chromium():
    from playwright.sync_api import sync_playwright
    with sync_playwright() as pw:
        b = browser.launch(pw)
        yield b
        b.close()

"""A real browser on the console page, for the benchmark and the tests: Debian's chromium driven by Playwright.

Playwright's own browser download is not used (nothing is fetched at run time): it drives the system's
chromium (`apt-get install chromium`), headless, with a fresh profile and no background traffic.
"""
from __future__ import annotations

import shutil

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def missing() -> str | None:
    """Why no browser can be driven here (one line), or None."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright for Python is not installed (pip install -e '.[test]')"
    if not shutil.which(CHROMIUM):
        return f"{CHROMIUM} is not installed (apt-get install -y chromium, as root; `make test` does it)"
    return None


def launch(playwright):
    """A headless chromium on a fresh temporary profile (Playwright makes and removes it)."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)


def wait_for(page, expression: str, timeout_s: float = 20.0, poll_s: float = 0.05):
    """Poll a JavaScript expression on the page until it is truthy; its value. (Playwright's wait_for_function
    evaluates a string in the page, which the console's Content-Security-Policy forbids.)"""
    import time
    end = time.monotonic() + timeout_s
    while True:
        v = page.evaluate(expression)
        if v:
            return v
        if time.monotonic() > end:
            raise TimeoutError(f"{expression!r} still false after {timeout_s:g} s")
        time.sleep(poll_s)

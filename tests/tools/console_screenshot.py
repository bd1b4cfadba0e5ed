"""The README's picture of the console: `python -m tests.tools.console_screenshot docs/console.png`.

Runs `rig run --console` on the simulated rig in a temporary folder, shows the page in headless chromium,
runs a short chirp identification from the page, switches isolation off and on again (so the spectrum has
both), records a few seconds and takes a full-page screenshot.
"""
from __future__ import annotations

import sys
import tempfile
import time

from rig.console import browser
from rig.console.browser import wait_for
from tests.console.support import ask_for_chirp, open_when_active, rig_run_console


def main(out: str) -> int:
    why = browser.missing()
    if why:
        print(f"console_screenshot: {why}", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as pw, \
            rig_run_console("--seconds", "600", cwd=tmp, realtime=True) as (proc, url, _):
        b = browser.launch(pw)
        page = open_when_active(b, url, 1500, 1200)
        ask_for_chirp(page, 1, 1, 60, 5)
        wait_for(page, "document.getElementById('ident-table')", 180)
        wait_for(page, "rigStats.lastNow && rigStats.lastNow.state === 'ACTIVE'", 60)
        page.click("#iso-off")
        time.sleep(14)
        page.click("#iso-on")
        page.fill("#rec-path", "rig_run_example.h5")
        page.click("#rec-start")
        time.sleep(14)                      # the traces fill their 10 s and the spectrum of "on" its segment
        page.screenshot(path=out, full_page=True)
        page.click("#rec-stop")
        page.click("#safe-stop")
        proc.wait(60)
        b.close()
    print(f"console_screenshot: {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "docs/console.png"))

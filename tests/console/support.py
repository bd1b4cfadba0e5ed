"""Helpers of the console tests: a run with its console in this process (the sim backend on the real clock,
its loop in a thread), plain HTTP to the console, and the `rig run --console` command as a process."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request

from rig.runtime.clock import MonotonicClock
from rig.config import Config
from rig.console.link import Console
from rig.runtime.lifecycle import State
from rig.runtime.session import Session
from tests.paths import REPO

# the configured rate: the Table 1 controller is designed for it; at 1000 Hz `rig design` calls its loop unstable
# (|z| = 1.03 at 110 Hz) and the oscillation rule faults the run within 0.1 s
RATE_HZ = Config().loop.rate_hz


def test_config() -> Config:
    """The default rig with a watchdog and timing rules that tolerate the shared test machine's stalls (a browser,
    the suite): no lag or missed-deadline fault from a starved loop."""
    cfg = Config()
    return cfg.replace(safety=dataclasses.replace(cfg.safety, watchdog_s=1.0, lag_limit_s=10.0, missed_limit=1.0))


@contextlib.contextmanager
def live_run(*, read_only: bool = False, isolation: bool = True, record=None, serve: str = "process", cfg=None,
             record_dir=None):
    """(session, console): the simulated rig (or cfg's) running in a thread, ACTIVE, its console attached (its
    recordings in record_dir, default the working directory)."""
    cfg = cfg or test_config()
    s = Session(cfg, "sim", clock=MonotonicClock(), rate_hz=RATE_HZ, stop_on_fault=False, isolation=isolation,
                record=record)
    with s, Console(cfg, "sim", port=0, read_only=read_only, serve=serve, record_dir=record_dir) as console:
        console.attach(s)
        th = threading.Thread(target=lambda: s.run(activate_after_s=0.05), name="test-loop", daemon=True)
        th.start()
        try:
            wait(lambda: s.loop.state is State.ACTIVE, "the loop to go ACTIVE")
            yield s, console
        finally:
            s.safe_stop("test done")
            th.join(30)
            console.detach()


def wait(cond, what: str, timeout_s: float = 20.0):
    end = time.monotonic() + timeout_s
    while True:
        v = cond()
        if v:
            return v
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(0.02)


def base(console) -> str:
    return f"http://127.0.0.1:{console.port}"


def http(url: str, *, data: dict | None = None, headers: dict | None = None) -> tuple[int, str]:
    """(status, body) of a GET (or a POST of JSON), never raising on an HTTP error status."""
    body = json.dumps(data).encode() if data is not None else None
    req = urllib.request.Request(url, data=body, headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def state(console) -> dict:
    code, body = http(f"{base(console)}/api/state?token={console.token}")
    assert code == 200, body
    return json.loads(body)


def command(console, cmd: str, **args) -> tuple[int, dict]:
    code, body = http(f"{base(console)}/api/command?token={console.token}", data={"cmd": cmd, "args": args})
    return code, json.loads(body)


TEST_TOML = """# the console tests' rig: the defaults with a watchdog that tolerates the shared machine's stalls
[safety]
watchdog_s = 1.0
lag_limit_s = 10
missed_limit = 1.0
"""


@contextlib.contextmanager
def rig_run_console(*extra: str, cwd=None, realtime: bool = False):
    """`rig run --console --port 0 ...` as a process: (process, url, stderr lines so far)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with tempfile.NamedTemporaryFile("w", suffix=".toml", prefix="rig-console-test-", delete=False) as f:
        f.write(TEST_TOML)
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "run", "--config", f.name, "--console", "--port", "0",
                             *([] if realtime else ["--no-realtime"]), *extra], cwd=cwd or REPO, stderr=subprocess.PIPE,
                            text=True, env=env)
    lines: list[str] = []
    url = None
    try:
        for line in proc.stderr:
            lines.append(line)
            m = re.search(r"(http://127\.0\.0\.1:\d+/\?token=[0-9a-f]+)", line)
            if m:
                url = m.group(1)
                break
        assert url, "no console address printed:\n" + "".join(lines)
        reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
        reader.start()
        yield proc, url, lines
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        os.unlink(f.name)


def open_page(chromium, console, **kw):
    """A page on `console` once it has had a few updates; its script errors collect in page.errors."""
    from rig.console.browser import wait_for
    page = chromium.new_page(viewport={"width": 1400, "height": 1300}, **kw)
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(console.url)
    wait_for(page, "window.rigStats && rigStats.deltas > 5 && rigStats.renders > 3")
    page.errors = errors
    return page


def open_when_active(chromium, url: str, width: int = 1400, height: int = 1300):
    """A page on the console at `url`, once it shows the run ACTIVE."""
    from rig.console.browser import wait_for
    page = chromium.new_page(viewport={"width": width, "height": height})
    page.goto(url)
    wait_for(page, "window.rigStats && rigStats.lastNow && rigStats.lastNow.state === 'ACTIVE'", 60)
    return page


def ask_for_chirp(page, amplitude_V: float, f0_hz: float, f1_hz: float, duration_s: float) -> None:
    """Fill in the page's chirp form and press its button."""
    for sel, v in (("#chirp-amp", amplitude_V), ("#chirp-f0", f0_hz), ("#chirp-f1", f1_hz),
                   ("#chirp-dur", duration_s)):
        page.fill(sel, str(v))
    page.click("#chirp-run")

"""`rig run --console` as an operator starts it: the address with its token on stderr, 403 without it, only
loopback listening in the whole process tree, a safe stop from the console ending the run; the options refused
with one line where they make no sense; a chirp identification asked for on the page, with its progress bar,
ending with the identified parameters beside Table 1 while the run goes on."""
from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import psutil
import pytest

from rig.console.browser import wait_for
from tests.console.support import http, open_when_active, rig_run_console, wait
from tests.paths import REPO


def _state(url):
    code, body = http(url.replace("/?token=", "/api/state?token="))
    assert code == 200, body
    return json.loads(body)


def _command(url, cmd, **args):
    code, body = http(url.replace("/?token=", "/api/command?token="), data={"cmd": cmd, "args": args})
    return code, json.loads(body)


def test_rig_run_console_address_token_loopback_and_safe_stop():
    with rig_run_console("--seconds", "120") as (proc, url, lines):
        port = int(url.split(":")[2].split("/")[0])
        wait(lambda: (_state(url).get("now") or {}).get("state") == "ACTIVE", "ACTIVE", 60)
        assert http(f"http://127.0.0.1:{port}/")[0] == 403
        assert http(f"http://127.0.0.1:{port}/api/state")[0] == 403
        code, page = http(url)
        assert code == 200 and "rig console" in page
        tree = [psutil.Process(proc.pid)] + psutil.Process(proc.pid).children(recursive=True)
        socks = [(p.name(), c.laddr) for p in tree for c in p.net_connections(kind="inet")
                 if c.status == psutil.CONN_LISTEN or (c.type == socket.SOCK_DGRAM and c.laddr)]
        assert any(a.port == port for _, a in socks)
        assert all(a.ip == "127.0.0.1" for _, a in socks), socks
        code, reply = _command(url, "safe_stop")
        assert code == 200 and reply["ok"]
        assert proc.wait(60) == 0
    text = "".join(lines)
    assert "stopped (console: safe stop)" in text and "console: safe stop requested" in text
    assert "Traceback" not in text


@pytest.mark.parametrize("args, want", [
    (["--port", "8000"], "--port/--read-only: only with --console"),
    (["--read-only"], "--port/--read-only: only with --console"),
    (["--console", "--port", "70000"], "--port: expected an integer >= 0 and <= 65535, got '70000'"),
])
def test_console_options_without_sense_are_refused_with_one_line(args, want):
    r = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--seconds", "1", *args], cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == f"rig run: error: {want}"


def test_a_busy_port_is_one_line():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "rig.cli", "run", "--seconds", "1", "--console", "--port",
                            str(port)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"rig run: error: --port: cannot listen on 127.0.0.1 "
                                                         f"port {port}")


@pytest.mark.browser
@pytest.mark.slow
def test_chirp_identification_from_the_page_with_its_defaults(chromium, tmp_path):
    """The page's "Run chirp identification" as an operator presses it: the form's defaults (2 V, 0.1 -> 100 Hz,
    100 s, on the real clock), then the identification, then the isolation run resumes."""
    with rig_run_console("--seconds", "900", cwd=tmp_path) as (proc, url, lines):
        page = open_when_active(chromium, url)
        assert [page.input_value(s) for s in ("#chirp-amp", "#chirp-f0", "#chirp-f1", "#chirp-dur")] == \
            ["2", "0.1", "100", "100"]
        page.click("#chirp-run")
        progress = []
        end = time.monotonic() + 600
        while page.locator("#ident-table").count() == 0 and time.monotonic() < end:
            progress.append((page.text_content("#chirp-text"), page.evaluate("+document.getElementById("
                                                                             "'chirp-progress').value")))
            if progress[-1][0].startswith("failed"):
                break
            time.sleep(0.2)
        assert page.locator("#ident-table").count(), f"no identification: {progress[-1][0]!r}\n{''.join(lines)}"
        table = page.locator("#ident-table").inner_text()
        wait_for(page, "rigStats.lastNow && rigStats.lastNow.state === 'ACTIVE'", 60)   # the run resumed
        page.click("#safe-stop")
        assert proc.wait(60) == 0
    phases = [t.split(":")[0] for t, _ in progress if t]
    assert "chirp" in phases and "identify" in phases
    assert any(0 < v < 1 for t, v in progress if t.startswith("chirp"))          # the bar moved
    rows = [r.split("\t") for r in table.strip().splitlines()]
    assert rows[0][:4] == ["parameter", "unit", "Table 1", "identified"]
    assert [r[0] for r in rows[1:]] == ["K_L", "C", "w_nv", "zeta", "K_Q", "K_C"]
    w = next(r for r in rows if r[0] == "w_nv")
    assert abs(float(w[3]) / float(w[2]) - 1) < 0.5          # the stand's valve frequency, near Table 1
    assert list(tmp_path.glob("chirp_*.h5"))

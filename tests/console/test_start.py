"""The console's address is printed once its web server answers (issue 29: the first page came 12-14 s after the
address at load 17, while the server was still importing); a server that does not start is one line, not an
address that never answers."""
from __future__ import annotations

import sys

import pytest

from rig.console.link import Console
from rig.errors import RigError
from tests.console import support
from tests.console.support import base, http


def test_the_console_is_entered_once_its_server_answers():
    with Console(support.test_config(), "sim", port=0) as console:
        proc = console._proc
        assert proc is not None and proc.poll() is None
        code, body = http(f"{base(console)}/?token={console.token}")
        assert code == 200 and "rig console" in body


def test_a_web_server_that_does_not_start_is_one_line(monkeypatch):
    monkeypatch.setattr(sys, "executable", "/bin/false")       # the server's process exits at once
    with pytest.raises(RigError) as e:
        with Console(support.test_config(), "sim", port=0):
            pass
    assert str(e.value) == "console: the web server did not start (exit 1)"

"""The console's web server over plain HTTP and websockets: nothing without the token (page, data, control),
no other Host, read-only refuses every command, commands reach the loop through the session's requests, and
the only listening socket is on 127.0.0.1."""
from __future__ import annotations

import json

import psutil
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from rig.runtime.lifecycle import State
from tests.console.support import base, command, http, live_run, state, wait


@pytest.fixture(scope="module")
def run():
    with live_run() as (s, console):
        yield s, console


@pytest.mark.parametrize("path", ["/", "/api/state", "/static/console.js", "/static/vendor/uplot/uPlot.iife.min.js",
                                  "/static/index.html"])
def test_no_page_and_no_data_without_the_token(run, path):
    s, console = run
    for suffix in ("", "?token=", "?token=" + "0" * len(console.token), "?token=" + console.token[:-1]):
        code, body = http(base(console) + path + suffix)
        assert code == 403 and "forbidden" in body and "rig" not in body.split("forbidden")[0]
    code, body = http(base(console) + path + "?token=" + console.token)
    assert code == 200 and body


def test_no_control_without_the_token(run):
    s, console = run
    assert s.loop.isolation
    code, body = http(f"{base(console)}/api/command", data={"cmd": "isolation", "args": {"on": False}})
    assert code == 403
    code, body = http(f"{base(console)}/api/command?token=nope", data={"cmd": "safe_stop", "args": {}})
    assert code == 403
    with pytest.raises(InvalidStatus) as e:
        connect(f"ws://127.0.0.1:{console.port}/ws", open_timeout=10)
    assert e.value.response.status_code == 403
    assert s.loop.isolation and s.loop.stop_reason is None and s.loop.state is State.ACTIVE


def test_another_host_name_or_origin_is_refused(run):
    """The token alone is not enough from a page of another site (DNS rebinding, cross-site websocket)."""
    s, console = run
    code, _ = http(f"{base(console)}/api/state?token={console.token}", headers={"Host": "evil.example"})
    assert code == 403
    with pytest.raises(InvalidStatus):
        connect(f"ws://127.0.0.1:{console.port}/ws?token={console.token}", origin="http://evil.example",
                open_timeout=10)


def test_state_and_commands_with_the_token(run):
    s, console = run
    st = wait(lambda: (lambda x: x if x["now"].get("state") == "ACTIVE" and len(x["traces"]["t"]) > 10 else None)(
        state(console)), "ACTIVE with traces")
    assert st["layout"]["mounts"] == ["front_left", "front_right", "rear_left", "rear_right"]
    assert st["layout"]["limits"]["valve_limit_V"] == s.cfg.safety.valve_limit_V
    assert len(st["traces"]["v"]) == 12 and len(st["traces"]["t"]) > 10
    code, reply = command(console, "isolation", on=False)
    assert code == 200 and reply["ok"], reply
    wait(lambda: state(console)["now"]["isolation"] is False, "isolation off on the console")
    assert s.loop.isolation is False
    code, reply = command(console, "isolation", on=True)
    wait(lambda: state(console)["now"]["isolation"] is True, "isolation on on the console")
    # The gate logs "isolation on" a moment after the console logs the request: wait for both records.
    events = wait(lambda: (lambda ev: ev if any("isolation on requested" in t for t in ev)
                           and "isolation on" in ev else None)(
        [e["text"] for e in state(console)["events"]]), "the command's and the gate's log lines")
    assert "isolation off" in events and "isolation on" in events            # the gate's log records
    assert any("isolation off requested" in t and "http 127.0.0.1" in t for t in events)   # the command's log line


def test_malformed_and_unknown_commands_are_refused_with_one_line(run):
    s, console = run
    for cmd, args, want in (("launch", {}, "unknown command 'launch'"),
                            ("isolation", {}, "missing argument 'on'"),
                            ("isolation", {"on": "yes"}, "on must be bool"),
                            ("chirp", {"amplitude_V": float("nan"), "f0_hz": 1, "f1_hz": 2, "duration_s": 3,
                                       "mount": "front_left"}, "amplitude_V must be a finite number")):
        code, body = http(f"{base(console)}/api/command?token={console.token}", data={"cmd": cmd, "args": args})
        reply = json.loads(body)
        assert code == 409 and not reply["ok"] and "\n" not in reply["text"] and want in reply["text"]
    code, reply = command(console, "reset_fault")
    assert code == 409 and "no fault to reset" in reply["text"]
    assert s.loop.state is State.ACTIVE


def test_read_only_shows_everything_and_refuses_every_command():
    with live_run(read_only=True) as (s, console):
        st = wait(lambda: (lambda x: x if x["now"].get("state") == "ACTIVE" else None)(state(console)), "ACTIVE")
        assert st["read_only"] is True and len(st["traces"]["t"]) > 0
        for cmd, args in (("isolation", {"on": False}), ("safe_stop", {}), ("deactivate", {}),
                          ("record_start", {"path": "x.h5"})):
            code, reply = command(console, cmd, **args)
            assert code == 403 and reply["text"] == "read-only console: commands are refused"
        with connect(f"ws://127.0.0.1:{console.port}/ws?token={console.token}", open_timeout=10) as ws:
            full = json.loads(ws.recv(10))
            assert full["type"] == "full" and full["read_only"]
            ws.send(json.dumps({"id": 7, "cmd": "isolation", "args": {"on": False}}))
            reply = next(m for m in (json.loads(ws.recv(10)) for _ in range(200)) if m["type"] == "reply")
        assert reply == {"ok": False, "text": "read-only console: commands are refused", "type": "reply", "id": 7}
        assert s.loop.isolation and s.loop.state is State.ACTIVE and s.loop.stop_reason is None


def test_the_only_listening_socket_is_on_loopback(run):
    s, console = run
    procs = [psutil.Process()] + psutil.Process().children(recursive=True)
    listening = [(p.pid, c.laddr) for p in procs for c in p.net_connections(kind="inet")
                 if c.status == psutil.CONN_LISTEN or (c.type == 2 and c.laddr)]    # TCP listen, bound UDP
    assert any(a.port == console.port for _, a in listening)                 # the check sees the console
    assert all(a.ip == "127.0.0.1" for _, a in listening), listening


def test_the_mode_command_switches_a_stand_and_refuses_what_it_cannot_hold():
    """The console's `mode` command on the prototype: a track request reaches the compiled law through the
    session's request (bumpless, logged); one the actuator cannot hold is refused with the session's one line
    and the mode stays; on the machine the command is refused (no operating modes there)."""
    import dataclasses
    from rig.commands.run import LAYOUTS
    from rig.config import load_config
    cfg = load_config(LAYOUTS["prototype"][None])
    cfg = cfg.replace(safety=dataclasses.replace(cfg.safety, watchdog_s=1.0))
    with live_run(cfg=cfg) as (s, console):
        assert s.modes() == ["hold"]
        code, reply = command(console, "mode", request="track sine:amp=5um,freq=2")
        assert code == 200 and reply["ok"] and reply["text"].startswith("mode track sine"), reply
        wait(lambda: s.modes() == ["track"], "track on the stand")
        code, reply = command(console, "mode", request="hold 30um")
        assert code == 409 and not reply["ok"] and "outside what the actuator can hold" in reply["text"], reply
        assert s.modes() == ["track"]
    with live_run() as (s, console):
        code, reply = command(console, "mode", request="hold")
        assert code == 409 and not reply["ok"] and "no operating modes" in reply["text"], reply


def test_an_overlong_text_argument_is_refused_in_one_short_line(run):
    """Was: a 300 kB record_start path came back as 'no reply from the run (OSError)' (too big for the control
    socket); a 150 kB mode request was echoed whole into the refusal, on the page and in the terminal's log.
    (Bodies that long are now refused whole: test_hostile_command_bodies_get_one_line_and_the_run_goes_on.)"""
    s, console = run
    for cmd, args in (("record_start", {"path": "a" * 30_000 + ".h5"}), ("mode", {"request": "a" * 15_000})):
        code, body = http(f"{base(console)}/api/command?token={console.token}", data={"cmd": cmd, "args": args})
        reply = json.loads(body)
        assert code == 409 and not reply["ok"] and len(reply["text"]) < 200, reply["text"][:300]
        assert "must be at most 4096 characters" in reply["text"]
    assert s.loop.stop_reason is None


def test_a_recording_from_the_page_stays_in_the_consoles_recording_folder(tmp_path, monkeypatch):
    """Was: the page's recording path was taken as given, so whoever held the token could make an HDF5 file
    wherever the rig's user may write (`../`, an absolute path, `~/`). Now a name in the console's recording
    folder (where the run started) or below it; anything leading out, a symbolic link too, is refused in one
    line and nothing is written."""
    recs, elsewhere = tmp_path / "recs", tmp_path / "elsewhere"
    (recs / "day1").mkdir(parents=True)
    elsewhere.mkdir()
    (recs / "out").symlink_to(elsewhere)
    (recs / "dangling.h5").symlink_to(elsewhere / "via_link.h5")
    monkeypatch.chdir(recs)                                  # the run starts here: its recording folder
    with live_run() as (s, console):
        for path in ("../elsewhere/up.h5", str(elsewhere / "abs.h5"), "day1/../../elsewhere/x.h5", "out/x.h5",
                     "dangling.h5", "~/x.h5"):
            code, reply = command(console, "record_start", path=path)
            assert code == 409 and not reply["ok"], (path, reply)
            assert reply["text"] == (f"recording {path!r}: outside the console's recording folder {recs} (where the "
                                     f"run started): expected a file name there or below it")
        for path, made in (("day1/a.h5", recs / "day1" / "a.h5"), (str(recs / "b.h5"), recs / "b.h5")):
            code, reply = command(console, "record_start", path=path)
            assert code == 200 and reply["text"] == f"recording to {made}", reply
            code, reply = command(console, "record_stop")
            assert code == 200 and reply["ok"], reply
    assert list(elsewhere.iterdir()) == []
    assert sorted(p.name for p in recs.rglob("*.h5") if not p.is_symlink()) == ["a.h5", "b.h5"]


def _post(console, raw: bytes) -> tuple[int, dict]:
    import urllib.error
    import urllib.request
    req = urllib.request.Request(f"{base(console)}/api/command?token={console.token}", data=raw,
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_hostile_command_bodies_get_one_line_and_the_run_goes_on(run):
    """Were: a 500 and a server traceback for a `cmd` that is a list or an object (unhashable) and for JSON
    nested past Python's recursion limit; a body of any size read whole (300 MB: the server's memory grew by
    100 MB); a binary websocket frame a traceback and a dropped socket."""
    s, console = run
    for raw, code, want in ((b'{"cmd": ["isolation"]}', 409, "unknown command ['isolation']"),
                            (b'{"cmd": {"a": 1}}', 409, "unknown command {'a': 1}"),
                            (b"[" * 30_000 + b"]" * 30_000, 409, "a command is a JSON object"),
                            (b" " * (1 << 20), 413, "a command is at most 65536 bytes")):
        got, reply = _post(console, raw)
        assert got == code and not reply["ok"] and want in reply["text"] and "\n" not in reply["text"], reply
    with connect(f"ws://127.0.0.1:{console.port}/ws?token={console.token}", open_timeout=10) as ws:
        ws.recv(timeout=10)                                   # the first state
        ws.send(b'{"cmd": "isolation", "args": {"on": true}}')
        reply = next(m for m in (json.loads(ws.recv(timeout=10)) for _ in range(200)) if m.get("type") == "reply")
        assert not reply["ok"] and "a command is a JSON object" in reply["text"]
    assert s.loop.state is State.ACTIVE and s.loop.stop_reason is None


@pytest.mark.parametrize("args, want", [
    ({"duration_s": 1e7}, "duration_s: expected 0 < s <= 3600, got 1e+07"),
    ({"amplitude_V": 100.0}, "amplitude_V: expected 0 < V <= safety.valve_limit_V = 10, got 100"),
    ({"f0_hz": 30.0}, "f0_hz/f1_hz: expected 0 <= f0 < f1"),
])
def test_a_chirp_the_rig_would_refuse_is_refused_before_the_run_stops(run, args, want):
    """Were: the run stopped (isolation off), then the job failed (`--amplitude: ...`, named as the command line's
    option); a duration of 1e7 s built a list of 5e10 samples in the loop's process, memory growing without end."""
    s, console = run
    chirp = {"amplitude_V": 1.0, "f0_hz": 1.0, "f1_hz": 20.0, "duration_s": 2.0, "mount": "front_left", **args}
    code, reply = command(console, "chirp", **chirp)
    assert code == 409 and not reply["ok"] and want in reply["text"], reply
    assert s.loop.state is State.ACTIVE and s.loop.stop_reason is None

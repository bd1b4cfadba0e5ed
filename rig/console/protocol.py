"""What the page may ask for, and the messages between the loop's process and the console's web server.

One place for the command names and their arguments, read by both sides: the web server refuses an unknown
or malformed command (and every command in read-only mode) before it leaves the server; the loop's side
(rig/console/link.py) checks again and turns each into the session's own request.

Control socket (AF_UNIX, SOCK_SEQPACKET: one JSON object per message, a file descriptor may ride along):
  loop -> server  hello {token, read_only, backend, ...}; attach {layout} + the live ring's fd; detach;
                  status {run, recording, job, log} ten times a second; result {job result}; reply {id, ok,
                  text}; ended {reason}
  server -> loop  cmd {id, cmd, args, client}
"""
from __future__ import annotations

import json
import math
import socket

# name -> (argument names and their types, what the button does). Every one goes through the session's
# requests (rig/runtime/session.py), i.e. the lifecycle gate's thread-safe requests applied at a period boundary.
COMMANDS = {
    "isolation": ({"on": bool}, "switch isolation on or off (bumpless, in the controllers)"),
    "activate": ({}, "INACTIVE -> ACTIVE (valve commands allowed)"),
    "deactivate": ({}, "ACTIVE -> INACTIVE (valves to null, the loop keeps reading)"),
    "reset_fault": ({}, "FAULT -> INACTIVE (the operator acknowledges the fault)"),
    "safe_stop": ({}, "end the run safely: valves to null, safe state, recording closed"),
    "record_start": ({"path": str}, "record the loop's rows to an HDF5 file"),
    "record_stop": ({}, "stop and close the recording"),
    "mode": ({"request": str}, "operating mode of a stand layout: `hold [POS]`, `track REF`, `isolate`, `off` "
                               "(bumpless; a reference the actuator cannot follow is refused, never clamped)"),
    "chirp": ({"amplitude_V": float, "f0_hz": float, "f1_hz": float, "duration_s": float, "mount": str},
              "stop the run, chirp one valve, identify the six actuator parameters, resume the run"),
}


MAX_TEXT = 4096          # a path or mode request (PATH_MAX): longer would not fit the control socket's message


def check_command(msg) -> tuple[str, dict] | str:
    """(name, arguments) of a well-formed command message {"cmd": name, "args": {...}}, else one line saying
    what is wrong."""
    if not isinstance(msg, dict):
        return "a command is a JSON object {\"cmd\": name, \"args\": {...}}"
    name = msg.get("cmd")
    if not isinstance(name, str) or name not in COMMANDS:
        return f"unknown command {name!r} (expected one of {', '.join(COMMANDS)})"
    spec, _ = COMMANDS[name]
    args = msg.get("args") or {}
    if not isinstance(args, dict):
        return f"{name}: args must be an object"
    out = {}
    for key, typ in spec.items():
        if key not in args:
            return f"{name}: missing argument {key!r}"
        v = args[key]
        if typ is float:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                return f"{name}: {key} must be a finite number, got {v!r}"
            v = float(v)
        elif not isinstance(v, typ):
            return f"{name}: {key} must be {typ.__name__}, got {v!r}"
        elif typ is str and len(v) > MAX_TEXT:
            return f"{name}: {key} must be at most {MAX_TEXT} characters, got {len(v)}"
        out[key] = v
    return name, out


MAX_MESSAGE = 1 << 20


def send(sock: socket.socket, msg: dict, fds: tuple[int, ...] = ()) -> None:
    data = json.dumps(msg, separators=(",", ":")).encode()
    if fds:
        socket.send_fds(sock, [data], list(fds))
    else:
        sock.send(data)


def receive(sock: socket.socket) -> tuple[dict | None, list[int]]:
    """One message and the descriptors that came with it; (None, []) when the other side has gone."""
    data, fds, _, _ = socket.recv_fds(sock, MAX_MESSAGE, 4)
    if not data:
        return None, fds
    return json.loads(data), fds

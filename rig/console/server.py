"""The console's web server: the page, its live data over a websocket, and its commands (Starlette on uvicorn).

It runs in a process of its own by default (`python -m rig.console.server`, started by rig/console/link.py),
so its work (JSON, websocket framing, spectra) never holds the loop's interpreter lock; it can also run as a
thread of the loop's process (`serve_in_thread`, the comparison in `rig bench loop --console`). Either way it
reads the loop's rows from the live ring (rig/console/live.py) and talks to the loop's side over one control
socket (rig/console/protocol.py); it never touches the loop itself.

Access: the listening socket is bound to 127.0.0.1 by the loop's side and handed over. Every request, the
websocket included, needs the access token (in the address printed at start, then a SameSite=Strict cookie)
and a Host header naming this address (no DNS rebinding); without them: 403 and nothing else. A websocket
from another origin is refused. In read-only mode the page shows everything and every command is refused
here, before it reaches the loop.
"""
from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import hmac
import json
import logging
import math
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from rig import cliargs
from rig.console.feed import Feed
from rig.console.live import LiveReader
from rig.console.protocol import check_command, receive, send

STATIC = Path(__file__).with_name("static")
TICK_S = 0.05                  # the page's update period (20 Hz)
COOKIE = "rig_console_token"
COMMAND_TIMEOUT_S = 30.0       # a recording start waits for its writer process
EXTRA_TICKS_S = (0.005, 0.025)  # extra updates after a command (a recording's rows arrive every 20 ms)
MAX_BODY = 64 * 1024           # a command's JSON: the longest well-formed one (a 4096-character path) is ~4.2 kB
log = logging.getLogger("rig.console.server")


class ConsoleState:
    """What the server holds: the hello from the loop's side, the feed of the attached run, the latest status,
    the connected pages and the commands waiting for their reply."""

    def __init__(self, control: socket.socket) -> None:
        self.control = control
        self.hello: dict = {}
        self.token = ""
        self.read_only = True
        self.reader: LiveReader | None = None
        self.feed: Feed | None = None
        self.status: dict = {}
        self.result: dict | None = None
        self.result_new = False
        self.ended: str | None = None
        self.clients: set = set()
        self.pending: dict[int, asyncio.Future] = {}
        self._next_id = 0
        self.seq = 0
        self.gone = asyncio.Event()
        self.ready = asyncio.Event()
        self.soon = asyncio.Event()       # an extra update now: a command has just been applied
        self.attached = 0                 # attach count (a page resets its plots on a new one)
        self.tick_ms = collections.deque(maxlen=400)      # the server's own work per update (CPU time)
        self.events: list[dict] = []      # the loop's log records (commands, lifecycle, switches), oldest first
        self._new_events: list[dict] = []
        self._event_seq = 0

    def add_events(self, events) -> None:
        """Events in, each numbered: a page that got an event in a full state skips it in the next delta."""
        for e in events:
            self._event_seq += 1
            e["seq"] = self._event_seq
        self.events.extend(events)
        self._new_events.extend(events)
        del self.events[:-200]

    # ---- the control socket -----------------------------------------------------------------------------
    def on_control(self) -> None:
        try:
            msg, fds = receive(self.control)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            msg, fds = None, []
        if msg is None:
            self._ended(self.ended or "the run's process has gone")
            self.gone.set()
            return
        kind = msg.get("type")
        if kind == "hello":
            self.hello = msg
            self.token = msg["token"]
            self.read_only = bool(msg["read_only"])
            self.ready.set()
        elif kind == "attach":
            self._detach()
            self.reader = LiveReader(fds[0])
            os.close(fds[0])
            self.feed = Feed(msg["layout"])
            self.attached += 1
            self._broadcast_full()
        elif kind == "detach":
            self._detach()
        elif kind == "status":
            status = msg["status"]
            self.add_events([{"t_s": None, "wall": r["wall"], "text": r["text"], "source": "log",
                              "level": r["level"]} for r in status.pop("log", ())])
            self.status = status
        elif kind == "result":
            self.result = msg["result"]
            self.result_new = True
        elif kind == "reply":
            fut = self.pending.pop(msg["id"], None)
            if fut is not None and not fut.done():
                fut.set_result({"ok": bool(msg["ok"]), "text": msg["text"]})
        elif kind == "ended":
            self._ended(msg["reason"])
        for fd in fds[1:] if kind == "attach" else fds:
            os.close(fd)

    def _detach(self) -> None:
        if self.reader is not None:
            rows = self.reader.read()               # the last rows of the run
            if self.feed is not None and len(rows):
                self.feed.add(rows)
            self.reader.close()
        self.reader = None

    def _ended(self, reason: str) -> None:
        if self.ended is None:
            self.ended = reason
        self._queue_all({"type": "ended", "reason": self.ended})

    # ---- commands ----------------------------------------------------------------------------------------
    async def command(self, msg, client: str) -> dict:
        """A page's command: refused here in read-only mode or when malformed, else handed to the loop's side
        and its reply awaited."""
        if self.read_only:
            return {"ok": False, "text": "read-only console: commands are refused"}
        checked = check_command(msg)
        if isinstance(checked, str):
            return {"ok": False, "text": checked}
        if self.ended is not None:
            return {"ok": False, "text": f"the run has ended ({self.ended})"}
        name, args = checked
        self._next_id += 1
        cid = self._next_id
        fut = asyncio.get_running_loop().create_future()
        self.pending[cid] = fut
        try:
            send(self.control, {"type": "cmd", "id": cid, "cmd": name, "args": args, "client": client})
            reply = await asyncio.wait_for(fut, COMMAND_TIMEOUT_S)
            loop = asyncio.get_running_loop()
            for delay in EXTRA_TICKS_S:     # the loop applies a request at its next period: show it at once
                loop.call_later(delay, self.soon.set)
            return reply
        except (OSError, asyncio.TimeoutError) as e:
            self.pending.pop(cid, None)
            return {"ok": False, "text": f"no reply from the run ({e.__class__.__name__})"}

    # ---- to the pages ----------------------------------------------------------------------------------------
    def snapshot(self) -> dict:
        """The full state, for a page that has just connected and for /api/state."""
        base = self.feed.full() if self.feed is not None else {"layout": None}
        return {"type": "full", "seq": self.seq, "attached": self.attached, "read_only": self.read_only,
                "hello": {k: v for k, v in self.hello.items() if k != "token"}, "status": self.status,
                "result": self.result, "ended": self.ended, "events": self.events[-100:],
                "server": {"tick_ms": _pct(self.tick_ms), "tick_s": TICK_S}, **base}

    def tick(self) -> None:
        """One update: new rows into the feed, and what changed to every page."""
        if self.reader is not None and self.feed is not None:
            self.feed.add(self.reader.read())
        self.seq += 1
        msg = {"type": "delta", "seq": self.seq, "server_ms": time.time() * 1e3, "attached": self.attached,
               "status": self.status}
        if self.feed is not None:
            msg.update(self.feed.take_delta())
            msg["console_skipped_rows"] = self.reader.skipped_rows if self.reader is not None else 0
        if self._new_events:
            msg["events"], self._new_events = self._new_events, []
        if self.result_new:
            msg["result"] = self.result
            self.result_new = False
        self._queue_all(msg)

    def _broadcast_full(self) -> None:
        text = json.dumps(_finite(self.snapshot()), separators=(",", ":"))
        for c in list(self.clients):
            c.put(text)

    def _queue_all(self, msg: dict) -> None:
        if not self.clients:
            return
        text = json.dumps(_finite(msg), separators=(",", ":"))
        for c in list(self.clients):
            c.put(text)


class _Client:
    """One page's websocket: messages queued by the server's tick, sent by the client's own task (a slow page
    gets its backlog collapsed: the newest full state instead of a growing queue)."""

    def __init__(self, ws, state: ConsoleState) -> None:
        self.ws, self.state = ws, state
        self.queue: asyncio.Queue = asyncio.Queue()

    def put(self, text: str) -> None:
        if self.queue.qsize() > 50:          # stalled page: drop its backlog and start it afresh
            while not self.queue.empty():
                self.queue.get_nowait()
            self.queue.put_nowait(json.dumps(_finite(self.state.snapshot())))
        self.queue.put_nowait(text)

    async def pump(self) -> None:
        while True:
            await self.ws.send_text(await self.queue.get())


def _pct(a) -> dict:
    if not a:
        return {"p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(np.asarray(a), [50, 99])
    return {"p50": round(float(p50), 2), "p99": round(float(p99), 2), "max": round(float(max(a)), 2)}


def _json(data: str | bytes | None):
    """A command message from the page's text; None for what is not JSON (or too long, or nested past
    Python's recursion limit): check_command then says what a command is."""
    if data is None or len(data) > MAX_BODY:
        return None
    try:
        return json.loads(data)
    except (ValueError, RecursionError):
        return None


def _finite(o):
    """JSON has no NaN or infinity (a sensor reading NaN is a fault the page must show): null in their place."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


# ---- the web application ---------------------------------------------------------------------------------------
class _Site:
    """The web application over one ConsoleState: who may come in (Host header, access token), the page and
    its static files, the JSON API, the websocket, and the ticker that sends the pages each update."""

    def __init__(self, state: ConsoleState, port: int) -> None:
        self.state = state
        self.hosts = {f"127.0.0.1:{port}", f"localhost:{port}"}
        self.origins = {f"http://{h}" for h in self.hosts}
        self.csp = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
                    f"connect-src 'self' ws://127.0.0.1:{port} ws://localhost:{port}; frame-ancestors 'none'")

    # ---- access ----------------------------------------------------------------------------------------------
    @staticmethod
    def _token_of(conn) -> str:
        auth = conn.headers.get("authorization", "")
        return (conn.query_params.get("token") or conn.cookies.get(COOKIE)
                or (auth[6:] if auth.lower().startswith("token ") else ""))

    def allowed(self, conn) -> bool:
        if conn.headers.get("host") not in self.hosts:
            return False
        tok = self._token_of(conn)
        return bool(self.state.token) and hmac.compare_digest(tok.encode(), self.state.token.encode())

    @staticmethod
    def forbidden() -> Response:
        return PlainTextResponse("403 forbidden: open the console at the address `rig run --console` printed "
                                 "(it carries the access token)\n", status_code=403)

    def page_headers(self, resp: Response, request: Request) -> Response:
        resp.headers["Content-Security-Policy"] = self.csp
        resp.headers["Cache-Control"] = "no-store"
        resp.headers["X-Content-Type-Options"] = "nosniff"
        if request.query_params.get("token"):
            resp.set_cookie(COOKIE, self.state.token, httponly=True, samesite="strict", path="/")
        return resp

    # ---- routes ----------------------------------------------------------------------------------------------
    async def page(self, request: Request) -> Response:
        if not self.allowed(request):
            return self.forbidden()
        return self.page_headers(FileResponse(STATIC / "index.html", media_type="text/html"), request)

    async def static(self, request: Request) -> Response:
        if not self.allowed(request):
            return self.forbidden()
        path = (STATIC / request.path_params["path"]).resolve()
        if STATIC.resolve() not in path.parents or not path.is_file():
            return PlainTextResponse("404 not found\n", status_code=404)
        return self.page_headers(FileResponse(path), request)

    async def api_state(self, request: Request) -> Response:
        if not self.allowed(request):
            return self.forbidden()
        return JSONResponse(_finite(self.state.snapshot()))

    async def api_command(self, request: Request) -> Response:
        if not self.allowed(request):
            return self.forbidden()
        body = b""
        async for chunk in request.stream():     # read no further than a command can be long
            body += chunk
            if len(body) > MAX_BODY:
                return JSONResponse({"ok": False, "text": f"a command is at most {MAX_BODY} bytes"}, status_code=413)
        reply = await self.state.command(_json(body), f"http {request.client.host}:{request.client.port}")
        code = 200 if reply["ok"] else (403 if self.state.read_only else 409)
        return JSONResponse(reply, status_code=code)

    async def ws_endpoint(self, ws: WebSocket) -> None:
        state = self.state
        origin = ws.headers.get("origin")
        if not self.allowed(ws) or (origin is not None and origin not in self.origins):
            await ws.close(code=1008)          # before accept: the handshake gets HTTP 403
            return
        await ws.accept()
        client = _Client(ws, state)
        state.clients.add(client)
        client.put(json.dumps(_finite(state.snapshot())))
        who = f"page {ws.client.host}:{ws.client.port}"
        pump = asyncio.create_task(client.pump())
        try:
            while True:
                try:
                    msg = _json(await ws.receive_text())
                except KeyError:                 # a binary frame: not a command
                    msg = None
                reply = await state.command(msg, who)
                reply.update(type="reply", id=msg.get("id") if isinstance(msg, dict) else None)
                client.put(json.dumps(reply))
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            state.clients.discard(client)
            pump.cancel()

    # ---- updates ---------------------------------------------------------------------------------------------
    async def ticker(self) -> None:
        """An update every TICK_S, and at once when a command has just been applied."""
        state = self.state
        next_t = time.monotonic()
        while not state.gone.is_set():
            t0 = time.thread_time()
            try:
                state.tick()
                state.tick_ms.append((time.thread_time() - t0) * 1e3)
            except Exception as e:      # noqa: BLE001 - one bad tick must not end the console
                log.error("console: update failed: %s: %s", e.__class__.__name__, e)
            next_t += TICK_S
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0.0
            try:
                await asyncio.wait_for(state.soon.wait(), delay)
                state.soon.clear()
                next_t = time.monotonic()
            except asyncio.TimeoutError:
                pass

    @contextlib.asynccontextmanager
    async def lifespan(self, app):
        """While the server runs: the control socket read on the event loop, and the ticker."""
        loop = asyncio.get_running_loop()
        self.state.control.setblocking(False)
        loop.add_reader(self.state.control.fileno(), self.state.on_control)
        task = asyncio.create_task(self.ticker())
        yield
        task.cancel()
        loop.remove_reader(self.state.control.fileno())


def create_app(state: ConsoleState, port: int):
    """The console's Starlette application on 127.0.0.1:`port`: the routes of _Site over `state`."""
    site = _Site(state, port)
    return Starlette(routes=[Route("/", site.page), Route("/static/{path:path}", site.static),
                             Route("/api/state", site.api_state),
                             Route("/api/command", site.api_command, methods=["POST"]),
                             WebSocketRoute("/ws", site.ws_endpoint)], lifespan=site.lifespan)


def _server(state: ConsoleState, listen: socket.socket):
    import uvicorn
    port = listen.getsockname()[1]
    config = uvicorn.Config(create_app(state, port), log_level="warning", access_log=False, lifespan="on",
                            ws="websockets-sansio", ws_per_message_deflate=False)
    server = uvicorn.Server(config)
    return server


async def _announce_ready(state: ConsoleState, server) -> None:
    """Once the server answers, every import done: "ready" to the loop's side (it prints the page's address
    then, so that the address answers at once, and starts the loop then, so that no start-up of ours competes
    with the loop's first periods)."""
    while not server.started:
        if server.should_exit:
            return
        await asyncio.sleep(0.01)
    with contextlib.suppress(OSError):
        send(state.control, {"type": "ready"})


async def _serve(state: ConsoleState, listen: socket.socket) -> None:
    server = _server(state, listen)
    stop = asyncio.ensure_future(state.gone.wait())
    serve = asyncio.ensure_future(server.serve(sockets=[listen]))
    ready = asyncio.ensure_future(_announce_ready(state, server))
    await asyncio.wait([stop, serve], return_when=asyncio.FIRST_COMPLETED)
    ready.cancel()
    await asyncio.sleep(0.3)                 # the pages get the "ended" message
    server.should_exit = True
    await serve


def _wait_hello(control: socket.socket) -> ConsoleState:
    state = ConsoleState(control)
    control.setblocking(True)
    state.on_control()
    if not state.token:
        raise SystemExit("rig console: no hello from the run's process")
    return state


def serve_in_thread(control: socket.socket, listen: socket.socket) -> threading.Thread:
    """The server as a thread of the calling process (for the comparison with a process of its own)."""
    def run():
        state = _wait_hello(control)
        asyncio.run(_serve(state, listen))
    t = threading.Thread(target=run, name="rig-console-server", daemon=True)
    t.start()
    return t


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m rig.console.server", description=__doc__.splitlines()[0])
    p.add_argument("--control-fd", type=int, required=True)
    p.add_argument("--listen-fd", type=int, required=True)
    a = p.parse_args(argv)        # its CPU and priority are set before it starts (rig/console/link.py)
    cliargs.log_to_stderr("console")
    control = socket.socket(fileno=a.control_fd)
    listen = socket.socket(fileno=a.listen_fd)
    state = _wait_hello(control)
    asyncio.run(_serve(state, listen))
    return 0


if __name__ == "__main__":
    sys.exit(main())

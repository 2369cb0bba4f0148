"""The console's web server: stdlib ``ThreadingHTTPServer``, static page, JSON API and
server-sent events.

Endpoints (all on 127.0.0.1 unless told otherwise):

* ``GET /`` the page; ``GET /static/<file>`` its script and style (no CDN, no build step).
* ``GET /api/state`` the whole :meth:`ConsoleState.snapshot` as JSON.
* ``GET /api/events`` server-sent events: ``snapshot`` (everything, once), then ``update``
  (the sections that changed) and ``clock`` (``{"now": t}`` once a second). Every browser
  gets the same state.
* ``GET /map/<level>.png`` a map level; ``GET /image/<id>.png`` an image thumbnail.
* ``POST /api/action`` ``{"action": name, "args": {...}}`` runs a :class:`ConsoleActions`
  method; answers ``{"ok": true, "sent": [messages as JSON]}`` or ``{"ok": false, "error": ...}``
  (HTTP 400).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import urlsplit

from coex_core import jsonfmt
from coex_core.errors import CoexError, RequestRejected
from coex_core.messages import Message

from .hub import ConsoleHub
from .node import attach
from .state import ConsoleState

__all__ = ["ConsoleHub", "ConsoleServer", "serve"]

log = logging.getLogger(__name__)

_STATIC = {"app.js": "text/javascript", "style.css": "text/css", "index.html": "text/html"}


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    return str(obj)


def dumps(obj: Any) -> str:
    return json.dumps(obj, default=_jsonable, allow_nan=False, separators=(",", ":"))


class _Handler(BaseHTTPRequestHandler):
    server: ConsoleServer
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s " + format, self.address_string(), *args)

    # ------------------------------------------------------------------ helpers
    def _send(self, code: int, body: bytes, ctype: str, cache: bool = False) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, code: int, obj: Any) -> None:
        self._send(code, dumps(obj).encode(), "application/json")

    def _not_found(self) -> None:
        self._json(HTTPStatus.NOT_FOUND, {"ok": False, "error": f"no such page {self.path}"})

    # ------------------------------------------------------------------ GET
    def do_GET(self) -> None:
        path = urlsplit(self.path).path
        hub = self.server.hub
        if path in ("/", "/index.html"):
            self._send(200, _asset("index.html"), "text/html; charset=utf-8")
        elif path.startswith("/static/"):
            name = path[len("/static/"):]
            if name not in _STATIC:
                return self._not_found()
            self._send(200, _asset(name), _STATIC[name] + "; charset=utf-8")
        elif path == "/favicon.ico":
            self._send(204, b"", "image/x-icon", cache=True)
        elif path == "/api/state":
            self._json(200, hub.snapshot())
        elif path == "/api/events":
            self._events()
        elif path.startswith("/map/") and path.endswith(".png"):
            try:
                level = int(path[5:-4])
            except ValueError:
                return self._not_found()
            with hub.lock:
                png, render = hub.state.map_png_job(level)
            if render is not None:
                png = render()  # drawn outside the lock: the node's loop never waits for it
            if png is None:
                return self._not_found()
            self._send(200, png, "image/png", cache=True)
        elif path.startswith("/image/") and path.endswith(".png"):
            try:
                iid = int(path[7:-4])
            except ValueError:
                return self._not_found()
            with hub.lock:
                png = hub.state.image_png(iid)
            if png is None:
                return self._not_found()
            self._send(200, png, "image/png", cache=True)
        else:
            self._not_found()

    do_HEAD = do_GET

    def _events(self) -> None:
        hub = self.server.hub
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        with hub.lock:
            snap = hub.state.snapshot()
            seen = dict(hub.state.versions)
            last_now = hub.state.now
        last_clock = time.monotonic()
        try:
            self._event("snapshot", snap)
            while not hub.closed and not self.server.stopping:
                changes = hub.wait_changes(seen, 1.0, coalesce=self.server.coalesce)
                if changes:
                    with hub.lock:
                        changes["now"] = hub.state.now
                    self._event("update", changes)
                now = hub.state.now
                if time.monotonic() - last_clock >= 1.0:
                    # the clock also keeps the connection alive (and finds dead browsers)
                    self._event("clock", {"now": now, "moved": now != last_now})
                    last_now, last_clock = now, time.monotonic()
        except (BrokenPipeError, ConnectionResetError, OSError):
            return

    def _event(self, name: str, data: Any) -> None:
        self.wfile.write(f"event: {name}\ndata: {dumps(data)}\n\n".encode())
        self.wfile.flush()

    # ------------------------------------------------------------------ POST
    def do_POST(self) -> None:
        if urlsplit(self.path).path != "/api/action":
            return self._not_found()
        # Only the console's own page may act: a JSON body (other sites' pages cannot send one
        # without a CORS preflight, which this server never grants) from the same origin.
        ctype = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
        origin = self.headers.get("Origin")
        if ctype != "application/json":
            return self._json(415, {"ok": False, "error": "actions must be application/json"})
        if origin is not None and urlsplit(origin).netloc != self.headers.get("Host", ""):
            return self._json(403, {"ok": False, "error": f"cross-origin action from {origin}"})
        try:
            length = int(self.headers.get("Content-Length", "0"))
            if not 0 <= length <= 65536:
                raise ValueError("body too large")
            body = json.loads(self.rfile.read(length) or b"{}")
            action = str(body["action"])
            args = body.get("args") or {}
            if not isinstance(args, dict):
                raise ValueError("args must be an object")
        except (ValueError, KeyError, TypeError) as exc:
            return self._json(400, {"ok": False, "error": f"bad request: {exc}"})
        try:
            sent = self.server.hub.act(action, args)
        except CoexError as exc:
            return self._json(400, {"ok": False, "error": str(exc)})
        except Exception as exc:  # never let an operator action kill the console
            log.exception("action %s failed", action)
            return self._json(500, {"ok": False, "error": f"{type(exc).__name__}: {exc}"})
        self._json(200, {"ok": True, "sent": [_describe(m) for m in sent]})


def _describe(item: Any) -> dict[str, Any]:
    if isinstance(item, Message):
        return jsonfmt.to_json(item)
    # a region the bathymetry receiver will send as MapRoiRequest (and retry)
    fields = ("level", "x0", "y0", "w", "h", "fill_gaps")
    return {"type": "MapRoiRequest", "queued": True,
            **{k: getattr(item, k) for k in fields if hasattr(item, k)}}


def _asset(name: str) -> bytes:
    return resources.files(__package__).joinpath("static", name).read_bytes()


class ConsoleServer(ThreadingHTTPServer):
    """The console's HTTP server, running in a background thread once :meth:`start` is called."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, hub: ConsoleHub, host: str = "127.0.0.1", port: int = 8080) -> None:
        super().__init__((host, port), _Handler)
        self.hub = hub
        self.stopping = False
        #: Seconds an event stream waits after a change to send a burst as one update.
        self.coalesce = 0.2
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        name = host.decode() if isinstance(host, bytes) else str(host)
        return f"http://{name}:{port}/"

    def start(self) -> ConsoleServer:
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="coex-console", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self.stopping = True
        self.hub.close()
        self.shutdown()
        self.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def __enter__(self) -> ConsoleServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve(target: Any, host: str = "127.0.0.1", port: int = 8080, *,
          clock: Callable[[], float] | None = None,
          stream_names: dict[int, str] | None = None) -> ConsoleServer:
    """Serve the console in a background thread and return the running server (``server.url``,
    ``server.hub``, ``server.close()``). Port 0 picks a free port.

    ``target`` is a :class:`ConsoleHub`, a topside :class:`~coex_core.node.Node` (a hub is made
    with :func:`~coex_plugins.console.node.attach`; the loop driving the node must then hold
    ``server.hub.lock`` while stepping it and call ``server.hub.pump(node, now)``), or a
    :class:`ConsoleState` (view only: actions are refused). ``stream_names`` names the
    vehicle's streams in the queue table (with a node)."""
    if isinstance(target, ConsoleHub):
        hub = target
    elif isinstance(target, ConsoleState):
        def refuse(msg: Message) -> None:
            raise RequestRejected("this console is view-only (no topside node to send with)")
        hub = ConsoleHub(target, refuse, clock or (lambda: target.now))
    elif hasattr(target, "manager") and hasattr(target, "events"):
        hub = attach(target, clock, stream_names=stream_names)
    else:
        raise TypeError(f"serve() needs a ConsoleHub, Node or ConsoleState, "
                        f"got {type(target).__name__}")
    return ConsoleServer(hub, host, port).start()

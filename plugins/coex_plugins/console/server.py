"""The console's web server: stdlib ``ThreadingHTTPServer``, static page, JSON API and
server-sent events.

Endpoints (all on 127.0.0.1 unless told otherwise):

* ``GET /`` the page; ``GET /static/<file>`` its script and style (no CDN, no build step).
* ``GET /api/state`` the whole :meth:`ConsoleState.snapshot` as JSON.
* ``GET /api/events`` server-sent events: ``snapshot`` (everything, once), then ``update``
  (the sections that changed) and ``clock`` (``{"now": t}`` once a second). Every browser
  gets the same state.
* ``GET /map/<level>.png`` a map level (its drawn overview); ``GET
  /map/<level>/window.png?x0=&y0=&x1=&y1=&step=`` the part of a big level on screen, at
  ``step`` level cells per pixel, read from the receiver's tiles; ``GET /image/<id>.png`` an
  image thumbnail (``?full=1``: at full size, its crops pasted over it); ``GET /crop/<id>.png``
  what a crop (a region coded on its own) shows of its box.
* ``POST /api/action`` ``{"action": name, "args": {...}}`` runs a :class:`ConsoleActions`
  method; answers ``{"ok": true, "sent": [messages as JSON]}`` or ``{"ok": false, "error": ...}``
  (HTTP 400).
* ``GET /api/whoami``: ``{"auth", "name", "role", "may_command", "csrf"}``.

With an :class:`~coex_plugins.console.access.Access` (an operators file), everything but
``/login`` needs a session: ``GET /login`` the sign-in page, ``POST /login`` (form or JSON
``name``, ``password``) sets the session cookie (HttpOnly, SameSite=Strict, Secure under TLS),
``POST /logout`` ends it. An unauthenticated page request is redirected to ``/login`` (303), an
API or stream request gets 401; ``POST /api/action`` also needs the operator role (403 for a
viewer), the session's CSRF token in ``X-CSRF-Token`` (403) and the operator's command rate
(429). Failed sign-ins are logged and, after five in five minutes, refused for a while (429).
"""

from __future__ import annotations

import hmac
import json
import logging
import math
import ssl
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

from coex_core import jsonfmt
from coex_core.errors import CoexError, RequestRejected
from coex_core.messages import Message

from .access import Access, Session, describe, parse_cookies
from .hub import ConsoleHub
from .node import attach
from .state import ConsoleState

__all__ = ["ConsoleHub", "ConsoleServer", "serve"]

log = logging.getLogger(__name__)

_STATIC = {"app.js": "text/javascript", "style.css": "text/css", "index.html": "text/html"}
COOKIE = "coex_session"
#: the largest body a sign-in may have
MAX_LOGIN_BODY = 4096
_LOCAL = Session("", "", "operator", "", float("inf"))  # a console without sign-in


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

    # ------------------------------------------------------------------ access
    def _session(self) -> Session | None:
        access = self.server.access
        if access is None:
            return _LOCAL
        return access.session(parse_cookies(self.headers.get("Cookie")).get(COOKIE))

    def _client(self) -> str:
        return str(self.client_address[0])

    def _redirect(self, where: str, cookie: str | None = None) -> None:
        self.send_response(303)
        self.send_header("Location", where)
        self.send_header("Content-Length", "0")
        self.send_header("Cache-Control", "no-store")
        if cookie is not None:
            self.send_header("Set-Cookie", cookie)
        self.end_headers()

    def _cookie(self, sid: str, max_age: int) -> str:
        secure = "; Secure" if self.server.tls else ""
        return f"{COOKIE}={sid}; HttpOnly; SameSite=Strict; Path=/; Max-Age={max_age}{secure}"

    def _login_page(self, code: int = 200, error: str = "") -> None:
        self._send(code, _login_html(error).encode(), "text/html; charset=utf-8")

    # ------------------------------------------------------------------ GET
    def do_GET(self) -> None:
        path = urlsplit(self.path).path
        hub = self.server.hub
        if path == "/login":
            return self._login_page() if self.server.access is not None else self._redirect("/")
        if path == "/favicon.ico":
            return self._send(204, b"", "image/x-icon", cache=True)
        session = self._session()
        if session is None:
            if path in ("/", "/index.html"):
                return self._redirect("/login")
            return self._json(401, {"ok": False, "error": "sign in first (/login)"})
        if path == "/api/whoami":
            return self._json(200, {"auth": self.server.access is not None, **describe(session)})
        if path in ("/", "/index.html"):
            self._send(200, _asset("index.html"), "text/html; charset=utf-8")
        elif path.startswith("/static/"):
            name = path[len("/static/"):]
            if name not in _STATIC:
                return self._not_found()
            self._send(200, _asset(name), _STATIC[name] + "; charset=utf-8")
        elif path == "/api/state":
            self._json(200, hub.snapshot())
        elif path == "/api/events":
            self._events()
        elif path.startswith("/map/") and path.endswith("/window.png"):
            try:
                level = int(path[5:-len("/window.png")])
                q = {k: v[-1] for k, v in parse_qs(urlsplit(self.path).query).items()}
                box = [float(q[k]) for k in ("x0", "y0", "x1", "y1")]
                step = int(q.get("step", "1"))
            except (KeyError, ValueError):
                return self._not_found()
            if not all(math.isfinite(v) for v in box):
                return self._not_found()
            with hub.lock:
                job = hub.state.map_window_job(level, box[0], box[1], box[2], box[3], step=step)
            if job is None:
                return self._not_found()
            self._send(200, job(), "image/png", cache=True)  # drawn outside the lock
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
        elif path.startswith("/crop/") and path.endswith(".png"):
            try:
                cid = int(path[6:-4])
            except ValueError:
                return self._not_found()
            with hub.lock:
                png = hub.state.crop_png(cid)
            if png is None:
                return self._not_found()
            self._send(200, png, "image/png", cache=True)
        elif path.startswith("/image/") and path.endswith(".png"):
            try:
                iid = int(path[7:-4])
            except ValueError:
                return self._not_found()
            full = "full=1" in urlsplit(self.path).query
            with hub.lock:
                png = hub.state.image_png(iid, full=full)
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
            seen: dict[str, Any] = dict(hub.state.versions)
            # what this page holds of the map: its updates carry only what changed
            seen["_map"] = hub.state.map_held(snap["map"])
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
        path = urlsplit(self.path).path
        if path == "/login":
            return self._login()
        if path == "/logout":
            return self._logout()
        if path != "/api/action":
            return self._not_found()
        session = self._session()
        if session is None:
            return self._json(401, {"ok": False, "error": "sign in first (/login)"})
        if not session.may_command:
            return self._json(403, {"ok": False, "error": f"{session.name} is a viewer: viewers cannot command"})
        access = self.server.access
        if access is not None and not hmac.compare_digest(self.headers.get("X-CSRF-Token", ""), session.csrf):
            return self._json(403, {"ok": False, "error": "missing or wrong CSRF token (reload the page)"})
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
        if access is not None:
            wait = access.command_allowed(session)
            if wait:
                log.warning("command rate limit: %s asked for %s", session.name, action)
                return self._json(429, {"ok": False, "error": f"{session.name}: at most "
                                        f"{access.commands_per_minute} commands a minute; wait {wait:.0f} s"})
        try:
            hub = self.server.hub
            # the signed-in name goes with the commands (a console without sign-in has none)
            sent = hub.act(action, args, session.name) if session.name else hub.act(action, args)
        except CoexError as exc:
            return self._json(400, {"ok": False, "error": str(exc)})
        except Exception as exc:  # never let an operator action kill the console
            log.exception("action %s failed", action)
            return self._json(500, {"ok": False, "error": f"{type(exc).__name__}: {exc}"})
        self._json(200, {"ok": True, "sent": [_describe(m) for m in sent]})

    def _login(self) -> None:
        access = self.server.access
        if access is None:
            return self._redirect("/")
        ctype = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
        try:
            length = int(self.headers.get("Content-Length", "0"))
            if not 0 <= length <= MAX_LOGIN_BODY:
                raise ValueError("body too large")
            raw = self.rfile.read(length).decode()
            if ctype == "application/json":
                body = json.loads(raw or "{}")
                name, secret = str(body.get("name", "")), str(body.get("password", ""))
            else:
                form = parse_qs(raw)
                name, secret = form.get("name", [""])[0], form.get("password", [""])[0]
        except (ValueError, UnicodeDecodeError) as exc:
            return self._login_page(400, f"bad sign-in request: {exc}")
        client = self._client()
        wait = max(access.locked_out(name), access.locked_out(client))
        if wait:
            return self._login_page(429, f"too many failed sign-ins: try again in {wait:.0f} s")
        s = access.login(name, secret, client)
        if s is None:
            return self._login_page(401, "wrong name or password")
        self._redirect("/", self._cookie(s.sid, int(access.session_seconds)))

    def _logout(self) -> None:
        access = self.server.access
        session = self._session()
        if access is not None and session is not None:
            if not hmac.compare_digest(self.headers.get("X-CSRF-Token", ""), session.csrf):
                return self._json(403, {"ok": False, "error": "missing or wrong CSRF token"})
            access.logout(session.sid)
        self.send_response(200)
        body = b'{"ok":true}'
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Set-Cookie", self._cookie("", 0))
        self.end_headers()
        self.wfile.write(body)


def _login_html(error: str) -> str:
    import html

    msg = f'<p class="error" role="alert">{html.escape(error)}</p>' if error else ""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>CoEx console: sign in</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{{font:15px system-ui,sans-serif;background:#0d1b26;color:#e6eef3;display:grid;
place-items:center;height:100vh;margin:0}}form{{background:#152a38;padding:24px 28px;border-radius:8px;
min-width:280px}}label{{display:block;margin:10px 0 4px}}input{{width:100%;padding:6px;box-sizing:border-box}}
button{{margin-top:16px;padding:6px 16px}}.error{{color:#ff9b8a}}</style></head>
<body><form method="post" action="/login"><h1>CoEx console</h1>{msg}
<label for="name">Name</label><input id="name" name="name" autocomplete="username" required>
<label for="password">Password or token</label>
<input id="password" name="password" type="password" autocomplete="current-password" required>
<button type="submit" id="signin">Sign in</button></form></body></html>
"""


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

    def __init__(self, hub: ConsoleHub, host: str = "127.0.0.1", port: int = 8080, *,
                 access: Access | None = None, tls: ssl.SSLContext | None = None) -> None:
        super().__init__((host, port), _Handler)
        if tls is not None:
            self.socket = tls.wrap_socket(self.socket, server_side=True)
        #: sign-in and roles (None: no sign-in; only for a console on the loopback address)
        self.access = access
        self.tls = tls
        self.hub = hub
        self.stopping = False
        #: Seconds an event stream waits after a change to send a burst as one update.
        self.coalesce = 0.2
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        name = host.decode() if isinstance(host, bytes) else str(host)
        return f"{'https' if self.tls else 'http'}://{name}:{port}/"

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
          stream_names: dict[int, str] | None = None,
          access: Access | None = None, tls: ssl.SSLContext | None = None) -> ConsoleServer:
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
    return ConsoleServer(hub, host, port, access=access, tls=tls).start()


def tls_context(cert: str, key: str) -> ssl.SSLContext:
    """A server TLS context (TLS 1.2 or newer) from a PEM certificate chain and key."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise CoexError(f"cannot load the TLS certificate {cert} and key {key}: {exc}") from exc
    return ctx

"""The console's web server: a Starlette application on uvicorn (ASGI), in a background thread
with its own event loop. Static page, JSON API and server-sent events.

Endpoints (all on 127.0.0.1 unless told otherwise; docs/console.md has the table of actions):

* ``GET /`` the page; ``GET /static/<file>`` its script and style (no CDN, no build step).
* ``GET /api/state`` the whole :meth:`ConsoleState.snapshot` as JSON.
* ``GET /api/events`` server-sent events: ``snapshot`` (everything, once), then ``update``
  (the sections that changed), ``clock`` (``{"now": t}`` once a second) and ``session`` (the
  signed-in person's role changed). Every browser gets the same state.
* ``GET /map/<level>.png`` a map level (its drawn overview); ``GET
  /map/<level>/window.png?x0=&y0=&x1=&y1=&step=`` the part of a big level on screen, at
  ``step`` level cells per pixel, read from the receiver's tiles; ``GET /image/<id>.png`` an
  image thumbnail (``?full=1``: at full size, its crops pasted over it); ``GET /crop/<id>.png``
  what a crop (a region coded on its own) shows of its box.
* ``POST /api/action`` ``{"action": name, "args": {...}}`` runs a :class:`ConsoleActions`
  method; answers ``{"ok": true, "sent": [messages as JSON]}`` or ``{"ok": false, "error": ...}``
  (HTTP 400 with the reason).
* ``GET /api/whoami``: ``{"auth", "name", "role", "may_command", "csrf"}``.

With an :class:`~coex_apps.console.access.Access` (an operators file), everything but
``/login`` needs a session: ``GET /login`` the sign-in page, ``POST /login`` (form or JSON
``name``, ``password``) sets the session cookie (HttpOnly, SameSite=Strict, Secure under TLS),
``POST /logout`` ends it (and its event streams). An unauthenticated page request is redirected
to ``/login`` (303), an API or stream request gets 401; ``POST /api/action`` also needs the
operator role (403 for a viewer), the session's CSRF token in ``X-CSRF-Token`` (403) and the
operator's command rate (429).

Whatever the sign-in: a ``Host`` header not among :attr:`ConsoleServer.allowed_hosts` is refused
(400: DNS rebinding), an action from another origin is refused (403), every answer carries the
security headers of :func:`security_headers` and no ``Server`` banner, and the work one request
may cause is bounded (:class:`Limits`: 413, 429 or 503 with the reason). Every refusal is logged
with who and why.
"""

from __future__ import annotations

import asyncio
import base64
import gc
import hashlib
import hmac
import html
import json
import logging
import math
import socket
import ssl
import threading
import time
from asyncio import sslproto
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from importlib import resources
from typing import Any, cast
from urllib.parse import parse_qs, urlsplit

import h11
import uvicorn
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import ClientDisconnect, Request, cookie_parser
from starlette.responses import RedirectResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.types import Message as AsgiMessage
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware
from uvicorn.protocols.http.h11_impl import H11Protocol

from coex import CoexError, Message, Node, RequestRejected
from coex_core import jsonfmt
from coex_plugins.bathymetry import Region

from .access import DEVICE_DAYS, Access, Session, SignInRefused, describe
from .admission import (
    Busy,
    Connection,
    Doors,
    FairQueue,
    Lanes,
    Limits,
    Said,
    limit_arenas,
    lower_priority,
    raise_fd_limit,
    trim_memory,
)
from .fleet import FleetHub
from .hub import ConsoleHub
from .node import attach
from .state import ConsoleState

__all__ = ["ConsoleHub", "ConsoleServer", "Limits", "serve", "security_headers"]

log = logging.getLogger(__name__)

_STATIC = {"app.js": "text/javascript", "style.css": "text/css", "index.html": "text/html"}
COOKIE = "coex_session"
#: the cookie that makes a browser known for the name it signed in as (``Access.device``)
DEVICE_COOKIE = "coex_device"
#: the largest body a sign-in may have
MAX_LOGIN_BODY = 4096
DEVICE_SECONDS = DEVICE_DAYS * 86400.0
#: the largest number an action's JSON may hold (in size), and its deepest nesting
MAX_NUMBER = 1e12
MAX_DEPTH = 32
#: the largest coordinate of a map window (metres, in size) and its largest step
MAX_WINDOW_COORD = 1e9
MAX_WINDOW_STEP = 1 << 20
_LOCAL = Session("", "", "operator", "", float("inf"))  # a console without sign-in


class _Refused(Exception):
    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


# ------------------------------------------------------------------ HTTP/1.1 on admitted connections
class _H11(h11.Connection):
    """h11's connection with the head size the console allows (h11 bounds only a head that is
    still incomplete: a whole 100 KB head in one read passed) and no request framed two ways
    (``Content-Length`` and ``Transfer-Encoding`` both: refused, as a smuggling attempt)."""

    def __init__(self, head_bytes: int) -> None:
        super().__init__(h11.SERVER, max_incomplete_event_size=head_bytes)
        self.head_bytes = head_bytes
        #: why the last request was refused (said in the answer and the log)
        self.refusal = ""
        self.refusal_status = 400

    def next_event(self) -> Any:
        try:
            event = super().next_event()
        except h11.RemoteProtocolError as exc:
            self.refusal = f"bad HTTP request: {exc}"
            self.refusal_status = exc.error_status_hint
            raise
        if isinstance(event, h11.Request):
            raw = event.headers.raw_items()
            size = len(event.method) + len(event.target) + 12 + sum(len(k) + len(v) + 4 for k, v in raw)
            if size > self.head_bytes:
                self.refusal = f"the request head is {size} bytes, more than the {self.head_bytes} allowed"
                self.refusal_status = 431
                raise h11.RemoteProtocolError(self.refusal, error_status_hint=431)
            names = {k.lower() for k, _ in raw}
            if b"content-length" in names and b"transfer-encoding" in names:
                self.refusal = "a request with both Content-Length and Transfer-Encoding is refused"
                self.refusal_status = 400
                raise h11.RemoteProtocolError(self.refusal, error_status_hint=400)
        return event


def _protocol(limits: Limits, doors: Doors) -> type[H11Protocol]:
    """uvicorn's h11 protocol on connections the console admits (:class:`Doors`, by client
    address), with a deadline for each request's head (uvicorn times out an idle keep-alive
    connection, but not one that never finishes its request head) and the console's head and
    framing checks (:class:`_H11`)."""

    class Protocol(H11Protocol):
        _head_timer: asyncio.TimerHandle | None = None
        #: the connection's place in :class:`Doors` (set by :class:`_Door`)
        door: Connection | None = None

        def __init__(self, *args: Any, **kw: Any) -> None:
            super().__init__(*args, **kw)
            self.h11 = _H11(limits.header_bytes)
            self.conn = self.h11
            self.logger = _UVICORN  # its "Invalid HTTP request received." is said with the address

        def idle(self) -> bool:
            """No request being answered (between requests, or a head still arriving)."""
            return self.cycle is None or self.cycle.response_complete

        def _arm(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
            self._head_timer = self.loop.call_later(limits.header_seconds, self._head_timeout)

        def _head_timeout(self) -> None:
            self._head_timer = None
            if self.idle() and not self.transport.is_closing():
                doors.say(self.door.address if self.door else "?",
                          f"console closed a connection from {self.door.address if self.door else '?'} "
                          f"that sent no request head in {limits.header_seconds:.0f} s", logging.INFO,
                          kind="head timeout")
                try:
                    self.conn.send(h11.ConnectionClosed())
                except h11.LocalProtocolError:
                    pass
                self.transport.close()

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm()

        def send_400_response(self, msg: str) -> None:
            """A request h11 or the console's checks refused: answered (400, or 431 for a head
            too large) and the connection closed; logged with the client address."""
            status = self.h11.refusal_status if self.h11.refusal_status in (400, 408, 413, 414, 431) else 400
            reason = self.h11.refusal or msg
            address = self.client[0] if self.client else "?"
            doors.say(address, f"console refused a request from {address}: HTTP {status}, {reason}",
                      kind=f"HTTP {status}")
            body = reason[:300].encode("utf-8", "replace")
            try:
                out = self.conn.send(h11.Response(status_code=status, reason=HTTPStatus(status).phrase.encode(), headers=[
                    (b"content-type", b"text/plain; charset=utf-8"), (b"x-content-type-options", b"nosniff"),
                    (b"connection", b"close"), (b"content-length", str(len(body)).encode())]))
                out += self.conn.send(h11.Data(data=body)) or b""
                out += self.conn.send(h11.EndOfMessage()) or b""
                self.transport.write(out)
            except h11.LocalProtocolError:
                pass
            self.transport.close()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm()

        def release_door(self) -> None:
            doors.release(self.door)

        def connection_lost(self, exc: Exception | None) -> None:
            doors.release(self.door)
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None
            super().connection_lost(exc)

    return Protocol


class _WithoutAddress(logging.Filter):
    """uvicorn's line about a bad request names no client: the console says it with the address
    (``send_400_response``)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "Invalid HTTP request received."


_UVICORN = logging.getLogger("uvicorn.error.console")
_UVICORN.addFilter(_WithoutAddress())
_UVICORN.setLevel(logging.INFO)  # (not TRACE: uvicorn would format a line for every connection)


class _Tls(sslproto.SSLProtocol):
    """TLS for one admitted connection, with a read buffer of 16 KiB instead of asyncio's 256
    KiB (which every idle TLS socket held: 5,000 of them kept 1.2 GB, and after they closed
    until a full garbage collection), and the console's deadline for the handshake."""

    max_size = 16 * 1024

    def __init__(self, loop: asyncio.AbstractEventLoop, app: Any, context: ssl.SSLContext,
                 handshake_seconds: float) -> None:
        super().__init__(loop, app, context, None, server_side=True,  # type: ignore[arg-type]
                         ssl_handshake_timeout=handshake_seconds, ssl_shutdown_timeout=5.0)  # type: ignore[arg-type]
        self.coex_app = app

    def connection_lost(self, exc: BaseException | None) -> None:
        self.coex_app.release_door()  # (a handshake that failed never reaches the app)
        super().connection_lost(exc)


class _Door(asyncio.Protocol):
    """The first protocol of every accepted connection: it admits the connection by its client
    address (:class:`~.admission.Doors`) before anything else is made for it (a refused one
    costs no HTTP or TLS state), then hands it to TLS (the handshake counted as the
    connection's) or straight to HTTP."""

    def __init__(self, make: Callable[[], Any], doors: Doors, tls: ssl.SSLContext | None,
                 handshake_seconds: float, loop: asyncio.AbstractEventLoop) -> None:
        self.make, self.doors, self.tls, self.handshake_seconds, self.loop = make, doors, tls, handshake_seconds, loop
        self.app: Any = None

    def idle(self) -> bool:
        return self.app is None or bool(self.app.idle())

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        t = cast(asyncio.Transport, transport)
        peer = t.get_extra_info("peername")
        address, port = (str(peer[0]), int(peer[1])) if isinstance(peer, tuple) else ("?", id(self))
        door = self.doors.admit(address, port, self.idle, t.abort)
        if door is None:
            if self.tls is None:
                t.write(_NO_ROOM)
                t.close()
            else:
                t.abort()
            return
        app = self.app = self.make()
        app.door = door
        if self.tls is not None:
            tls = _Tls(self.loop, app, self.tls, self.handshake_seconds)
            t.set_protocol(tls)
            tls.connection_made(t)
        else:
            t.set_protocol(app)
            app.connection_made(t)

    def data_received(self, data: bytes) -> None:
        pass  # a refused connection's request: not read


_NO_REASON = b"the console has no room for another connection from your address: try again"
_NO_ROOM = (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\nretry-after: 1\r\n"
            b"connection: close\r\ncontent-length: " + str(len(_NO_REASON)).encode() + b"\r\n\r\n" + _NO_REASON)


class _Uvicorn(uvicorn.Server):
    """uvicorn's server on the console's own listening socket and connection factory (plain
    HTTP, or TLS admitted before its handshake), with the console's upkeep every second:
    refusal counts logged, freed memory given back."""

    def __init__(self, config: uvicorn.Config, console: ConsoleServer) -> None:
        super().__init__(config)
        self.console = console
        self._trimming = False
        self._trimmed_at = 0.0
        self._collected_at = -1e9
        self._activity = 0
        self._closed = 0

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await self.lifespan.startup()
        loop = asyncio.get_running_loop()
        console, config = self.console, self.config
        proto = console.protocol

        def app() -> H11Protocol:
            return proto(config=config, server_state=self.server_state, app_state=self.lifespan.state, _loop=loop)

        def make() -> asyncio.BaseProtocol:
            return _Door(app, console.doors, console.tls, console.limits.header_seconds, loop)

        self.servers = [await loop.create_server(make, sock=sock, backlog=1024) for sock in sockets or []]
        self.started = True

    async def on_tick(self, counter: int) -> bool:
        if counter % 10 == 0:
            console = self.console
            console.say.flush()
            if console.access is not None:
                console.access.say.flush()
            closed = console.doors.closed
            activity = closed + console.app_routes.renders.done + console.app_routes.sign_ins.done
            now = time.monotonic()
            if activity > self._activity and now - self._trimmed_at >= 5.0 and not self._trimming:
                # connections closed, pictures drawn, passwords checked: memory to give back.
                # Objects of closed connections may be held by reference cycles (a TLS
                # handshake that failed keeps its exception's frames) until a full collection:
                # one after many closed (at most every 30 s), and one when it has gone quiet
                quiet = activity - self._activity < 16
                collect = closed > self._closed and (
                    (closed - self._closed >= 256 and now - self._collected_at >= 30.0) or quiet)
                if collect:
                    self._closed, self._collected_at = closed, now
                self._activity, self._trimmed_at, self._trimming = activity, now, True

                def trim() -> None:
                    try:
                        if collect:
                            gc.collect()
                        trim_memory()
                    finally:
                        self._trimming = False

                asyncio.get_running_loop().run_in_executor(console.housekeeping, trim)
        return await super().on_tick(counter)

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        await super().shutdown(sockets)
        self.console.doors.abort_all()
        self.console.say.flush(force=True)


# ------------------------------------------------------------------ headers and refusals
def _sha256(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


def security_headers(tls: bool, style_hash: str | None = None) -> list[tuple[bytes, bytes]]:
    """The headers every answer carries: a Content-Security-Policy that allows only the
    console's own script, style, pictures and connections and no framing (clickjacking),
    ``X-Frame-Options: DENY`` for older browsers, ``nosniff``, ``Referrer-Policy:
    same-origin`` (``no-referrer`` would make browsers send ``Origin: null`` with the sign-in
    form), and under TLS ``Strict-Transport-Security``."""
    style = f"'self' {style_hash}" if style_hash else "'self'"
    csp = ("default-src 'none'; script-src 'self'; style-src " + style + "; img-src 'self'; "
           "connect-src 'self'; form-action 'self'; base-uri 'none'; frame-ancestors 'none'")
    out = [(b"content-security-policy", csp.encode()), (b"x-frame-options", b"DENY"),
           (b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"same-origin"),
           (b"cross-origin-opener-policy", b"same-origin"),
           (b"cross-origin-resource-policy", b"same-origin")]
    if tls:
        out.append((b"strict-transport-security", b"max-age=31536000"))
    return out


class _Peer:
    """Outermost: remembers the connection's own peer address (``coex.peer``) before a trusted
    proxy's ``X-Forwarded-For`` names the client (the connection is the peer's, the limits the
    client's)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            scope["coex.peer"] = scope.get("client")
        await self.app(scope, receive, send)


class _Guard:
    """The security headers on every answer (``Strict-Transport-Security`` when the client's
    scheme is https: TLS here, or a trusted proxy's ``X-Forwarded-Proto``), and a log line with
    the client address for a refusal nobody logged yet (a wrong Host, a request turned away)."""

    def __init__(self, app: ASGIApp, say: Said) -> None:
        self.app = app
        self.say = say
        self.headers = {tls: security_headers(tls) for tls in (False, True)}
        self.login_headers = {tls: security_headers(tls, _sha256(_LOGIN_STYLE)) for tls in (False, True)}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = str(scope.get("path", ""))
        if path.startswith("//"):  # ``url + "/api/state"`` with a url ending in /: as http.server did
            scope = {**scope, "path": "/" + path.lstrip("/"), "raw_path": b"/" + scope.get("raw_path", b"").lstrip(b"/")}
        https = scope.get("scheme") == "https"
        extra = (self.login_headers if scope.get("path") == "/login" else self.headers)[https]

        async def send_with_headers(message: AsgiMessage) -> None:
            if message["type"] == "http.response.start":
                status = int(message["status"])
                names = {k.lower() for k, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []),
                                      *((k, v) for k, v in extra if k not in names)]
                if status >= 400 and not scope.get("coex.logged"):
                    host = dict(scope.get("headers", [])).get(b"host", b"").decode("latin-1")
                    client = (scope.get("client") or ("?",))[0]
                    self.say(client, f"console refused {scope.get('method')} {str(scope.get('path'))[:100]} from "
                                     f"{client} (Host {host[:100]!r}): HTTP {status}", kind=f"HTTP {status}")
            await send(message)

        await self.app(scope, receive, send_with_headers)


class _Admission:
    """Requests being answered at once, per client address, per session and in all, with
    operators' sessions in a lane of their own (:class:`~.admission.Lanes`); a request beyond
    is answered 503 with the reason (and the connection closed). It also marks a connection
    that carried an operator's request (never closed to make room). Event streams are counted
    by their own handler (:meth:`_App.events`)."""

    def __init__(self, app: ASGIApp, server: ConsoleServer) -> None:
        self.app = app
        self.server = server

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        server = self.server
        client = str((scope.get("client") or ("?",))[0])
        operator, session = server.classify(scope)
        scope["coex.operator"] = operator
        scope["coex.session"] = session
        scope["coex.key"] = session or client
        peer = scope.get("coex.peer")
        # a connection that carried an operator's session is kept (without sign-in everyone is
        # the operator: none is kept for it; a known browser's sign-in has no session yet)
        if operator and session and isinstance(peer, tuple | list) and len(peer) == 2:
            server.doors.mark_operator(str(peer[0]), int(peer[1]))
        if scope.get("path") == "/api/events":
            await self.app(scope, receive, send)
            return
        ticket = server.lanes.request(operator, client, session)
        if isinstance(ticket, str):
            scope["coex.logged"] = True
            server.say(client, f"console answered 503 to {scope.get('method')} {str(scope.get('path'))[:100]} "
                               f"from {client}: {ticket}", kind="503 " + ticket)
            body = json.dumps({"ok": False, "error": f"the console is busy: {ticket}; try again"}).encode()
            await send({"type": "http.response.start", "status": 503, "headers": [
                (b"content-type", b"application/json"), (b"retry-after", b"1"), (b"connection", b"close"),
                (b"cache-control", b"no-store"), (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})
            return
        try:
            await self.app(scope, receive, send)
        finally:
            ticket.release()


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    return str(obj)


def dumps(obj: Any) -> str:
    return json.dumps(obj, default=_jsonable, allow_nan=False, separators=(",", ":"))


def loads_bounded(raw: bytes | str) -> Any:
    """A request's JSON, refused (:class:`ValueError`, with the reason) when it holds a number
    beyond +-:data:`MAX_NUMBER` (1e308 and the like), ``NaN`` or ``Infinity``, or nests deeper
    than :data:`MAX_DEPTH` (3,000 levels once made a 500)."""
    def number(text: str) -> float:
        value = float(text)
        if not math.isfinite(value) or abs(value) > MAX_NUMBER:
            raise ValueError(f"the number {text[:40]} is out of range (at most {MAX_NUMBER:g} in size)")
        return value

    def integer(text: str) -> int:
        if len(text.lstrip("-")) > 13:
            raise ValueError(f"the number {text[:40]} is out of range (at most {MAX_NUMBER:g} in size)")
        return int(text)

    def constant(text: str) -> Any:
        raise ValueError(f"{text} is not a number")

    try:
        doc = json.loads(raw, parse_float=number, parse_int=integer, parse_constant=constant)
    except RecursionError:
        raise ValueError(f"the JSON is nested too deeply (at most {MAX_DEPTH} levels)") from None
    todo: list[tuple[Any, int]] = [(doc, 1)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, dict | list):
            if depth > MAX_DEPTH:
                raise ValueError(f"the JSON is nested too deeply (at most {MAX_DEPTH} levels)")
            todo.extend((v, depth + 1) for v in (item.values() if isinstance(item, dict) else item))
    return doc


def _json(code: int, obj: Any, headers: dict[str, str] | None = None) -> Response:
    return Response(dumps(obj), code, media_type="application/json",
                    headers={"Cache-Control": "no-store", **(headers or {})})


def _png(body: bytes) -> Response:
    return Response(body, 200, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


# ------------------------------------------------------------------ the application
class _App:
    """The routes of one console server."""

    def __init__(self, server: ConsoleServer) -> None:
        self.server = server
        self.hub = server.hub
        self.access = server.access
        self.limits = lim = server.limits
        #: pictures: drawn ``renders`` at once, an operator's first, client by client in turn
        self.renders = FairQueue([server.render_threads, server.other_render_threads], lim.renders,
                                 (lim.operator_render_queue, lim.render_queue), lim.renders_per_client,
                                 "pictures", reserved=1)
        #: password checks: a known browser's first, then addresses without failures, then the
        #: rest (addresses that failed: at a lower priority, one at a time)
        self.sign_ins = FairQueue([server.sign_in_threads, server.other_sign_in_threads],
                                  server.access.sign_ins if server.access else 1, lim.sign_in_queue, 8,
                                  "sign-ins", reserved=1, low=2)
        #: per hub: (key, time, JSON of the snapshot) and the one being made
        self._snapshots: dict[int, tuple[Any, float, bytes]] = {}
        self._making: dict[int, asyncio.Future[tuple[Any, bytes]]] = {}

    def routes(self) -> list[Route]:
        return [Route("/login", self.login_page, methods=["GET"]),
                Route("/login", self.login, methods=["POST"]),
                Route("/logout", self.logout, methods=["POST"]),
                Route("/favicon.ico", lambda r: Response(b"", 204, headers={"Cache-Control": "max-age=3600"})),
                Route("/", self.index), Route("/index.html", self.index),
                Route("/static/{name}", self.static),
                Route("/api/whoami", self.whoami), Route("/api/state", self.state),
                Route("/api/events", self.events),
                Route("/api/action", self.action, methods=["POST"]),
                Route("/map/{level}/window.png", self.map_window),
                Route("/map/{level}.png", self.map_level),
                Route("/image/{iid}.png", self.image),
                Route("/crop/{cid}.png", self.crop)]

    # -------------------------------------------------------------- refusals, sessions
    def refuse(self, request: Request, status: int, reason: str, session: Session | None = None,
               page: bool = False) -> Response:
        who = session.name if session is not None and session.name else "anonymous"
        client = self.client(request)
        request.scope["coex.logged"] = True
        self.server.say(client, f"console refused {request.method} {request.url.path[:100]} from {client} "
                                f"({who}): {reason}", kind=f"{status} {request.url.path[:100]} {who} {reason[:60]}")
        headers = {"Cache-Control": "no-store"}
        if status in (429, 503):
            headers["Retry-After"] = "1"
        if page:
            return Response(_login_html(reason), status, media_type="text/html; charset=utf-8", headers=headers)
        return _json(status, {"ok": False, "error": reason}, headers=headers)

    def client(self, request: Request) -> str:
        return request.client.host if request.client else "?"

    def operator(self, request: Request) -> bool:
        """The request is in the operators' lane (set by :class:`_Admission`)."""
        return bool(request.scope.get("coex.operator"))

    def key(self, request: Request) -> str:
        """Whose request it is, for fair queues: the session (without sign-in: the address)."""
        return str(request.scope.get("coex.key") or self.client(request))

    async def thread(self, request: Request, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` in a worker thread: the operators' own few, or the others' few (a
        flood of viewers' requests waits for the others' threads, not the operators')."""
        pool = self.server.operator_threads if self.operator(request) else self.server.other_threads
        return await asyncio.get_running_loop().run_in_executor(pool, fn, *args)

    def session(self, request: Request) -> Session | None:
        if self.access is None:
            return _LOCAL
        return self.access.session(request.cookies.get(COOKIE))

    def signed_in(self, request: Request) -> Session:
        s = self.session(request)
        if s is None:
            raise _Refused(401, "sign in first (/login)")
        return s

    def view(self, request: Request, vehicle: Any = None) -> Any:
        """The hub a request is about: a fleet console's vehicle named by ``?vehicle=`` (or
        ``vehicle``; none: the first vehicle), refused with 400 when the fleet has no such
        vehicle; a one-vehicle console's hub."""
        hub = self.hub
        if not isinstance(hub, FleetHub):
            return hub
        if vehicle is None:
            vehicle = request.query_params.get("vehicle")
        try:
            return hub.view(vehicle)
        except RequestRejected as exc:
            raise _Refused(400, str(exc)) from None

    def cookie(self, request: Request, response: Response, sid: str, max_age: int) -> None:
        # Secure whenever the browser reached the console over https: TLS here, or a trusted
        # proxy's X-Forwarded-Proto (the scheme uvicorn's proxy headers set)
        response.set_cookie(COOKIE, sid, max_age=max_age, path="/", secure=request.url.scheme == "https",
                            httponly=True, samesite="strict")

    def same_origin(self, request: Request) -> str | None:
        """Why a state-changing request is not from the console's own page (None: it is). The
        ``Origin`` (scheme, host and port) must be one of the console's public origins
        (:attr:`ConsoleServer.public_origins`; never compared with ``Host``, which a rebinding
        page controls too) and a browser's ``Sec-Fetch-Site`` must not say cross-site."""
        if request.headers.get("sec-fetch-site", "same-origin") not in ("same-origin", "none"):
            return f"cross-site request ({request.headers['sec-fetch-site'][:40]})"
        origin = request.headers.get("origin")
        if origin is None:
            return None
        if origin_of(origin) not in self.server.public_origins:
            return (f"cross-origin request from {origin[:100]} (the console's origins: "
                    f"{', '.join(sorted(self.server.origin_names()))[:300]})")
        return None

    async def body(self, request: Request, limit: int) -> bytes:
        declared = request.headers.get("content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            raise _Refused(413, f"the body is larger than {limit} bytes")
        chunks, size = [], 0
        try:
            async with asyncio.timeout(self.limits.body_seconds):  # a body sent a byte at a time
                async for chunk in request.stream():
                    size += len(chunk)
                    if size > limit:
                        raise _Refused(413, f"the body is larger than {limit} bytes")
                    chunks.append(chunk)
        except TimeoutError:
            raise _Refused(408, f"the body did not arrive within {self.limits.body_seconds:g} s") from None
        except ClientDisconnect:
            raise _Refused(400, "the client left before its body arrived") from None
        return b"".join(chunks)

    # -------------------------------------------------------------- sign-in
    async def login_page(self, request: Request) -> Response:
        if self.access is None:
            return RedirectResponse("/", 303)
        return Response(_login_html(""), 200, media_type="text/html; charset=utf-8",
                        headers={"Cache-Control": "no-store"})

    async def login(self, request: Request) -> Response:
        access = self.access
        if access is None:
            return RedirectResponse("/", 303)
        why = self.same_origin(request)
        if why:
            return self.refuse(request, 403, why, page=True)
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        try:
            raw = (await self.body(request, MAX_LOGIN_BODY)).decode()
            if ctype == "application/json":
                body = loads_bounded(raw or "{}")
                if not isinstance(body, dict):
                    raise ValueError("a JSON object is expected")
                name, secret = str(body.get("name", "")), str(body.get("password", ""))
            else:
                form = parse_qs(raw)
                name, secret = form.get("name", [""])[0], form.get("password", [""])[0]
        except _Refused as exc:
            return self.refuse(request, exc.status, f"bad sign-in request: {exc.reason}", page=True)
        except (ValueError, UnicodeDecodeError) as exc:
            return self.refuse(request, 400, f"bad sign-in request: {exc}", page=True)
        client = self.client(request)
        try:
            # counted (and maybe refused, 429) before the password is checked; a browser that
            # signed in as the name before (its device cookie) or holds a session of it is known
            attempt = access.begin(name, client, request.cookies.get(DEVICE_COOKIE), request.cookies.get(COOKIE))
        except SignInRefused as exc:  # logged by Access with the name and the address
            request.scope["coex.logged"] = True
            return Response(_login_html(exc.reason), exc.status, media_type="text/html; charset=utf-8",
                            headers={"Cache-Control": "no-store", "Retry-After": str(max(1, math.ceil(exc.wait)))})
        try:
            op = await self.sign_ins.run(access.check, attempt, secret, client=client, klass=attempt.klass)
        except Busy as exc:
            access.cancel(attempt)
            return self.refuse(request, 429, str(exc), page=True)
        except BaseException:
            access.cancel(attempt)
            raise
        try:
            s = access.finish(attempt, op)
        except SignInRefused as exc:  # logged by Access
            request.scope["coex.logged"] = True
            return Response(_login_html(exc.reason), exc.status, media_type="text/html; charset=utf-8",
                            headers={"Cache-Control": "no-store"})
        response = RedirectResponse("/", 303)
        device = access.device_cookie(s)
        if device is not None:  # before the session's cookie (a client reading one sees that)
            response.set_cookie(DEVICE_COOKIE, device, max_age=int(DEVICE_SECONDS), path="/login",
                                secure=request.url.scheme == "https", httponly=True, samesite="strict")
        self.cookie(request, response, s.sid, int(access.session_seconds))
        return response

    async def logout(self, request: Request) -> Response:
        access = self.access
        response = _json(200, {"ok": True})
        if access is not None:
            session = access.session(request.cookies.get(COOKIE), touch=False)
            if session is not None:
                if not hmac.compare_digest(request.headers.get("x-csrf-token", ""), session.csrf):
                    return self.refuse(request, 403, "missing or wrong CSRF token", session)
                access.logout(session.sid)
            self.cookie(request, response, "", 0)
        return response

    # -------------------------------------------------------------- pages
    async def index(self, request: Request) -> Response:
        if self.session(request) is None:
            return RedirectResponse("/login", 303)
        return Response(_asset("index.html"), 200, media_type="text/html; charset=utf-8",
                        headers={"Cache-Control": "no-store"})

    async def static(self, request: Request) -> Response:
        self.signed_in(request)
        name = request.path_params["name"]
        if name not in _STATIC:
            raise _Refused(404, f"no such page {request.url.path}")
        return Response(_asset(name), 200, media_type=_STATIC[name] + "; charset=utf-8",
                        headers={"Cache-Control": "no-store"})

    async def whoami(self, request: Request) -> Response:
        s = self.signed_in(request)
        return _json(200, {"auth": self.access is not None, **describe(s)})

    async def state(self, request: Request) -> Response:
        self.signed_in(request)
        body = await self.snapshot_json(request, self.view(request))
        return Response(body, 200, media_type="application/json", headers={"Cache-Control": "no-store"})

    async def snapshot_json(self, request: Request, hub: Any) -> bytes:
        """The snapshot of ``hub`` as JSON, made once for all who ask while nothing changed
        (the state's section versions and clock; at most :attr:`ConsoleServer.snapshot_seconds`
        old): a hundred pollers cost one snapshot, not a hundred."""
        key = id(hub)

        def current() -> tuple[Any, ...]:
            st = hub.state
            return (tuple(sorted(st.versions.items())), st.now)

        cached = self._snapshots.get(key)
        now = time.monotonic()
        if cached is not None and now - cached[1] < self.server.snapshot_seconds and cached[0] == current():
            return cached[2]
        making = self._making.get(key)
        if making is None:
            def make() -> tuple[Any, bytes]:
                with hub.lock:
                    version = current()
                    snap = hub.snapshot()
                return version, dumps(snap).encode()

            pool = self.server.operator_threads if self.operator(request) else self.server.other_threads
            making = asyncio.get_running_loop().run_in_executor(pool, make)
            self._making[key] = making

            def done(f: asyncio.Future[tuple[Any, bytes]]) -> None:
                self._making.pop(key, None)
                if not f.cancelled() and f.exception() is None:
                    version, body = f.result()
                    self._snapshots[key] = (version, time.monotonic(), body)

            making.add_done_callback(done)
        return (await asyncio.shield(making))[1]

    # -------------------------------------------------------------- pictures
    def _level(self, request: Request) -> int:
        try:
            return int(request.path_params["level"])
        except ValueError:
            raise _Refused(400, f"the map level must be a whole number, not {request.path_params['level'][:20]!r}") from None

    async def picture(self, request: Request, fn: Callable[[], bytes | None]) -> bytes | None:
        """``fn()`` (drawing a picture) in turn (:class:`~.admission.FairQueue`): an operator's
        pictures before viewers', each client's in turn; 429 when there is no room."""
        try:
            return await self.renders.run(fn, client=self.key(request), klass=0 if self.operator(request) else 1)  # type: ignore[no-any-return]
        except Busy as exc:
            raise _Refused(429, str(exc)) from None

    async def map_level(self, request: Request) -> Response:
        self.signed_in(request)
        level, hub = self._level(request), self.view(request)

        def draw() -> bytes | None:
            with hub.lock:
                png, render = hub.state.map_png_job(level)
            return cast("bytes | None", render() if render is not None else png)  # drawn outside the lock

        png = await self.picture(request, draw)
        if png is None:
            raise _Refused(404, f"no map level {level} yet")
        return _png(png)

    async def map_window(self, request: Request) -> Response:
        self.signed_in(request)
        level, hub, q = self._level(request), self.view(request), request.query_params
        try:
            box = [float(q[k]) for k in ("x0", "y0", "x1", "y1")]
            step = int(q.get("step", "1")[:12])
        except KeyError as exc:
            raise _Refused(400, f"a map window needs x0, y0, x1, y1 (metres): {exc.args[0]} is missing") from None
        except ValueError as exc:
            raise _Refused(400, f"a map window's x0, y0, x1, y1 are numbers and step a whole number: "
                                f"{str(exc)[:100]}") from None
        if not all(math.isfinite(v) for v in box):
            raise _Refused(400, "a map window's corners must be finite numbers")
        if not all(abs(v) <= MAX_WINDOW_COORD for v in box) or step > MAX_WINDOW_STEP:
            raise _Refused(400, f"a map window's corners are within +-{MAX_WINDOW_COORD:g} m and its step at "
                                f"most {MAX_WINDOW_STEP}")
        if not (box[2] > box[0] and box[3] > box[1] and step >= 1):
            raise _Refused(400, "a map window needs x1 > x0, y1 > y0 and step >= 1")
        pixels = self.limits.window_pixels

        def draw() -> bytes | None:
            with hub.lock:
                job = hub.state.map_window_job(level, box[0], box[1], box[2], box[3], step=step,
                                               max_pixels=pixels)
            return job() if job is not None else None  # drawn outside the lock

        try:
            png = await self.picture(request, draw)
        except RequestRejected as exc:
            raise _Refused(413, str(exc)) from None
        if png is None:
            raise _Refused(404, f"nothing of map level {level} to draw there")
        return _png(png)

    async def image(self, request: Request) -> Response:
        self.signed_in(request)
        try:
            iid = int(request.path_params["iid"][:20])
        except ValueError:
            raise _Refused(400, "an image id is a whole number") from None
        full = request.query_params.get("full") == "1"
        hub = self.view(request)

        def draw() -> bytes | None:
            with hub.lock:
                return hub.state.image_png(iid, full=full)  # type: ignore[no-any-return]

        png = await self.picture(request, draw)
        if png is None:
            raise _Refused(404, f"no picture of image {iid} yet")
        return _png(png)

    async def crop(self, request: Request) -> Response:
        self.signed_in(request)
        try:
            cid = int(request.path_params["cid"][:20])
        except ValueError:
            raise _Refused(400, "a crop id is a whole number") from None
        hub = self.view(request)

        def draw() -> bytes | None:
            with hub.lock:
                return hub.state.crop_png(cid)  # type: ignore[no-any-return]

        png = await self.picture(request, draw)
        if png is None:
            raise _Refused(404, f"no picture of crop {cid} yet")
        return _png(png)

    # -------------------------------------------------------------- events
    async def events(self, request: Request) -> Response:
        session = self.signed_in(request)
        hub, access, sid = self.view(request), self.access, request.cookies.get(COOKIE)
        # the stream's places are taken here, before anything waits: streams opened together
        # are counted one by one (per session, per address, in all; operators' own places)
        ticket = self.server.lanes.stream(self.operator(request), self.client(request),
                                          request.scope.get("coex.session"))
        if isinstance(ticket, str):
            raise _Refused(429, ticket)
        try:
            def first() -> tuple[str, dict[str, Any], float]:
                with hub.lock:
                    snap = hub.snapshot()
                    seen: dict[str, Any] = hub.seen()
                    # what this page holds of the map: its updates carry only what changed
                    seen["_map"] = hub.state.map_held(snap["map"])
                    return _event("snapshot", snap), seen, hub.state.now

            snap, seen, last_now = await self.thread(request, first)
        except BaseException:
            ticket.release()
            raise

        def update() -> str | None:
            changes = hub.changes_since(seen)
            return _event("update", changes) if changes else None

        async def stream() -> AsyncIterator[str]:
            nonlocal last_now
            role = session.role
            last_clock = time.monotonic()
            yield snap
            while not hub.closed and not self.server.stopping:
                if access is not None:
                    s = access.session(sid)
                    if s is None:  # signed out, expired, removed, new password: the stream ends
                        yield _event("session", {"ended": True})
                        return
                    if s.role != role:
                        role = s.role
                        yield _event("session", describe(s))
                if hub._dirty(seen):
                    await asyncio.sleep(self.server.coalesce)  # a burst goes out as one update
                    text = await self.thread(request, update)
                    if text:
                        yield text
                now = hub.state.now
                if time.monotonic() - last_clock >= 1.0:
                    # the clock also keeps the connection alive (and finds dead browsers)
                    yield _event("clock", {"now": now, "moved": now != last_now})
                    last_now, last_clock = now, time.monotonic()
                await asyncio.sleep(0.1)

        return _Stream(stream(), ticket.release, media_type="text/event-stream",
                       headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    # -------------------------------------------------------------- actions
    async def action(self, request: Request) -> Response:
        session = self.signed_in(request)
        if not session.may_command:
            return self.refuse(request, 403, f"{session.name} is a viewer: viewers cannot command", session)
        access = self.access
        if access is not None and not hmac.compare_digest(request.headers.get("x-csrf-token", ""), session.csrf):
            return self.refuse(request, 403, "missing or wrong CSRF token (reload the page)", session)
        # Only the console's own page may act: a JSON body (other sites' pages cannot send one
        # without a CORS preflight, which this server never grants) from an allowed origin.
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return self.refuse(request, 415, "actions must be application/json", session)
        why = self.same_origin(request)
        if why:
            return self.refuse(request, 403, why, session)
        try:
            body = loads_bounded(await self.body(request, self.limits.body_bytes) or b"{}")
            if not isinstance(body, dict):
                raise ValueError("the body must be a JSON object")
            if "action" not in body:
                raise ValueError("the body needs an 'action'")
            action = str(body["action"])[:64]
            args = body.get("args") or {}
            if not isinstance(args, dict):
                raise ValueError("args must be an object")
        except (ValueError, UnicodeDecodeError) as exc:
            return self.refuse(request, 400, f"bad request: {exc}", session)
        if access is not None:
            wait = access.command_allowed(session)
            if wait:
                return self.refuse(request, 429, f"{session.name}: at most {access.commands_per_minute} "
                                   f"commands a minute; wait {wait:.0f} s", session)
        hub = self.hub
        try:
            # the signed-in name goes with the commands (a console without sign-in has none)
            sent = await self.thread(
                request, (lambda: hub.act(action, args, session.name)) if session.name else (lambda: hub.act(action, args)))
        except CoexError as exc:
            if access is not None:
                access.command_refused(session)  # nothing sent: the budget is not used up
            return self.refuse(request, 400, f"{action}: {exc}", session)
        except Exception as exc:  # never let an operator action kill the console
            if access is not None:
                access.command_refused(session)
            log.exception("console action %s from %s (%s) failed", action, self.client(request),
                          session.name or "local")
            request.scope["coex.logged"] = True
            return _json(500, {"ok": False, "error": f"{action}: the console could not carry it out "
                                                     f"({type(exc).__name__}; logged)"})
        return _json(200, {"ok": True, "sent": [_describe(m) for m in sent]})

    # -------------------------------------------------------------- errors
    async def refused(self, request: Request, exc: Exception) -> Response:
        assert isinstance(exc, _Refused)
        session = None
        if exc.status != 401 and self.access is not None:
            session = self.access.session(request.cookies.get(COOKIE), touch=False)
        return self.refuse(request, exc.status, exc.reason, session)

    async def not_found(self, request: Request, exc: Exception) -> Response:
        return self.refuse(request, 404, f"no such page {request.url.path[:100]}")

    async def not_allowed(self, request: Request, exc: Exception) -> Response:
        return self.refuse(request, 405, f"{request.method} is not allowed on {request.url.path[:100]}")


class _Stream(StreamingResponse):
    """A streaming answer that gives its places back however it ends (the browser left before
    it began, it ended, it failed)."""

    def __init__(self, content: AsyncIterator[str], release: Callable[[], None], **kw: Any) -> None:
        super().__init__(content, **kw)
        self.release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.release()


def origin_of(url: str) -> tuple[str, str, int] | None:
    """An origin's (scheme, host, port) (the default port when none is written), or None for
    one that is not http(s) or has no host (``null``)."""
    try:
        parts = urlsplit(url.strip())
        port = parts.port
    except ValueError:
        return None
    scheme, host = parts.scheme.lower(), (parts.hostname or "").lower()
    if scheme not in ("http", "https") or not host:
        return None
    return scheme, host, port or (443 if scheme == "https" else 80)


def _event(name: str, data: Any) -> str:
    return f"event: {name}\ndata: {dumps(data)}\n\n"


_LOGIN_STYLE = ("body{font:15px system-ui,sans-serif;background:#0d1b26;color:#e6eef3;display:grid;"
                "place-items:center;height:100vh;margin:0}form{background:#152a38;padding:24px 28px;"
                "border-radius:8px;min-width:280px}label{display:block;margin:10px 0 4px}input{width:100%;"
                "padding:6px;box-sizing:border-box}button{margin-top:16px;padding:6px 16px}"
                ".error{color:#ff9b8a}")


def _login_html(error: str) -> str:
    msg = f'<p class="error" role="alert">{html.escape(error)}</p>' if error else ""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>CoEx console: sign in</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>{_LOGIN_STYLE}</style></head>
<body><form method="post" action="/login"><h1>CoEx console</h1>{msg}
<label for="name">Name</label><input id="name" name="name" autocomplete="username" required>
<label for="password">Password or token</label>
<input id="password" name="password" type="password" autocomplete="current-password" required>
<button type="submit" id="signin">Sign in</button></form></body></html>
"""


def _describe(item: Message | Region) -> dict[str, Any]:
    if isinstance(item, Message):
        return jsonfmt.to_json(item)
    # a region the bathymetry receiver will send as MapRoiRequest (and retry)
    return {"type": "MapRoiRequest", "queued": True, "level": item.level, "x0": item.x0,
            "y0": item.y0, "w": item.w, "h": item.h, "fill_gaps": item.fill_gaps}


def _asset(name: str) -> bytes:
    return resources.files(__package__).joinpath("static", name).read_bytes()


def default_hosts(host: str) -> list[str]:
    """The ``Host`` names a console bound to ``host`` answers to by default: the loopback names,
    the address itself, and for a wildcard address (0.0.0.0, ::) this machine's names and
    addresses. Others (a DNS name of the ship's network) are added with ``allowed_hosts``."""
    names = {"localhost", "127.0.0.1", "::1"}
    if host in ("", "0.0.0.0", "::"):
        me = socket.gethostname()
        names |= {me, socket.getfqdn()}
        try:
            names |= {str(a[4][0]) for a in socket.getaddrinfo(me, None)}
        except OSError:
            pass
    else:
        names.add(host)
    return sorted(n.lower() for n in names if n)


class ConsoleServer:
    """The console's web server (Starlette on uvicorn), running in a background thread with its
    own event loop once :meth:`start` is called. The socket is bound at construction (port 0
    picks a free port: :attr:`server_address`)."""

    def __init__(self, hub: ConsoleHub | FleetHub, host: str = "127.0.0.1", port: int = 8080, *,
                 access: Access | None = None, tls: ssl.SSLContext | None = None,
                 allowed_hosts: list[str] | tuple[str, ...] | None = None,
                 limits: Limits | None = None,
                 trusted_proxies: list[str] | tuple[str, ...] | None = None,
                 public_origins: list[str] | tuple[str, ...] | None = None) -> None:
        #: sign-in and roles (None: no sign-in; only for a console on the loopback address)
        self.access = access
        self.tls = tls
        self.hub = hub
        self.limits = lim = limits or Limits()
        origins = []
        for text in public_origins or ():
            o = origin_of(text)
            if o is None or urlsplit(text.strip()).path not in ("", "/"):
                raise CoexError(f"a public origin is scheme://host[:port] (http or https, no path), "
                                f"got {text!r}")
            origins.append(o)
        #: the Host names answered (lower case); anything else is refused with 400
        self.allowed_hosts = sorted({h.lower() for h in (*default_hosts(host), *(allowed_hosts or ()),
                                                         *(o[1] for o in origins))})
        self.stopping = False
        #: Seconds an event stream waits after a change to send a burst as one update.
        self.coalesce = 0.2
        #: Seconds a snapshot made for one ``/api/state`` serves others while nothing changed.
        self.snapshot_seconds = 0.5
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.socket = socket.create_server((host, port), family=family, backlog=1024)
        self.server_address: tuple[Any, ...] = self.socket.getsockname()
        own = ("https" if tls is not None else "http", int(self.server_address[1]))
        #: the origins (scheme, host, port) a state-changing request may come from: the
        #: console's own scheme and port with each allowed host name, and ``public_origins``
        #: (a reverse proxy's, e.g. https://console.ship.example)
        self.public_origins = {(own[0], h, own[1]) for h in self.allowed_hosts} | set(origins)
        # open files: enough for the connections allowed (and the node's own); memory: the
        # worker threads share two malloc arenas (each thread's own arena kept what it freed)
        raise_fd_limit(lim.connections + 256)
        limit_arenas(2)
        trusted = list(trusted_proxies or ())
        #: refusals logged with the client address, a flood of them in one line
        self.say = Said()
        self.doors = Doors(lim, _trusted(trusted), self.say)
        self.lanes = Lanes(lim)
        #: worker threads: operators' work, everyone else's, pictures, password checks, upkeep
        self.operator_threads = ThreadPoolExecutor(2, "coex-console-operator")
        self.other_threads = ThreadPoolExecutor(4, "coex-console-work")
        # operators' pictures and known browsers' sign-ins at the usual priority; everyone else's
        # heavy work at a lower one (it gives way to the loop and to the operator's work)
        self.render_threads = ThreadPoolExecutor(max(1, lim.renders), "coex-console-picture")
        self.other_render_threads = ThreadPoolExecutor(max(1, lim.renders), "coex-console-picture-low",
                                                       initializer=lower_priority)
        sign_ins = access.sign_ins if access else 1
        self.sign_in_threads = ThreadPoolExecutor(sign_ins, "coex-console-sign-in")
        self.other_sign_in_threads = ThreadPoolExecutor(sign_ins, "coex-console-sign-in-low",
                                                        initializer=lower_priority)
        self.housekeeping = ThreadPoolExecutor(1, "coex-console-upkeep")
        self.app_routes = app = _App(self)
        starlette = Starlette(
            routes=app.routes(),
            middleware=[Middleware(TrustedHostMiddleware, allowed_hosts=self.allowed_hosts, www_redirect=False)],
            exception_handlers={_Refused: app.refused, 404: app.not_found, 405: app.not_allowed})
        inner: ASGIApp = _Guard(_Admission(starlette, self), self.say)
        if trusted:
            inner = cast(ASGIApp, ProxyHeadersMiddleware(inner, trusted_hosts=trusted))  # type: ignore[arg-type]
        self.app: ASGIApp = _Peer(inner)
        self.protocol = _protocol(lim, self.doors)
        config = uvicorn.Config(
            self.app, http=self.protocol, ws="none", lifespan="off", log_config=None, access_log=False,
            server_header=False, proxy_headers=False, limit_concurrency=None,
            timeout_keep_alive=lim.keep_alive_seconds, timeout_graceful_shutdown=1,
            h11_max_incomplete_event_size=lim.header_bytes)
        self._uvicorn = _Uvicorn(config, self)
        self._thread: threading.Thread | None = None

    def classify(self, scope: Scope) -> tuple[bool, str | None]:
        """Whether a request is in the operators' lane, and its session's key: an operator's
        session (or, on ``POST /login``, a browser known for an operator: its device cookie);
        without sign-in everyone is the operator (the session key is then the address)."""
        access = self.access
        if access is None:
            return True, None
        cookie = b""
        for name, value in scope.get("headers", ()):
            if name == b"cookie":
                cookie = value
                break
        if not cookie:
            return False, None
        cookies = cookie_parser(cookie.decode("latin-1"))
        s = access.session(cookies.get(COOKIE), touch=False)
        if s is not None:
            return s.may_command, s.sid
        if scope.get("path") == "/login":
            op = access.device(cookies.get(DEVICE_COOKIE))
            if op is not None and op.commands:
                return True, None
        return False, None

    def origin_names(self) -> list[str]:
        out = []
        for scheme, host, port in self.public_origins:
            name = f"[{host}]" if ":" in host else host
            out.append(f"{scheme}://{name}" + ("" if port == (443 if scheme == "https" else 80) else f":{port}"))
        return out

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        name = f"[{host}]" if ":" in str(host) else str(host)
        return f"{'https' if self.tls else 'http'}://{name}:{port}/"

    def _run(self) -> None:
        asyncio.run(self._uvicorn.serve(sockets=[self.socket]))

    def start(self) -> ConsoleServer:
        self._thread = threading.Thread(target=self._run, name="coex-console", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 10.0
        while not self._uvicorn.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.close()
                raise CoexError(f"the console server on {self.url} did not start")
            time.sleep(0.01)
        return self

    def close(self) -> None:
        self.stopping = True
        self.hub.close()
        self._uvicorn.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=5)
        self.socket.close()
        for pool in (self.operator_threads, self.other_threads, self.render_threads, self.other_render_threads,
                     self.sign_in_threads, self.other_sign_in_threads, self.housekeeping):
            pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> ConsoleServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _trusted(proxies: list[str]) -> Callable[[str], bool]:
    """Whether an address is one of the trusted reverse proxies (addresses or networks)."""
    import ipaddress

    nets = []
    for p in proxies:
        try:
            nets.append(ipaddress.ip_network(p, strict=False))
        except ValueError:
            pass

    def trusted(address: str) -> bool:
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(ip in n for n in nets)

    return trusted


def serve(target: Any, host: str = "127.0.0.1", port: int = 8080, *,
          clock: Callable[[], float] | None = None,
          stream_names: dict[int, str] | None = None,
          access: Access | None = None, tls: ssl.SSLContext | None = None,
          allowed_hosts: list[str] | tuple[str, ...] | None = None,
          limits: Limits | None = None,
          trusted_proxies: list[str] | tuple[str, ...] | None = None,
          public_origins: list[str] | tuple[str, ...] | None = None) -> ConsoleServer:
    """Serve the console in a background thread and return the running server (``server.url``,
    ``server.hub``, ``server.close()``). Port 0 picks a free port.

    ``target`` is a :class:`ConsoleHub` (a :class:`~.fleet.FleetHub`: a console of several
    vehicles, each request naming its vehicle), a topside :class:`~coex_core.node.Node` (a hub is made
    with :func:`~coex_apps.console.node.attach`; the loop driving the node must then hold
    ``server.hub.lock`` while stepping it and call ``server.hub.pump(node, now)``), or a
    :class:`ConsoleState` (view only: actions are refused). ``stream_names`` names the
    vehicle's streams in the queue table (with a node). ``allowed_hosts`` adds names the
    console answers to (:func:`default_hosts`); ``limits`` the bounds of :class:`Limits`;
    ``trusted_proxies`` the addresses of reverse proxies whose ``X-Forwarded-For`` (and
    ``X-Forwarded-Proto``) name the client (none by default: the peer address is the client);
    ``public_origins`` the origins the console's page is reached at besides its own address and
    names (a reverse proxy's ``https://console.ship.example``)."""
    hub: ConsoleHub | FleetHub
    if isinstance(target, ConsoleHub | FleetHub):
        hub = target
    elif isinstance(target, ConsoleState):
        def refuse(msg: Message) -> None:
            raise RequestRejected("this console is view-only (no topside node to send with)")
        hub = ConsoleHub(target, refuse, clock or (lambda: target.now))
    elif isinstance(target, Node):
        hub = attach(target, clock, stream_names=stream_names)
    else:
        raise TypeError(f"serve() needs a ConsoleHub, Node or ConsoleState, "
                        f"got {type(target).__name__}")
    return ConsoleServer(hub, host, port, access=access, tls=tls, allowed_hosts=allowed_hosts,
                         limits=limits, trusted_proxies=trusted_proxies, public_origins=public_origins).start()


def tls_context(cert: str, key: str) -> ssl.SSLContext:
    """A server TLS context (TLS 1.2 or newer) from a PEM certificate chain and key."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise CoexError(f"cannot load the TLS certificate {cert} and key {key}: {exc}") from exc
    return ctx

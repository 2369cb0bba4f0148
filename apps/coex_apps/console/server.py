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
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

import h11
import uvicorn
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import RedirectResponse, Response, StreamingResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.types import Message as AsgiMessage
from uvicorn.protocols.http.h11_impl import H11Protocol

from coex import CoexError, Message, Node, RequestRejected
from coex_core import jsonfmt
from coex_plugins.bathymetry import Region

from .access import Access, Session, SignInRefused, describe
from .fleet import FleetHub
from .hub import ConsoleHub
from .node import attach
from .state import MAP_WINDOW_CELLS, ConsoleState

__all__ = ["ConsoleHub", "ConsoleServer", "Limits", "serve", "security_headers"]

log = logging.getLogger(__name__)

_STATIC = {"app.js": "text/javascript", "style.css": "text/css", "index.html": "text/html"}
COOKIE = "coex_session"
#: the largest body a sign-in may have
MAX_LOGIN_BODY = 4096
_LOCAL = Session("", "", "operator", "", float("inf"))  # a console without sign-in


@dataclass(frozen=True)
class Limits:
    """What clients can make the console do (docs/console.md, "The web server")."""

    #: open connections (event streams included); a request beyond gets 503
    connections: int = 64
    #: seconds for a request's headers to arrive (a silent or slow connection is closed)
    header_seconds: float = 10.0
    #: seconds an idle keep-alive connection stays open
    keep_alive_seconds: int = 5
    #: the largest request head (line and headers), bytes
    header_bytes: int = 16 * 1024
    #: the largest action body, bytes
    body_bytes: int = 64 * 1024
    #: seconds for a request's body to arrive once its head has (408 beyond)
    body_seconds: float = 10.0
    #: pictures (map levels, map windows, images) drawn at once; more wait
    renders: int = 2
    #: pictures waiting to be drawn; one more is refused (429)
    render_queue: int = 32
    #: the largest map window, pixels (about 86 bytes of memory each while drawn)
    window_pixels: int = MAP_WINDOW_CELLS
    #: event streams open at once (429 beyond)
    streams: int = 32


class _Refused(Exception):
    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


# ------------------------------------------------------------------ HTTP/1.1 with a header timeout
def _protocol(limits: Limits) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a deadline for each request's headers: uvicorn times out an
    idle keep-alive connection, but not one that never finishes its request head."""

    class Protocol(H11Protocol):
        _head_timer: asyncio.TimerHandle | None = None

        def _arm(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
            self._head_timer = self.loop.call_later(limits.header_seconds, self._head_timeout)

        def _head_timeout(self) -> None:
            self._head_timer = None
            waiting = self.cycle is None or self.cycle.response_complete
            if waiting and not self.transport.is_closing():
                log.info("console: closed a connection from %s that sent no request head in %.0f s",
                         (self.client or ("?",))[0], limits.header_seconds)
                try:
                    self.conn.send(h11.ConnectionClosed())
                except h11.LocalProtocolError:
                    pass
                self.transport.close()

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm()

        def connection_lost(self, exc: Exception | None) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None
            super().connection_lost(exc)

    return Protocol


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


class _Guard:
    """Outermost middleware: the security headers on every answer, and a log line for a
    refusal nobody logged yet (a wrong Host, a request the concurrency limit turned away)."""

    def __init__(self, app: ASGIApp, tls: bool) -> None:
        self.app = app
        self.headers = security_headers(tls)
        self.login_headers = security_headers(tls, _sha256(_LOGIN_STYLE))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = str(scope.get("path", ""))
        if path.startswith("//"):  # ``url + "/api/state"`` with a url ending in /: as http.server did
            scope = {**scope, "path": "/" + path.lstrip("/"), "raw_path": b"/" + scope.get("raw_path", b"").lstrip(b"/")}
        extra = self.login_headers if scope.get("path") == "/login" else self.headers

        async def send_with_headers(message: AsgiMessage) -> None:
            if message["type"] == "http.response.start":
                status = int(message["status"])
                names = {k.lower() for k, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []),
                                      *((k, v) for k, v in extra if k not in names)]
                if status >= 400 and not scope.get("coex.logged"):
                    host = dict(scope.get("headers", [])).get(b"host", b"").decode("latin-1")
                    log.warning("console refused %s %s from %s (Host %r): HTTP %d", scope.get("method"),
                                scope.get("path"), (scope.get("client") or ("?",))[0], host[:100], status)
            await send(message)

        await self.app(scope, receive, send_with_headers)


def _jsonable(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    return str(obj)


def dumps(obj: Any) -> str:
    return json.dumps(obj, default=_jsonable, allow_nan=False, separators=(",", ":"))


def _json(code: int, obj: Any, **kw: Any) -> Response:
    return Response(dumps(obj), code, media_type="application/json",
                    headers={"Cache-Control": "no-store"}, **kw)


def _png(body: bytes) -> Response:
    return Response(body, 200, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


class _Gate:
    """At most ``running`` jobs at once in worker threads and ``waiting`` more queued; one more
    is refused (429)."""

    def __init__(self, running: int, waiting: int, what: str) -> None:
        self.running, self.limit, self.what = max(1, running), max(1, running) + max(0, waiting), what
        self.sem: asyncio.Semaphore | None = None
        self.busy = 0

    async def run(self, fn: Callable[..., Any], *args: Any) -> Any:
        if self.sem is None:
            self.sem = asyncio.Semaphore(self.running)
        if self.busy >= self.limit:
            raise _Refused(429, f"the console is busy drawing {self.busy} {self.what}: try again")
        self.busy += 1
        try:
            async with self.sem:
                return await run_in_threadpool(fn, *args)
        finally:
            self.busy -= 1


# ------------------------------------------------------------------ the application
class _App:
    """The routes of one console server."""

    def __init__(self, server: ConsoleServer) -> None:
        self.server = server
        self.hub = server.hub
        self.access = server.access
        self.limits = server.limits
        self.renders = _Gate(server.limits.renders, server.limits.render_queue, "pictures")
        self.streams = 0

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
        log.warning("console refused %s %s from %s (%s): %s", request.method, request.url.path, client,
                    who, reason)
        if page:
            return Response(_login_html(reason), status, media_type="text/html; charset=utf-8",
                            headers={"Cache-Control": "no-store"})
        return _json(status, {"ok": False, "error": reason})

    def client(self, request: Request) -> str:
        return request.client.host if request.client else "?"

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

    def cookie(self, response: Response, sid: str, max_age: int) -> None:
        response.set_cookie(COOKIE, sid, max_age=max_age, path="/", secure=self.server.tls is not None,
                            httponly=True, samesite="strict")

    def same_origin(self, request: Request) -> str | None:
        """Why a state-changing request is not from the console's own page (None: it is). The
        ``Origin`` must name an allowed host (never compared with ``Host``, which a rebinding
        page controls too) and a browser's ``Sec-Fetch-Site`` must not say cross-site."""
        if request.headers.get("sec-fetch-site", "same-origin") not in ("same-origin", "none"):
            return f"cross-site request ({request.headers['sec-fetch-site']})"
        origin = request.headers.get("origin")
        if origin is None:
            return None
        parts = urlsplit(origin)
        if (parts.hostname or "").lower() not in self.server.allowed_hosts:
            return f"cross-origin request from {origin[:100]}"
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
                body = json.loads(raw or "{}")
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
        try:
            s = await run_in_threadpool(access.login, name, secret, self.client(request))
        except SignInRefused as exc:  # logged by Access with the name and the address
            request.scope["coex.logged"] = True
            return Response(_login_html(exc.reason), exc.status, media_type="text/html; charset=utf-8",
                            headers={"Cache-Control": "no-store"})
        response = RedirectResponse("/", 303)
        self.cookie(response, s.sid, int(access.session_seconds))
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
            self.cookie(response, "", 0)
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
        return _json(200, await run_in_threadpool(self.view(request).snapshot))

    # -------------------------------------------------------------- pictures
    def _level(self, request: Request) -> int:
        try:
            return int(request.path_params["level"])
        except ValueError:
            raise _Refused(400, f"the map level must be a whole number, not {request.path_params['level']!r}") from None

    async def map_level(self, request: Request) -> Response:
        self.signed_in(request)
        level, hub = self._level(request), self.view(request)

        def draw() -> bytes | None:
            with hub.lock:
                png, render = hub.state.map_png_job(level)
            return render() if render is not None else png  # drawn outside the lock

        png = await self.renders.run(draw)
        if png is None:
            raise _Refused(404, f"no map level {level} yet")
        return _png(png)

    async def map_window(self, request: Request) -> Response:
        self.signed_in(request)
        level, hub, q = self._level(request), self.view(request), request.query_params
        try:
            box = [float(q[k]) for k in ("x0", "y0", "x1", "y1")]
            step = int(q.get("step", "1"))
        except KeyError as exc:
            raise _Refused(400, f"a map window needs x0, y0, x1, y1 (metres): {exc.args[0]} is missing") from None
        except ValueError as exc:
            raise _Refused(400, f"a map window's x0, y0, x1, y1 are numbers and step a whole number: {exc}") from None
        if not all(math.isfinite(v) for v in box):
            raise _Refused(400, "a map window's corners must be finite numbers")
        if not (box[2] > box[0] and box[3] > box[1] and step >= 1):
            raise _Refused(400, "a map window needs x1 > x0, y1 > y0 and step >= 1")
        pixels = self.limits.window_pixels

        def draw() -> bytes | None:
            with hub.lock:
                job = hub.state.map_window_job(level, box[0], box[1], box[2], box[3], step=step,
                                               max_pixels=pixels)
            return job() if job is not None else None  # drawn outside the lock

        try:
            png = await self.renders.run(draw)
        except RequestRejected as exc:
            raise _Refused(413, str(exc)) from None
        if png is None:
            raise _Refused(404, f"nothing of map level {level} to draw there")
        return _png(png)

    async def image(self, request: Request) -> Response:
        self.signed_in(request)
        try:
            iid = int(request.path_params["iid"])
        except ValueError:
            raise _Refused(400, "an image id is a whole number") from None
        full = request.query_params.get("full") == "1"
        hub = self.view(request)

        def draw() -> bytes | None:
            with hub.lock:
                return hub.state.image_png(iid, full=full)

        png = await self.renders.run(draw)
        if png is None:
            raise _Refused(404, f"no picture of image {iid} yet")
        return _png(png)

    async def crop(self, request: Request) -> Response:
        self.signed_in(request)
        try:
            cid = int(request.path_params["cid"])
        except ValueError:
            raise _Refused(400, "a crop id is a whole number") from None
        hub = self.view(request)

        def draw() -> bytes | None:
            with hub.lock:
                return hub.state.crop_png(cid)

        png = await self.renders.run(draw)
        if png is None:
            raise _Refused(404, f"no picture of crop {cid} yet")
        return _png(png)

    # -------------------------------------------------------------- events
    async def events(self, request: Request) -> Response:
        session = self.signed_in(request)
        if self.streams >= self.limits.streams:
            raise _Refused(429, f"{self.streams} event streams are open already (at most {self.limits.streams})")
        hub, access, sid = self.view(request), self.access, request.cookies.get(COOKIE)

        def first() -> tuple[dict[str, Any], dict[str, Any], float]:
            with hub.lock:
                snap = hub.snapshot()
                seen: dict[str, Any] = hub.seen()
                # what this page holds of the map: its updates carry only what changed
                seen["_map"] = hub.state.map_held(snap["map"])
                return snap, seen, hub.state.now

        snap, seen, last_now = await run_in_threadpool(first)

        async def stream() -> AsyncIterator[str]:
            nonlocal last_now
            role = session.role
            last_clock = time.monotonic()
            self.streams += 1  # counted here: a stream whose browser left before it began never runs
            try:
                yield _event("snapshot", snap)
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
                        changes = await run_in_threadpool(hub.changes_since, seen)
                        if changes:
                            yield _event("update", changes)
                    now = hub.state.now
                    if time.monotonic() - last_clock >= 1.0:
                        # the clock also keeps the connection alive (and finds dead browsers)
                        yield _event("clock", {"now": now, "moved": now != last_now})
                        last_now, last_clock = now, time.monotonic()
                    await asyncio.sleep(0.1)
            finally:
                self.streams -= 1

        return StreamingResponse(stream(), media_type="text/event-stream",
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
            body = json.loads(await self.body(request, self.limits.body_bytes) or b"{}")
            if not isinstance(body, dict):
                raise ValueError("the body must be a JSON object")
            if "action" not in body:
                raise ValueError("the body needs an 'action'")
            action = str(body["action"])
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
            sent = await run_in_threadpool(
                (lambda: hub.act(action, args, session.name)) if session.name else (lambda: hub.act(action, args)))
        except CoexError as exc:
            return self.refuse(request, 400, f"{action}: {exc}", session)
        except Exception as exc:  # never let an operator action kill the console
            log.exception("action %s failed", action)
            request.scope["coex.logged"] = True
            return _json(500, {"ok": False, "error": f"{type(exc).__name__}: {exc}"})
        return _json(200, {"ok": True, "sent": [_describe(m) for m in sent]})

    # -------------------------------------------------------------- errors
    async def refused(self, request: Request, exc: Exception) -> Response:
        assert isinstance(exc, _Refused)
        session = None
        if exc.status != 401 and self.access is not None:
            session = self.access.session(request.cookies.get(COOKIE), touch=False)
        return self.refuse(request, exc.status, exc.reason, session)

    async def not_found(self, request: Request, exc: Exception) -> Response:
        return self.refuse(request, 404, f"no such page {request.url.path}")

    async def not_allowed(self, request: Request, exc: Exception) -> Response:
        return self.refuse(request, 405, f"{request.method} is not allowed on {request.url.path}")


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
                 trusted_proxies: list[str] | tuple[str, ...] | None = None) -> None:
        #: sign-in and roles (None: no sign-in; only for a console on the loopback address)
        self.access = access
        self.tls = tls
        self.hub = hub
        self.limits = limits or Limits()
        #: the Host names answered (lower case); anything else is refused with 400
        self.allowed_hosts = sorted({h.lower() for h in (*default_hosts(host), *(allowed_hosts or ()))})
        self.stopping = False
        #: Seconds an event stream waits after a change to send a burst as one update.
        self.coalesce = 0.2
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.socket = socket.create_server((host, port), family=family, backlog=128)
        self.server_address: tuple[Any, ...] = self.socket.getsockname()
        app = _App(self)
        self.app = Starlette(
            routes=app.routes(),
            middleware=[Middleware(_Guard, tls=tls is not None),
                        Middleware(TrustedHostMiddleware, allowed_hosts=self.allowed_hosts, www_redirect=False)],
            exception_handlers={_Refused: app.refused, 404: app.not_found, 405: app.not_allowed})
        lim = self.limits
        config = uvicorn.Config(
            self.app, http=_protocol(lim), ws="none", lifespan="off", log_config=None, access_log=False,
            server_header=False, proxy_headers=bool(trusted_proxies),
            forwarded_allow_ips=list(trusted_proxies) if trusted_proxies else None,
            limit_concurrency=lim.connections, timeout_keep_alive=lim.keep_alive_seconds,
            timeout_graceful_shutdown=1, h11_max_incomplete_event_size=lim.header_bytes,
            ssl_context_factory=(lambda cfg, default: tls) if tls is not None else None)
        self._uvicorn = uvicorn.Server(config)
        self._thread: threading.Thread | None = None

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

    def __enter__(self) -> ConsoleServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve(target: Any, host: str = "127.0.0.1", port: int = 8080, *,
          clock: Callable[[], float] | None = None,
          stream_names: dict[int, str] | None = None,
          access: Access | None = None, tls: ssl.SSLContext | None = None,
          allowed_hosts: list[str] | tuple[str, ...] | None = None,
          limits: Limits | None = None,
          trusted_proxies: list[str] | tuple[str, ...] | None = None) -> ConsoleServer:
    """Serve the console in a background thread and return the running server (``server.url``,
    ``server.hub``, ``server.close()``). Port 0 picks a free port.

    ``target`` is a :class:`ConsoleHub` (a :class:`~.fleet.FleetHub`: a console of several
    vehicles, each request naming its vehicle), a topside :class:`~coex_core.node.Node` (a hub is made
    with :func:`~coex_apps.console.node.attach`; the loop driving the node must then hold
    ``server.hub.lock`` while stepping it and call ``server.hub.pump(node, now)``), or a
    :class:`ConsoleState` (view only: actions are refused). ``stream_names`` names the
    vehicle's streams in the queue table (with a node). ``allowed_hosts`` adds names the
    console answers to (:func:`default_hosts`); ``limits`` the bounds of :class:`Limits`;
    ``trusted_proxies`` the addresses of reverse proxies whose ``X-Forwarded-For`` names the
    client (none by default: the peer address is the client)."""
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
                         limits=limits, trusted_proxies=trusted_proxies).start()


def tls_context(cert: str, key: str) -> ssl.SSLContext:
    """A server TLS context (TLS 1.2 or newer) from a PEM certificate chain and key."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise CoexError(f"cannot load the TLS certificate {cert} and key {key}: {exc}") from exc
    return ctx

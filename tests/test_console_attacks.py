"""The console as an attacker on the same network would try it (loopback only, each test a few
seconds): an idle TLS socket, a silent connection, revoked operators, a rebinding Host, framing,
oversized and parallel pictures, parallel password guessing, request smuggling, bad arguments.
Each of these passed against the old ``http.server`` console (issue 40) and must fail now."""

from __future__ import annotations

import http.client
import json
import shutil
import socket
import ssl
import subprocess
import sys
import time
import urllib.parse
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from coex_apps.console import ConsoleHub, ConsoleState, serve
from coex_apps.console.access import Access, OperatorsFile
from coex_apps.console.server import Limits
from coex_apps.console.testing import feed_sample
from coex_core import messages as m
from coex_core.channel.schedule import Schedule

from .test_console_access import _certificate

T0 = 36000.0
PASSWORDS = {"ana": "correct horse battery", "vic": "viewer password 1", "bob": "another operator 2"}


@pytest.fixture(scope="module")
def hashed_operators(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The operators file, its passwords hashed once for the module (scrypt takes tens of
    milliseconds a password); each test gets a copy of its own (``operators``)."""
    path = tmp_path_factory.mktemp("operators") / "operators.json"
    f = OperatorsFile(path)
    f.add("ana", "operator", PASSWORDS["ana"])
    f.add("bob", "operator", PASSWORDS["bob"])
    f.add("vic", "viewer", PASSWORDS["vic"])
    f.save()
    return path


@pytest.fixture
def operators(tmp_path: Path, hashed_operators: Path) -> Path:
    path = tmp_path / "operators.json"
    shutil.copy(hashed_operators, path)  # its private mode too
    return path


class Console:
    """A console fed with the sample dive; ``sent`` holds what it commanded."""

    def __init__(self, operators: Path | None = None, tls: ssl.SSLContext | None = None,
                 limits: Limits | None = None, **access: Any) -> None:
        self.state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
        feed_sample(self.state, t0=T0)
        self.sent: list[m.Message] = []
        self.hub = ConsoleHub(self.state, self.sent.append, lambda: T0)
        self.access = Access(OperatorsFile(operators), **access) if operators else None
        self.server = serve(self.hub, "127.0.0.1", 0, access=self.access, tls=tls, limits=limits)
        self.port = int(self.server.server_address[1])
        self.tls = tls

    def connection(self, source: str = "127.0.0.1", timeout: float = 10.0) -> http.client.HTTPConnection:
        if self.tls is not None:
            return http.client.HTTPSConnection("127.0.0.1", self.port, timeout=timeout, source_address=(source, 0),
                                               context=ssl._create_unverified_context())
        return http.client.HTTPConnection("127.0.0.1", self.port, timeout=timeout, source_address=(source, 0))

    def request(self, method: str, path: str, body: Any = None, headers: dict[str, str] | None = None,
                form: dict[str, str] | None = None, source: str = "127.0.0.1") -> tuple[int, dict[str, str], bytes]:
        conn = self.connection(source)
        h = dict(headers or {})
        data = None
        if form is not None:
            data = urllib.parse.urlencode(form).encode()
            h.setdefault("Content-Type", "application/x-www-form-urlencoded")
        elif body is not None:
            data = json.dumps(body).encode()
            h.setdefault("Content-Type", "application/json")
        try:
            conn.request(method, path, body=data, headers=h)
            r = conn.getresponse()
            return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
        finally:
            conn.close()

    def login(self, name: str, password: str | None = None, source: str = "127.0.0.1") -> tuple[str, str]:
        code, h, body = self.request("POST", "/login", form={"name": name, "password": password or PASSWORDS[name]},
                                     source=source)
        assert code == 303, (code, body)
        cookie = h["set-cookie"].split(";")[0]
        code, _, body = self.request("GET", "/api/whoami", headers={"Cookie": cookie})
        assert code == 200
        return cookie, json.loads(body)["csrf"]

    def act(self, cookie: str | None = None, csrf: str | None = None, action: str = "queue_config",
            args: dict[str, Any] | None = None, headers: dict[str, str] | None = None) -> tuple[int, dict[str, Any]]:
        h = dict(headers or {})
        if cookie:
            h["Cookie"] = cookie
        if csrf:
            h["X-CSRF-Token"] = csrf
        code, _, body = self.request("POST", "/api/action", headers=h, body={
            "action": action, "args": {"stream": 3, "priority": 50} if args is None else args})
        return code, json.loads(body) if body.startswith(b"{") else {"error": body.decode()}

    def stream(self, cookie: str | None = None) -> Stream:
        return Stream(self, cookie)

    def close(self) -> None:
        self.server.close()


class Stream:
    """An open ``/api/events`` stream, read event by event."""

    def __init__(self, console: Console, cookie: str | None) -> None:
        self.conn = console.connection(timeout=5.0)
        self.conn.request("GET", "/api/events", headers={"Cookie": cookie} if cookie else {})
        self.response = self.conn.getresponse()
        assert self.response.status == 200, self.response.status

    def next(self) -> tuple[str, Any] | None:
        """The next event (name, data), or None when the server ended the stream."""
        name, data = "", None
        while True:
            line = self.response.readline()  # the chunked body, decoded: b"" at its end
            if not line:
                return None
            text = line.decode().rstrip("\r\n")
            if text.startswith("event: "):
                name = text[7:]
            elif text.startswith("data: "):
                data = json.loads(text[6:])
            elif text == "" and name:
                return name, data

    def until(self, want: str, seconds: float = 5.0) -> tuple[str, Any] | None:
        """Events up to the first named ``want`` (or the end of the stream)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            ev = self.next()
            if ev is None or ev[0] == want:
                return ev
        raise AssertionError(f"no {want} event in {seconds} s")

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
def console(operators: Path) -> Iterator[Console]:
    c = Console(operators)
    try:
        yield c
    finally:
        c.close()


# ------------------------------------------------------------------ connections
def test_an_idle_tls_connection_does_not_block_anyone(operators: Path, tmp_path: Path) -> None:
    """The old server ran every TLS handshake inside accept(): one silent TCP connection froze
    the HTTPS console for everyone."""
    from coex_apps.console.server import tls_context

    c = Console(operators, tls=tls_context(*_certificate(tmp_path)))
    idle = [socket.create_connection(("127.0.0.1", c.port)) for _ in range(3)]  # no ClientHello
    try:
        t = time.monotonic()
        code, h, body = c.request("GET", "/login")
        assert code == 200 and b'name="password"' in body
        assert time.monotonic() - t < 5.0
        assert h["strict-transport-security"].startswith("max-age=")  # HSTS under TLS
    finally:
        for s in idle:
            s.close()
        c.close()


def test_a_connection_that_never_finishes_its_request_is_closed() -> None:
    """A slow or silent client cannot hold a connection (and a slot of the cap) for ever."""
    c = Console(limits=Limits(header_seconds=0.5))
    try:
        s = socket.create_connection(("127.0.0.1", c.port), timeout=5.0)
        s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # the head never ends
        t = time.monotonic()
        assert s.recv(1024) == b""  # closed by the server
        assert time.monotonic() - t < 3.0
        s.close()
        assert c.request("GET", "/api/state")[0] == 200
    finally:
        c.close()


def test_a_body_that_never_arrives_is_refused_in_time() -> None:
    """A slow client announcing a body and sending a byte now and then held a server thread
    for ever."""
    c = Console(limits=Limits(body_seconds=0.5))
    try:
        s = socket.create_connection(("127.0.0.1", c.port), timeout=5.0)
        s.sendall(b"POST /api/action HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                  b"Content-Length: 100\r\n\r\n{\"action\"")
        t = time.monotonic()
        answer = b""
        while b"did not arrive" not in answer and time.monotonic() - t < 5.0:
            got = s.recv(4096)
            if not got:
                break
            answer += got
        assert answer.startswith(b"HTTP/1.1 408") and b"did not arrive" in answer, answer
        assert time.monotonic() - t < 3.0
        s.close()
        assert c.sent == []
    finally:
        c.close()


def test_idle_connections_beyond_the_cap_make_room() -> None:
    """Idle connections at the cap once got everyone 503 (uvicorn's limit was shared by all):
    now the oldest idle one makes room (busy ones: tests/test_console_admission.py)."""
    c = Console(limits=Limits(connections=4, header_seconds=5.0))
    held = [socket.create_connection(("127.0.0.1", c.port)) for _ in range(4)]
    try:
        time.sleep(0.5)
        code, _, body = c.request("GET", "/api/state")
        assert code == 200, (code, body[:200])
        assert c.server.doors.count <= 4
    finally:
        for s in held:
            s.close()
        c.close()


def _raw(port: int, data: bytes, seconds: float = 1.5, source: str = "127.0.0.1") -> bytes:
    """Send ``data`` on one connection and read what comes back for ``seconds``."""
    s = socket.create_connection(("127.0.0.1", port), timeout=seconds, source_address=(source, 0))
    s.sendall(data)
    out = b""
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            got = s.recv(65536)
            if not got:
                break
            out += got
    except TimeoutError:
        pass
    finally:
        s.close()
    return out


def _after_first_answer(out: bytes) -> bytes:
    """What came back after the first complete answer (its head and Content-Length body)."""
    head, sep, rest = out.partition(b"\r\n\r\n")
    assert sep and head.startswith(b"HTTP/1.1 "), out
    length = [int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")[1:]
              if line.lower().startswith(b"content-length:")]
    assert length, head
    return rest[length[0]:]


@pytest.mark.parametrize("framing", ["content-length", "chunked"])
def test_a_request_hidden_in_a_body_is_never_answered(framing: str) -> None:
    """Request smuggling: the old server left an unread body in the stream and parsed it as a
    second request (and ignored Transfer-Encoding)."""
    c = Console()
    try:
        hidden = b"GET /api/smuggled HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
        if framing == "content-length":
            head = f"POST /nowhere HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: {len(hidden)}\r\n\r\n"
            body = hidden
        else:  # a chunked body the old server did not read at all
            head = "POST /logout HTTP/1.1\r\nHost: 127.0.0.1\r\nTransfer-Encoding: chunked\r\n\r\n"
            body = f"{len(hidden):x}\r\n".encode() + hidden + b"\r\n0\r\n\r\n"
        out = _raw(c.port, head.encode() + body)
        assert _after_first_answer(out) == b"", out  # one answer, nothing else
        assert b"smuggled" not in out
        # both framings at once (a proxy reading one and the server the other): refused, one
        # answer and the connection closed (test_console_admission.py)
        hidden_head = (b"POST /logout HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 4\r\n"
                       b"Transfer-Encoding: chunked\r\n\r\n")
        chunked = f"{len(hidden):x}\r\n".encode() + hidden + b"\r\n0\r\n\r\n"
        out = _raw(c.port, hidden_head + chunked)
        assert _after_first_answer(out) == b"" and b"smuggled" not in out, out
    finally:
        c.close()


# ------------------------------------------------------------------ the browser's boundary
def test_a_rebinding_host_is_refused_and_cannot_command() -> None:
    """DNS rebinding: a page of evil.example whose name now points at 127.0.0.1 talks to the
    console as evil.example (Host and Origin both the attacker's)."""
    c = Console()
    try:
        evil = {"Host": f"evil.example:{c.port}"}
        assert c.request("GET", "/api/state", headers=evil)[0] == 400
        assert c.request("GET", "/", headers=evil)[0] == 400
        code, _ = c.act(headers={**evil, "Origin": f"http://evil.example:{c.port}"})
        assert code == 400
        # the right Host with another site's Origin (or a browser saying cross-site) is refused too
        assert c.act(headers={"Origin": f"http://evil.example:{c.port}"})[0] == 403
        assert c.act(headers={"Sec-Fetch-Site": "cross-site"})[0] == 403
        assert c.sent == []
        assert c.request("GET", "/api/state", headers={"Host": f"localhost:{c.port}"})[0] == 200
        assert c.act(headers={"Origin": f"http://127.0.0.1:{c.port}", "Sec-Fetch-Site": "same-origin"})[0] == 200
    finally:
        c.close()


def test_every_answer_forbids_framing_and_sniffing_and_names_no_server() -> None:
    c = Console()
    try:
        for path in ("/", "/api/state", "/static/app.js", "/nowhere"):
            _, h, _ = c.request("GET", path)
            assert "frame-ancestors 'none'" in h["content-security-policy"], path
            assert h["x-frame-options"] == "DENY"
            assert h["x-content-type-options"] == "nosniff"
            assert h["referrer-policy"] == "same-origin"
            assert "server" not in h, h["server"]
            assert "strict-transport-security" not in h  # plain HTTP: HSTS would be ignored
        assert c.request("GET", "/nowhere")[0] == 404
        assert c.request("GET", "//api/state")[0] == 200  # a base URL ending in / plus "/api/state"
    finally:
        c.close()


# ------------------------------------------------------------------ the operators file, live
def test_removing_an_operator_ends_their_session_and_stream_at_once(console: Console, operators: Path) -> None:
    cookie, csrf = console.login("ana")
    stream = console.stream(cookie)
    try:
        assert stream.next()[0] == "snapshot"  # type: ignore[index]
        f = OperatorsFile(operators)
        f.remove("ana")
        f.save()
        t = time.monotonic()
        assert stream.until("session") == ("session", {"ended": True})
        assert time.monotonic() - t < 2.0
        assert console.act(cookie, csrf)[0] == 401
        code, _, _ = console.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]})
        assert code == 401
        assert console.sent == []
    finally:
        stream.close()


def test_a_demoted_operator_cannot_command_and_their_page_is_told(console: Console, operators: Path) -> None:
    cookie, csrf = console.login("ana")
    assert console.act(cookie, csrf)[0] == 200
    stream = console.stream(cookie)
    try:
        r = subprocess.run([sys.executable, "-m", "coex_core.cli", "operators", "--file", str(operators),
                            "role", "ana", "--role", "viewer"], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "ana is now viewer" in r.stdout, r.stderr
        ev = stream.until("session")
        assert ev is not None and ev[1]["role"] == "viewer" and ev[1]["may_command"] is False
        code, reply = console.act(cookie, csrf)
        assert code == 403 and "viewer" in reply["error"]
        assert len(console.sent) == 1
        assert console.request("GET", "/api/state", headers={"Cookie": cookie})[0] == 200  # still watches
    finally:
        stream.close()


def test_a_new_password_ends_the_old_sessions_and_logout_ends_the_stream(console: Console, operators: Path) -> None:
    cookie, csrf = console.login("ana")
    other, other_csrf = console.login("bob")
    stream = console.stream(other)
    try:
        f = OperatorsFile(operators)
        f.add("ana", "operator", "a brand new passphrase")
        f.save()
        time.sleep(0.3)
        assert console.act(cookie, csrf)[0] == 401
        assert console.login("ana", "a brand new passphrase")
        # bob signs out in another tab: his open stream ends too
        assert stream.next()[0] == "snapshot"  # type: ignore[index]
        code, _, _ = console.request("POST", "/logout", headers={"Cookie": other, "X-CSRF-Token": other_csrf})
        assert code == 200
        assert stream.until("session") == ("session", {"ended": True})
        assert stream.next() is None
    finally:
        stream.close()


def test_an_idle_session_ends(operators: Path) -> None:
    now = [1000.0]
    access = Access(OperatorsFile(operators), idle_minutes=10, clock=lambda: now[0])
    s = access.login("ana", PASSWORDS["ana"], "127.0.0.1")
    now[0] += 9 * 60
    assert access.session(s.sid) is s  # used: the idle time starts again
    now[0] += 9 * 60
    assert access.session(s.sid) is s
    now[0] += 10 * 60
    assert access.session(s.sid) is None


def test_the_command_rate_is_per_operator_not_per_session(operators: Path) -> None:
    c = Console(operators, commands_per_minute=3)
    try:
        first, second = c.login("ana"), c.login("ana")
        codes = [c.act(*first)[0], c.act(*first)[0], c.act(*second)[0], c.act(*second)[0]]
        assert codes == [200, 200, 200, 429]
        assert c.act(*c.login("bob"))[0] == 200  # another operator has their own
    finally:
        c.close()


# ------------------------------------------------------------------ sign-in
def test_parallel_guesses_cannot_pass_the_limit_nor_lock_the_operator_out(operators: Path) -> None:
    console = Console(operators, backoff=30.0)
    try:
        _guesses(console)
    finally:
        console.close()


def _guesses(console: Console) -> None:
    def guess(k: int) -> int:
        return console.request("POST", "/login", form={"name": "ana", "password": f"wrong guess {k}"})[0]

    with ThreadPoolExecutor(20) as pool:
        codes = list(pool.map(guess, range(20)))
    assert codes.count(401) <= console.access.max_failures, codes  # type: ignore[union-attr]
    assert set(codes) <= {401, 429} and codes.count(429) >= 20 - console.access.max_failures  # type: ignore[union-attr]
    # from here the right password must wait too ...
    code, _, body = console.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]})
    assert code == 429 and b"try again in" in body
    # ... but ana at her own computer (another address) is not locked out by a stranger
    assert console.login("ana", source="127.0.0.2")


# ------------------------------------------------------------------ bounded work
def test_an_oversized_map_window_is_refused_with_the_reason(console: Console) -> None:
    cookie, _ = console.login("vic")
    t = time.monotonic()
    code, _, body = console.request("GET", "/map/0/window.png?x0=0&y0=0&x1=1e9&y1=1e9&step=1",
                                    headers={"Cookie": cookie})
    assert code == 413 and b"larger than" in body, (code, body)
    for bad, why in (("x0=nan&y0=0&x1=1&y1=1", b"finite"), ("x0=0&y0=0&x1=1", b"y1 is missing"),
                     ("x0=0&y0=0&x1=1&y1=1&step=0", b"step >= 1"), ("x0=a&y0=0&x1=1&y1=1", b"numbers")):
        code, _, body = console.request("GET", f"/map/0/window.png?{bad}", headers={"Cookie": cookie})
        assert code == 400 and why in body, (bad, code, body)
    assert time.monotonic() - t < 5.0


def test_pictures_are_drawn_a_few_at_a_time_and_the_rest_refused() -> None:
    # without sign-in everyone is the operator: the operators' queue is the one that fills
    c = Console(limits=Limits(renders=1, render_queue=1, operator_render_queue=1))
    real = c.state.image_png

    def slow(iid: int, full: bool = False) -> bytes | None:
        time.sleep(2.0)
        return real(iid, full)

    c.state.image_png = slow  # type: ignore[method-assign]
    iid = next(iter(c.state.images))
    try:
        with ThreadPoolExecutor(6) as pool:
            codes = list(pool.map(lambda _: c.request("GET", f"/image/{iid}.png?full=1")[0], range(6)))
        assert codes.count(200) >= 1 and codes.count(429) >= 3, codes
        assert set(codes) <= {200, 429}
    finally:
        c.close()


# ------------------------------------------------------------------ the API's arguments
def test_every_bad_argument_is_answered_400_with_the_reason() -> None:
    c = Console()
    try:
        for body, status, why in (
                ({"action": "queue_config", "args": {"stream": 3, "priorty": 5}}, 400, "no argument 'priorty'"),
                ({"action": "queue_config", "args": {}}, 400, "needs stream"),
                ({"action": "link_control", "args": {"link": 0, "enabled": True, "mute": 1, "x": 2}}, 400,
                 "no argument 'x'"),
                ({"action": "survey", "args": {"kind": "waypoints", "points": [[1, 2], [3, 4]]}}, 400,
                 "survey receiver"),
                ({"action": "nothing"}, 400, "unknown action 'nothing'"),
                ({"args": {}}, 400, "needs an 'action'"),
                (["queue_config"], 400, "JSON object")):
            code, _, raw = c.request("POST", "/api/action", body=body)
            reply = json.loads(raw)
            assert code == status and why in reply["error"], (body, code, reply)
            assert "TypeError" not in reply["error"] and "positional" not in reply["error"]
        code, _, raw = c.request("POST", "/api/action", body=None, headers={"Content-Type": "application/json",
                                                                           "Content-Length": "1000000"})
        assert code == 413
    finally:
        c.close()


def test_the_page_runs_under_its_content_security_policy() -> None:
    """The page in headless Chromium *with* its CSP enforced (the other browser tests bypass it
    to poll with eval): it connects and shows the map with no CSP violation."""
    from playwright import sync_api

    from .test_console_browser import ARGS, CHROMIUM

    c = Console()
    try:
        with sync_api.sync_playwright() as p:
            b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                page = b.new_page()
                messages: list[str] = []
                page.on("console", lambda msg: messages.append(msg.text))
                page.on("pageerror", lambda e: messages.append(str(e)))
                page.goto(c.server.url)
                deadline = time.monotonic() + 20
                while time.monotonic() < deadline and not page.evaluate("window.coex && window.coex.updates > 0"):
                    time.sleep(0.1)
                assert page.evaluate("window.coex.updates > 0 && window.coex.connected")
                assert page.evaluate("document.querySelector('.skey.s-footprint') !== null")
                colour = page.evaluate("getComputedStyle(document.querySelector('.s-footprint')).borderTopColor")
                assert colour == "rgb(120, 230, 255)"
                assert not [t for t in messages if "Content Security Policy" in t], messages
            finally:
                b.close()
    finally:
        c.close()


def test_the_sign_in_page_keeps_its_style_under_its_policy(console: Console) -> None:
    from playwright import sync_api

    from .test_console_browser import ARGS, CHROMIUM

    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = b.new_page()
            messages: list[str] = []
            page.on("console", lambda msg: messages.append(msg.text))
            page.goto(console.server.url + "login")
            assert page.evaluate("getComputedStyle(document.body).backgroundColor") == "rgb(13, 27, 38)"
            page.fill("#name", "vic")
            page.fill("#password", PASSWORDS["vic"])
            page.click("#signin")
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not page.evaluate("!!(window.coex && window.coex.me)"):
                time.sleep(0.1)
            assert page.evaluate("window.coex.me.role") == "viewer"
            assert not [t for t in messages if "Content Security Policy" in t], messages
        finally:
            b.close()


def test_sigterm_stops_an_https_console_that_holds_an_idle_connection(operators: Path, tmp_path: Path) -> None:
    """The old console ignored SIGTERM while a silent connection held its TLS handshake."""
    import signal

    cert, key = _certificate(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "coex_core.cli", "topside", "--transport", "loopback://sigterm",
                             "--http", "127.0.0.1:0", "--operators", str(operators), "--tls-cert", cert,
                             "--tls-key", key], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    idle = None
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        port = int(line.split("https://127.0.0.1:")[1].split("/")[0])
        idle = socket.create_connection(("127.0.0.1", port))
        time.sleep(0.3)
        t = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=15) == 0
        assert time.monotonic() - t < 10.0
    finally:
        if idle is not None:
            idle.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_every_refusal_is_logged_with_who_and_why(console: Console, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("INFO")
    cookie, csrf = console.login("vic")
    console.act(cookie, csrf)
    console.request("POST", "/login", form={"name": "ana", "password": "not her password"})
    console.request("GET", "/api/state", headers={"Host": "evil.example"})
    text = caplog.text
    assert "(vic): vic is a viewer: viewers cannot command" in text
    assert "sign-in failed for 'ana' from 127.0.0.1: wrong name or password" in text
    assert "'evil.example'" in text and "HTTP 400" in text


def test_event_streams_are_capped_and_a_closed_one_frees_its_place() -> None:
    c = Console(limits=Limits(streams=2))
    streams = [c.stream(), c.stream()]
    try:
        for s in streams:
            assert s.next()[0] == "snapshot"  # type: ignore[index]
        conn = c.connection(timeout=5.0)
        conn.request("GET", "/api/events")
        third = conn.getresponse()
        assert third.status == 429, third.status  # read no further: a stream never ends
        assert b"event streams are open" in third.read()
        conn.close()
        streams.pop().close()
        deadline = time.monotonic() + 5
        while True:  # the server notices the browser leave (Starlette listens for the disconnect)
            conn = c.connection(timeout=5.0)
            conn.request("GET", "/api/events")
            status = conn.getresponse().status
            conn.close()
            if status == 200:
                break
            assert time.monotonic() < deadline, "the closed stream's place was not freed"
            time.sleep(0.2)
    finally:
        for s in streams:
            s.close()
        c.close()

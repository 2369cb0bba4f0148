"""The console lets in only who belongs: sign-in, roles, CSRF, rate limits, TLS, and a record of
who commanded what (HTTP with urllib, and the real page in headless Chromium)."""

from __future__ import annotations

import http.client
import json
import shutil
import ssl
import subprocess
import sys
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from coex_apps.console import ConsoleHub, ConsoleState, serve
from coex_apps.console.access import Access, OperatorsFile
from coex_apps.console.cli import console_access
from coex_apps.console.testing import feed_sample
from coex_core import messages as m
from coex_core.channel.schedule import Schedule
from coex_core.errors import ConfigError

T0 = 36000.0
PASSWORDS = {"ana": "correct horse battery", "vic": "viewer password 1"}


@pytest.fixture(scope="module")
def hashed_operators(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The operators file, its passwords hashed once for the module (scrypt takes tens of
    milliseconds a password); each test gets a copy of its own (``operators``)."""
    path = tmp_path_factory.mktemp("operators") / "operators.json"
    f = OperatorsFile(path)
    f.add("ana", "operator", PASSWORDS["ana"])
    f.add("vic", "viewer", PASSWORDS["vic"])
    f.save()
    return path


@pytest.fixture
def operators(tmp_path: Path, hashed_operators: Path) -> Path:
    path = tmp_path / "operators.json"
    shutil.copy(hashed_operators, path)  # its private mode too
    return path


class Console:
    """A console fed with the sample dive, behind sign-in; ``sent`` holds what it commanded."""

    def __init__(self, operators: Path, tls: ssl.SSLContext | None = None) -> None:
        self.state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
        feed_sample(self.state, t0=T0)
        self.sent: list[m.Message] = []
        hub = ConsoleHub(self.state, self.sent.append, lambda: T0)
        self.access = Access(OperatorsFile(operators))
        self.server = serve(hub, "127.0.0.1", 0, access=self.access, tls=tls)
        self.port = self.server.server_address[1]
        self.tls = tls

    def request(self, method: str, path: str, body: Any = None, headers: dict[str, str] | None = None,
                form: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
        if self.tls is not None:
            conn: http.client.HTTPConnection = http.client.HTTPSConnection(
                "127.0.0.1", self.port, timeout=10, context=ssl._create_unverified_context())
        else:
            conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
        h = dict(headers or {})
        data = None
        if form is not None:
            data = urllib.parse.urlencode(form).encode()
            h.setdefault("Content-Type", "application/x-www-form-urlencoded")
        elif body is not None:
            data = json.dumps(body).encode()
            h.setdefault("Content-Type", "application/json")
        conn.request(method, path, body=data, headers=h)
        r = conn.getresponse()
        out = r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
        conn.close()
        return out

    def login(self, name: str, password: str | None = None) -> tuple[str, str]:
        """Sign in; returns the session cookie header value and the CSRF token."""
        code, h, _ = self.request("POST", "/login", form={"name": name, "password": password or PASSWORDS[name]})
        assert code == 303 and h["location"] == "/", (code, h)
        cookie = h["set-cookie"].split(";")[0]
        code, _, body = self.request("GET", "/api/whoami", headers={"Cookie": cookie})
        assert code == 200
        return cookie, json.loads(body)["csrf"]

    def act(self, cookie: str | None, csrf: str | None, action: str = "queue_config",
            args: dict[str, Any] | None = None) -> tuple[int, dict[str, Any]]:
        h = {}
        if cookie:
            h["Cookie"] = cookie
        if csrf:
            h["X-CSRF-Token"] = csrf
        code, _, body = self.request("POST", "/api/action", body={"action": action,
                                                                 "args": args or {"stream": 3, "priority": 50}},
                                     headers=h)
        return code, json.loads(body)

    def close(self) -> None:
        self.server.close()


@pytest.fixture
def console(operators: Path) -> Iterator[Console]:
    c = Console(operators)
    try:
        yield c
    finally:
        c.close()


def test_the_operators_file_keeps_only_salted_hashes(tmp_path: Path) -> None:
    path = tmp_path / "ops.json"
    f = OperatorsFile(path)
    token = f.add("ana", "operator")
    assert token is not None and len(token) >= 30
    assert f.add("bob", "viewer", "a long password") is None
    f.save()
    text = path.read_text()
    assert token not in text and "a long password" not in text
    assert path.stat().st_mode & 0o077 == 0  # not readable by others
    again = OperatorsFile(path)
    assert again.verify("ana", token) is not None and again.verify("ana", "wrong") is None
    assert again.verify("bob", "a long password").role == "viewer"  # type: ignore[union-attr]
    assert again.verify("nobody", token) is None
    with pytest.raises(ConfigError, match="role"):
        f.add("eve", "admin", "a long password")
    for weak, why in (("short", "at least 12"), ("password", "at least 12"), (" " * 8, "at least 12"),
                      (" " * 16, "at least 12"), ("aaaaaaaaaaaaaaaa", "five different"),
                      ("Password1234", "too common"), ("eve.the.operator", None)):
        if why is None:
            assert f.add("eve", "viewer", weak) is None
        else:
            with pytest.raises(ConfigError, match=why):
                f.add("eve", "viewer", weak)
    f.remove("eve")
    f.remove("bob")
    assert set(f.operators) == {"ana"}


def test_coex_operators_add_list_remove(tmp_path: Path) -> None:
    path = str(tmp_path / "ops.json")

    def coex(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "coex_core.cli", "operators", "--file", path, *args],
                              input=stdin, capture_output=True, text=True, timeout=60)

    r = coex("add", "ana", "--role", "operator")
    assert r.returncode == 0 and "token (shown once" in r.stdout
    token = r.stdout.rsplit(": ", 1)[1].strip()
    assert coex("add", "vic", "--role", "viewer", "--password-stdin", stdin="viewer password 1\n").returncode == 0
    r = coex("list")
    assert r.stdout.split() == ["ana", "operator", "vic", "viewer"]
    assert OperatorsFile(path).verify("ana", token) is not None
    r = coex("role", "vic", "--role", "operator")  # a new role, the same password
    assert r.returncode == 0 and coex("list").stdout.split() == ["ana", "operator", "vic", "operator"]
    assert OperatorsFile(path).verify("vic", "viewer password 1") is not None
    assert coex("role", "nobody", "--role", "viewer").returncode == 2
    assert coex("remove", "vic").returncode == 0
    r = coex("remove", "vic")
    assert r.returncode == 2 and "no operator 'vic'" in r.stderr


def test_unauthenticated_page_stream_and_commands_are_refused(console: Console) -> None:
    code, h, _ = console.request("GET", "/")
    assert code == 303 and h["location"] == "/login"
    for path in ("/api/state", "/api/events", "/api/whoami", "/static/app.js", "/map/0.png"):
        assert console.request("GET", path)[0] == 401, path
    assert console.act(None, None)[0] == 401
    code, _, body = console.request("GET", "/login")
    assert code == 200 and b'name="password"' in body
    assert console.sent == []


def test_a_viewer_watches_but_cannot_command(console: Console) -> None:
    cookie, csrf = console.login("vic")
    code, _, body = console.request("GET", "/api/state", headers={"Cookie": cookie})
    assert code == 200 and "vehicle" in json.loads(body)
    code, reply = console.act(cookie, csrf)
    assert code == 403 and "viewers cannot command" in reply["error"]
    assert console.sent == []


def test_an_operators_command_needs_the_csrf_token_and_carries_their_name(console: Console) -> None:
    cookie, csrf = console.login("ana")
    assert console.act(cookie, None)[0] == 403
    assert console.act(cookie, "forged")[0] == 403
    # a cross-site form POST (no JSON, no token) is refused too
    code, _, _ = console.request("POST", "/api/action", form={"action": "queue_config"},
                                 headers={"Cookie": cookie, "Origin": "http://evil.example"})
    assert code == 403
    assert console.sent == []
    code, reply = console.act(cookie, csrf)
    assert code == 200 and reply["ok"], reply
    assert [type(x).__name__ for x in console.sent] == ["QueueConfig"]
    (cmd,) = [c for c in console.state.snapshot()["commands"] if c["kind"] == "QueueConfig"]
    assert cmd["by"] == "ana"
    assert any(line["text"].startswith("ana sent") for line in console.state.snapshot()["log"])


def test_five_wrong_passwords_lock_the_name_out(console: Console) -> None:
    for _ in range(5):
        code, _, _ = console.request("POST", "/login", form={"name": "ana", "password": "wrong password"})
        assert code == 401
    code, _, body = console.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]})
    assert code == 429 and b"too many failed sign-ins" in body


def test_logout_ends_the_session(console: Console) -> None:
    cookie, csrf = console.login("ana")
    assert console.request("POST", "/logout", headers={"Cookie": cookie})[0] == 403  # no CSRF token
    code, h, _ = console.request("POST", "/logout", headers={"Cookie": cookie, "X-CSRF-Token": csrf})
    assert code == 200 and "Max-Age=0" in h["set-cookie"]
    assert console.request("GET", "/api/state", headers={"Cookie": cookie})[0] == 401


def test_the_session_cookie_is_httponly_and_samesite_strict(console: Console) -> None:
    code, h, _ = console.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]})
    assert code == 303
    cookie = h["set-cookie"]
    low = cookie.lower()  # attribute names and values are case-insensitive (RFC 6265)
    assert "httponly" in low and "samesite=strict" in low and "secure" not in low


def test_an_operators_commands_are_rate_limited(console: Console) -> None:
    console.access.commands_per_minute = 3
    cookie, csrf = console.login("ana")
    codes = [console.act(cookie, csrf)[0] for _ in range(4)]
    assert codes == [200, 200, 200, 429]


def test_the_console_refuses_a_non_loopback_address_without_an_operators_file(operators: Path) -> None:
    with pytest.raises(ConfigError, match=r"refusing to serve the console on 0\.0\.0\.0 without sign-in"):
        console_access("0.0.0.0", None, False, None, None)
    assert console_access("127.0.0.1", None, False, None, None) == (None, None)
    access, tls = console_access("0.0.0.0", operators, False, None, None)
    assert isinstance(access, Access) and tls is None
    assert console_access("0.0.0.0", None, True, None, None) == (None, None)  # --insecure-open
    r = subprocess.run([sys.executable, "-m", "coex_core.cli", "topside", "--transport", "loopback://x",
                        "--http", "0.0.0.0:0"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "without sign-in" in r.stderr


def _certificate(tmp_path: Path) -> tuple[str, str]:
    openssl = shutil.which("openssl")
    assert openssl, "openssl is needed to make the test certificate"
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run([openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key),
                    "-out", str(cert), "-days", "1", "-subj", "/CN=127.0.0.1"],
                   check=True, capture_output=True, timeout=60)
    return str(cert), str(key)


def test_https_with_a_test_certificate(operators: Path, tmp_path: Path) -> None:
    cert, key = _certificate(tmp_path)
    _, tls = console_access("127.0.0.1", operators, False, cert, key)
    assert tls is not None
    c = Console(operators, tls=tls)
    try:
        assert c.server.url.startswith("https://")
        code, h, _ = c.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]})
        assert code == 303 and "Secure" in h["set-cookie"]
        cookie = h["set-cookie"].split(";")[0]
        assert c.request("GET", "/api/state", headers={"Cookie": cookie})[0] == 200
    finally:
        c.close()


def test_in_the_browser_a_viewer_sees_disabled_buttons_and_an_operator_commands(operators: Path) -> None:
    """Headless Chromium: the sign-in page, a viewer's page with its command buttons disabled,
    and an operator whose command reaches the node with their name in the commands panel."""
    from playwright import sync_api

    from .test_console_browser import ARGS, CHROMIUM

    c = Console(operators)
    try:
        with sync_api.sync_playwright() as p:
            b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                for name in ("vic", "ana"):
                    page = b.new_context(bypass_csp=True).new_page()  # Playwright polls with eval
                    page.goto(c.server.url)
                    assert page.url.endswith("/login")
                    page.fill("#name", name)
                    page.fill("#password", PASSWORDS[name])
                    page.click("#signin")
                    page.wait_for_function("window.coex && window.coex.me && window.coex.updates > 0")
                    assert f"{name} (" in page.inner_text("#who")
                    disabled = page.eval_on_selector("#sched-send", "b => b.disabled")
                    if name == "vic":
                        assert disabled is True
                        # the page keeps its layout (the image viewer's overlay class once
                        # turned a viewer's whole page into a fixed overlay)
                        assert page.evaluate("getComputedStyle(document.body).position") == "static"
                        assert page.eval_on_selector("header", "h => h.getBoundingClientRect().top") == 0
                        assert page.eval_on_selector("#fit-btn", "b => b.disabled") is False
                    else:
                        assert disabled is False
                        page.evaluate("act('link_control', {link: 0, enabled: true})")
                        page.wait_for_function("window.coex.S.commands.some(c => c.by === 'ana')")
                        assert "LinkControl" in [type(x).__name__ for x in c.sent]
                    page.close()
            finally:
                b.close()
    finally:
        c.close()


def test_who_sent_a_command_is_saved_with_the_console(console: Console) -> None:
    """The commands panel's "by" survives the store's save and restore (explicit state)."""
    from coex_core import state as st

    cookie, csrf = console.login("ana")
    assert console.act(cookie, csrf)[0] == 200
    restored = st.loads(st.dumps(console.state))
    assert [c["by"] for c in restored.snapshot()["commands"] if c["kind"] == "QueueConfig"] == ["ana"]


def test_the_demo_console_follows_the_same_rule_and_logs_who_acted(operators: Path, tmp_path: Path) -> None:
    """`coex demo --gui` refuses an address beyond loopback without sign-in; with an operators
    file a signed-in person's action reaches the decision list with their name."""
    from coex_apps.demo.config import DemoConfig
    from coex_apps.demo.run import _start_gui
    from coex_core.channel import ChannelManager, LinkConfig
    from coex_core.node import Node

    r = subprocess.run([sys.executable, "-m", "coex_core.cli", "demo", "--quick", "--gui", "--http", "0.0.0.0:0",
                        "--quiet", "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "without sign-in" in r.stderr
    node = Node(ChannelManager(1, [LinkConfig(0, Schedule.simple([1, 2], 20.0, 2.0), dst=2)]))
    vehicle = Node(ChannelManager(2, [LinkConfig(0, Schedule.simple([1, 2], 20.0, 2.0), dst=1)]))
    said: list[tuple[str, str, str]] = []
    server = _start_gui(DemoConfig(http="127.0.0.1:0", operators=operators), node, vehicle,
                        lambda now, kind, text, who="script": said.append((kind, text, who)))
    try:
        c = Console.__new__(Console)
        c.server, c.port, c.tls, c.sent = server, server.server_address[1], None, []
        cookie, csrf = c.login("ana")
        code, reply = c.act(cookie, csrf, "link_control", {"link": 0, "enabled": True})
        assert code == 200, reply
        assert ("console action", 'ana: link_control {"link": 0, "enabled": true}', "person") in said
    finally:
        server.close()

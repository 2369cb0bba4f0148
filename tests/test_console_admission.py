"""The console stays up for its operator (issue 52): admission per address, per session and per
role, fair pictures, lockout that cannot be aimed, and the smaller holes (deep JSON, huge
numbers, long heads, two framings, origins, Secure behind a proxy, passwords in logs, the
command budget, file modes, ``--file`` anywhere). Loopback only; addresses 127.0.0.x stand
for other machines. Each test a few seconds; the whole flood is ``test_console_flood.py``."""

from __future__ import annotations

import http.client
import json
import logging
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex_apps.console.access import Access, OperatorsFile, secret_file_problem
from coex_apps.console.admission import trim_memory
from coex_apps.console.cli import console_access
from coex_apps.console.server import Limits, loads_bounded
from coex_core.errors import ConfigError

from .test_console_attacks import PASSWORDS, Console, _raw

#: the operator's answers come within this many seconds (the availability the console promises)
BOUND = 3.0

# ------------------------------------------------------------------ helpers


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


def idle_sockets(port: int, n: int, source: str) -> list[socket.socket]:
    out = []
    for _ in range(n):
        s = socket.socket()
        s.bind((source, 0))
        s.connect(("127.0.0.1", port))
        out.append(s)
    return out


def closed_by_server(s: socket.socket, seconds: float = 2.0) -> bool:
    s.settimeout(seconds)
    try:
        return s.recv(1) == b""
    except (TimeoutError, BlockingIOError):
        return False
    except OSError:
        return True


def get(c: Console, path: str, cookie: str | None = None, source: str = "127.0.0.1",
        headers: dict[str, str] | None = None) -> tuple[int, bytes]:
    h = dict(headers or {})
    if cookie:
        h["Cookie"] = cookie
    code, _, body = c.request("GET", path, headers=h, source=source)
    return code, body


def slow_pictures(c: Console, seconds: float) -> int:
    """Make image pictures take ``seconds``; returns an image id."""
    real = c.state.image_png

    def slow(iid: int, full: bool = False) -> bytes | None:
        time.sleep(seconds)
        return real(iid, full)

    c.state.image_png = slow  # type: ignore[method-assign]
    return next(iter(c.state.images))


# ------------------------------------------------------------------ connections
def test_idle_sockets_from_one_address_cost_that_address_its_own_places() -> None:
    """63 idle sockets once gave 503 to everyone: now an address holds at most its own places,
    and a new connection takes the place of its oldest idle one."""
    c = Console(limits=Limits(connections_per_address=4, header_seconds=30.0))
    held = idle_sockets(c.port, 10, "127.0.0.2")
    try:
        time.sleep(0.3)
        assert c.server.doors.others.get("127.0.0.2", 0) <= 4
        assert sum(closed_by_server(s, 0.2) for s in held) >= 6  # the oldest made room
        assert get(c, "/api/state")[0] == 200  # another machine
        assert get(c, "/api/state", source="127.0.0.2")[0] == 200  # and the same one, on a new socket
    finally:
        for s in held:
            s.close()
        c.close()


def test_busy_connections_beyond_the_address_cap_are_refused_and_logged(operators: Path,
                                                                       caplog: pytest.LogCaptureFixture) -> None:
    """Only when none of its connections is idle is an address refused (503 at once, logged
    with the address); others are served meanwhile."""
    caplog.set_level(logging.INFO)
    c = Console(operators, limits=Limits(connections_per_address=2, body_seconds=5.0))
    slow = []
    try:
        for _ in range(2):  # bodies that never finish: busy connections
            s = socket.create_connection(("127.0.0.1", c.port), source_address=("127.0.0.2", 0))
            s.sendall(b"POST /login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                      b"Content-Length: 100\r\n\r\n{")
            slow.append(s)
        time.sleep(0.3)
        third = socket.create_connection(("127.0.0.1", c.port), source_address=("127.0.0.2", 0), timeout=2.0)
        out = third.recv(4096)  # answered before it asks anything
        third.close()
        assert out.startswith(b"HTTP/1.1 503") and b"no room" in out, out[:200]
        assert get(c, "/login", source="127.0.0.3")[0] == 200
        assert "refused a connection from 127.0.0.2" in caplog.text
    finally:
        for s in slow:
            s.close()
        c.close()


def test_a_full_console_makes_room_from_the_address_holding_most() -> None:
    c = Console(limits=Limits(connections=8, connections_per_address=6, header_seconds=30.0))
    hog = idle_sockets(c.port, 6, "127.0.0.2")
    other = idle_sockets(c.port, 2, "127.0.0.3")
    try:
        time.sleep(0.3)
        assert c.server.doors.count == 8
        assert get(c, "/api/state", source="127.0.0.4")[0] == 200
        time.sleep(0.2)
        assert not any(closed_by_server(s, 0.1) for s in other)  # the hog paid
        assert sum(closed_by_server(s, 0.1) for s in hog) >= 1
    finally:
        for s in hog + other:
            s.close()
        c.close()


def test_an_operators_connection_is_never_closed_to_make_room(operators: Path) -> None:
    c = Console(operators, limits=Limits(connections_per_address=3, header_seconds=30.0, keep_alive_seconds=30))
    try:
        cookie, _ = c.login("ana", source="127.0.0.2")
        conn = c.connection("127.0.0.2")  # her page's keep-alive connection
        conn.request("GET", "/api/whoami", headers={"Cookie": cookie})
        assert conn.getresponse().read() and True
        held = idle_sockets(c.port, 8, "127.0.0.2")  # someone else at her address (NAT)
        try:
            time.sleep(0.3)
            conn.request("GET", "/api/state", headers={"Cookie": cookie})
            r = conn.getresponse()
            assert r.status == 200 and r.read()
        finally:
            for s in held:
                s.close()
            conn.close()
    finally:
        c.close()


# ------------------------------------------------------------------ streams
def _open_stream(c: Console, cookie: str | None, source: str = "127.0.0.1") -> tuple[int, http.client.HTTPConnection]:
    conn = c.connection(source, timeout=10.0)
    conn.request("GET", "/api/events", headers={"Cookie": cookie} if cookie else {})
    r = conn.getresponse()
    if r.status != 200:
        r.read()
    return r.status, conn


def test_streams_opened_at_once_are_counted_one_by_one(operators: Path) -> None:
    """A signed-in viewer once passed the stream cap by opening streams at once (the cap was
    checked before the count rose)."""
    c = Console(operators, limits=Limits(streams_per_session=3, streams_per_address=50))
    try:
        cookie, _ = c.login("vic", source="127.0.0.3")
        barrier = threading.Barrier(24)

        def one(_: int) -> tuple[int, http.client.HTTPConnection]:
            barrier.wait()
            return _open_stream(c, cookie, "127.0.0.3")

        with ThreadPoolExecutor(24) as pool:
            got = list(pool.map(one, range(24)))
        codes = [code for code, _ in got]
        assert codes.count(200) == 3 and codes.count(429) == 21, codes
        for _, conn in got:
            conn.close()
    finally:
        c.close()


def test_operators_keep_stream_places_that_viewers_cannot_take(operators: Path) -> None:
    c = Console(operators, limits=Limits(streams=6, operator_streams=2, streams_per_session=20,
                                         streams_per_address=20))
    conns = []
    try:
        vic, _ = c.login("vic", source="127.0.0.3")
        codes = []
        for _ in range(8):
            code, conn = _open_stream(c, vic, "127.0.0.3")
            codes.append(code)
            conns.append(conn)
        assert codes == [200] * 4 + [429] * 4, codes
        ana, _ = c.login("ana")
        for _ in range(2):
            code, conn = _open_stream(c, ana)
            conns.append(conn)
            assert code == 200
    finally:
        for conn in conns:
            conn.close()
        c.close()


# ------------------------------------------------------------------ requests and pictures
def test_a_viewers_flood_of_pictures_leaves_the_operator_served(operators: Path) -> None:
    """One viewer once filled the shared picture queue: the operator's map waited 32 s or got
    429. Now her requests have their own places and her picture is drawn next, in the drawing
    place kept for operators, not after the viewer's queue."""
    c = Console(operators, limits=Limits(renders=2, requests_per_session=40, requests_per_address=40))
    real = c.state.image_png
    started: list[tuple[str, float]] = []  # (whose thread, when) of every picture drawn

    def slow(iid: int, full: bool = False) -> bytes | None:
        started.append((threading.current_thread().name, time.monotonic()))
        time.sleep(0.4)
        return real(iid, full)

    c.state.image_png = slow  # type: ignore[method-assign]
    iid = next(iter(c.state.images))
    try:
        vic, _ = c.login("vic", source="127.0.0.3")
        ana, csrf = c.login("ana")

        def viewer(_: int) -> int:
            return get(c, f"/image/{iid}.png?full=1", vic, "127.0.0.3")[0]

        with ThreadPoolExecutor(30) as pool:
            flood = [pool.submit(viewer, k) for k in range(30)]
            time.sleep(0.8)  # the viewer's pictures wait in the queue
            asked = time.monotonic()
            assert get(c, f"/image/{iid}.png?full=1", ana)[0] == 200
            t = time.monotonic()
            assert get(c, "/api/state", ana)[0] == 200
            assert c.act(ana, csrf)[0] == 200
            rest = time.monotonic() - t
            codes = [f.result() for f in flood]
        mine = [when for name, when in started if "low" not in name]
        theirs = [when for name, when in started if "low" in name]
        assert len(mine) == 1 and len(theirs) >= 2, started
        # hers did not wait for the viewer's queue: viewer's pictures asked before her were still
        # waiting when hers started (a shared first-come queue would have drawn them all first).
        # How many of them began between her ask and hers depends on the machine's load (her
        # request is read and checked meanwhile), so the count is not asserted.
        assert asked < mine[0] and any(when > mine[0] for when in theirs), (asked, mine, theirs)
        assert rest < BOUND, rest
        assert codes.count(429) >= 20 and set(codes) <= {200, 429}, codes  # 6 of one session at once
    finally:
        c.close()


def test_requests_beyond_the_lanes_are_answered_503_with_the_reason(operators: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    c = Console(operators, limits=Limits(requests=3, requests_per_address=3, requests_per_session=3,
                                         renders_per_client=20, render_queue=20))
    iid = slow_pictures(c, 0.6)
    try:
        vic, _ = c.login("vic", source="127.0.0.3")
        with ThreadPoolExecutor(8) as pool:
            got = list(pool.map(lambda _: get(c, f"/image/{iid}.png", vic, "127.0.0.3"), range(8)))
        codes = [code for code, _ in got]
        assert codes.count(200) >= 3 and codes.count(503) >= 3, codes
        assert any(b"requests" in body and b"being answered" in body for code, body in got if code == 503)
        assert "console answered 503 to GET /image/" in caplog.text and "from 127.0.0.3" in caplog.text
        ana, _ = c.login("ana")
        assert get(c, "/api/state", ana)[0] == 200
    finally:
        c.close()


def test_a_hundred_pollers_get_one_snapshot(operators: Path) -> None:
    """100 pollers of /api/state once made 55 % 503: a snapshot is now made once while
    nothing changes and served to all."""
    c = Console(operators)
    try:
        viewers = [c.login("vic", source=f"127.0.1.{k + 1}")[0] for k in range(10)]  # ten laptops
        calls = [0]
        real = c.hub.snapshot

        def counted() -> dict[str, Any]:
            calls[0] += 1
            return real()

        c.hub.snapshot = counted  # type: ignore[method-assign]
        with ThreadPoolExecutor(20) as pool:
            codes = list(pool.map(lambda k: get(c, "/api/state", viewers[k % 10], f"127.0.1.{k % 10 + 1}")[0],
                                  range(100)))
        assert codes == [200] * 100
        assert calls[0] <= 10, calls
    finally:
        c.close()


# ------------------------------------------------------------------ sign-in
def test_a_browser_that_signed_in_before_is_not_refused_by_others_guessing(operators: Path) -> None:
    """Anyone behind the operator's address could keep her correct password refused (429).
    Failures count per name and address, per address and per name; her browser, known from a
    previous sign-in (a signed device cookie), answers only for its own failures."""
    c = Console(operators, account_failures=6, backoff=30.0)
    try:
        set_device = next(v for k, v in _headers(c, "ana") if k == "set-cookie" and "coex_device" in v)
        assert "path=/login" in set_device.lower() and "httponly" in set_device.lower()
        device = set_device.split(";")[0]

        def guess(k: int) -> int:  # a stranger at her address, and others elsewhere
            src = "127.0.0.1" if k < 6 else f"127.0.2.{k}"
            return c.request("POST", "/login", form={"name": "ana", "password": f"wrong guess {k}"}, source=src)[0]

        with ThreadPoolExecutor(12) as pool:
            codes = list(pool.map(guess, range(12)))
        assert set(codes) <= {401, 429}
        # her name is held for browsers that never signed in as her ...
        code, _, body = c.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]},
                                  source="127.0.0.9")
        assert code == 429 and b"try again" in body
        # ... and her own browser at her (shared) address is not refused
        code, _, _ = c.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]},
                               headers={"Cookie": device})
        assert code == 303, code
        # a device cookie made for her does not help with another name, nor a forged one
        assert c.request("POST", "/login", form={"name": "bob", "password": "wrong wrong wrong"},
                         headers={"Cookie": device}, source="127.0.0.1")[0] in (401, 429)
        forged = device[:-3] + ("aaa" if not device.endswith("aaa") else "bbb")
        code, _, _ = c.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]},
                               headers={"Cookie": forged.replace(device.split(".")[1], "0" * 32)}, source="127.0.0.9")
        assert code == 429
    finally:
        c.close()


def _headers(c: Console, name: str) -> list[tuple[str, str]]:
    conn = c.connection()
    body = f"name={name}&password={PASSWORDS[name].replace(' ', '+')}"
    conn.request("POST", "/login", body=body, headers={"Content-Type": "application/x-www-form-urlencoded"})
    r = conn.getresponse()
    r.read()
    conn.close()
    assert r.status == 303
    return [(k.lower(), v) for k, v in r.getheaders()]


def test_a_known_browser_has_its_own_few_tries(operators: Path) -> None:
    """A stolen device cookie is no free pass to guess: it gets max_failures tries, then waits."""
    now = [1000.0]
    access = Access(OperatorsFile(operators), backoff=30.0, clock=lambda: now[0])
    s = access.login("ana", PASSWORDS["ana"], "127.0.0.1")
    device = access.device_cookie(s)
    for _ in range(5):
        with pytest.raises(Exception, match="wrong name or password"):
            access.login("ana", "not her password", "127.0.0.5", device=device)
    with pytest.raises(Exception, match="too many failed"):
        access.login("ana", PASSWORDS["ana"], "127.0.0.5", device=device)
    assert access.login("ana", PASSWORDS["ana"], "127.0.0.6")  # the name itself is not held


def test_a_password_typed_into_the_name_field_is_never_logged(console: Console, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    for _ in range(7):  # failures, then a wait: every line about it
        console.request("POST", "/login", form={"name": PASSWORDS["ana"], "password": ""})
    console.request("POST", "/login", body={"name": PASSWORDS["bob"], "password": "x"})
    assert "sign-in failed for a name that is nobody's" in caplog.text
    assert PASSWORDS["ana"] not in caplog.text and PASSWORDS["bob"] not in caplog.text
    console.request("POST", "/login", form={"name": "ana", "password": "not her password"})
    assert "'ana'" in caplog.text  # an operator's name is said


@pytest.fixture
def console(operators: Path) -> Any:
    c = Console(operators)
    try:
        yield c
    finally:
        c.close()


# ------------------------------------------------------------------ the smaller holes
@pytest.mark.parametrize("body", [
    "[" * 3000 + "]" * 3000,
    '{"action": "request_region", "args": {"level": 0, "x_min": 1e308, "y_min": 0, "x_max": 1, "y_max": 1}}',
    '{"action": "queue_config", "args": {"stream": 3, "priority": 1e999}}',
    '{"action": "queue_config", "args": {"stream": 3, "ttl": NaN}}',
    '{"action": "queue_config", "args": {"stream": 3, "ttl": -Infinity}}',
    '{"action": "queue_config", "args": {"stream": 3, "ttl": 10000000000000000000000000}}',
    '{"action": "queue_config", "args": {"stream": ' + "[" * 40 + "]" * 40 + "}}",
])
def test_deep_json_and_huge_numbers_answer_400_not_500(body: str, caplog: pytest.LogCaptureFixture) -> None:
    c = Console()
    try:
        conn = c.connection()
        conn.request("POST", "/api/action", body=body.encode(), headers={"Content-Type": "application/json"})
        r = conn.getresponse()
        raw = r.read()
        conn.close()
        assert r.status == 400, (r.status, raw[:300])
        reply = json.loads(raw)
        assert "Traceback" not in raw.decode() and reply["ok"] is False
        assert "Traceback" not in caplog.text and c.sent == []
    finally:
        c.close()


def test_every_action_refuses_huge_but_allowed_numbers_with_a_reason() -> None:
    """Numbers up to 1e12 pass the JSON bound: each action's own checks answer them (no 500)."""
    from coex_apps.console.actions import ACTIONS

    c = Console()
    try:
        samples: dict[str, dict[str, Any]] = {
                   "request_region": {"level": 0, "x_min": 0, "y_min": 0, "x_max": 1, "y_max": 1},
                   "survey": {"kind": "goto", "x": 0, "y": 0},
                   "set_image_goal": {"image_id": 0, "kind": "fraction", "value": 50},
                   "image_by_time": {"t": 36000},
                   "image_region": {"image_id": 0, "x0": 0, "y0": 0, "x1": 8, "y1": 8},
                   "refine_series": {"channel": 0, "start": 35000, "end": 36000},
                   "queue_config": {"stream": 3, "priority": 50},
                   "link_control": {"link": 0, "enabled": True},
                   "spare_config": {"percent": 50},
                   "propose_schedule": {"link": 0, "slots": [{"owner": 1, "duration": 20, "guard": 2}]}}
        assert set(samples) == set(ACTIONS)
        for action, args in samples.items():
            for key, value in args.items():
                if isinstance(value, bool) or not isinstance(value, int | float):
                    continue
                for big in (1e12, -1e12, 999999999999, 2**40):
                    code, _, raw = c.request("POST", "/api/action", body={"action": action, "args": {**args, key: big}})
                    assert code in (200, 400), (action, key, big, code, raw[:300])
    finally:
        c.close()


def test_the_json_bounds() -> None:
    assert loads_bounded(b'{"a": [1, 2.5, -1e12]}') == {"a": [1, 2.5, -1e12]}
    for bad in (b"1e13", b"[NaN]", b"[Infinity]", b"1" * 14, b"[" * 33 + b"]" * 33):
        with pytest.raises(ValueError):
            loads_bounded(bad)


def test_the_16_kb_head_limit_holds_over_http() -> None:
    """The documented 16 KB limit on a request's head was not enforced (100 KB accepted)."""
    c = Console()
    try:
        for size, want in ((100_000, b"HTTP/1.1 431"), (20_000, b"HTTP/1.1 431"), (8_000, b"HTTP/1.1 200")):
            head = (b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Pad: " + b"a" * size + b"\r\n\r\n")
            out = _raw(c.port, head, 2.0)
            assert out.startswith(want), (size, out[:100])
    finally:
        c.close()


def test_both_content_length_and_chunked_get_one_answer_and_the_connection_closed() -> None:
    c = Console()
    try:
        hidden = b"GET /api/smuggled HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
        head = (b"POST /logout HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 4\r\n"
                b"Transfer-Encoding: chunked\r\n\r\n")
        out = _raw(c.port, head + f"{len(hidden):x}\r\n".encode() + hidden + b"\r\n0\r\n\r\n", 1.5)
        assert out.startswith(b"HTTP/1.1 400") and out.count(b"HTTP/1.1") == 1, out
        assert b"connection: close" in out.lower() and b"smuggled" not in out
    finally:
        c.close()


def test_the_origin_check_compares_scheme_host_and_port(tmp_path: Path) -> None:
    c = Console()
    try:
        port = c.port
        for origin, want in ((f"http://127.0.0.1:{port}", 200), (f"http://localhost:{port}", 200),
                             (f"http://127.0.0.1:{port + 1}", 403), (f"https://127.0.0.1:{port}", 403),
                             ("http://127.0.0.1", 403), ("null", 403), (f"http://evil.example:{port}", 403)):
            assert c.act(headers={"Origin": origin})[0] == want, origin
    finally:
        c.close()


def test_behind_the_documented_proxy_the_cookie_is_secure_and_the_origin_the_proxys(operators: Path) -> None:
    """nginx with TLS in front (X-Forwarded-For, X-Forwarded-Proto) and --trusted-proxy,
    --public-origin https://console.ship.example."""
    from coex_apps.console import serve

    c = Console(operators)
    c.server.close()
    c.server = serve(c.hub, "127.0.0.1", 0, access=c.access, trusted_proxies=["127.0.0.1"],
                     public_origins=["https://console.ship.example"])
    c.port = int(c.server.server_address[1])
    try:
        proxied = {"X-Forwarded-For": "10.0.0.7", "X-Forwarded-Proto": "https", "Host": "console.ship.example",
                   "Origin": "https://console.ship.example"}
        code, h, _ = c.request("POST", "/login", form={"name": "ana", "password": PASSWORDS["ana"]}, headers=proxied)
        assert code == 303 and "secure" in h["set-cookie"].lower(), h
        assert h["strict-transport-security"].startswith("max-age=")
        cookie = h["set-cookie"].split(";")[0]
        code, _, body = c.request("GET", "/api/whoami", headers={**proxied, "Cookie": cookie})
        csrf = json.loads(body)["csrf"]
        assert c.act(cookie, csrf, headers=proxied)[0] == 200
        assert c.act(cookie, csrf, headers={**proxied, "Origin": "http://console.ship.example"})[0] == 403
        # a client that is not the proxy cannot claim https
        code, h, _ = c.request("POST", "/login", form={"name": "bob", "password": PASSWORDS["bob"]},
                               headers={"X-Forwarded-Proto": "https"}, source="127.0.0.2")
        assert code == 303 and "secure" not in h["set-cookie"].lower()
    finally:
        c.close()


def test_refused_actions_do_not_use_up_the_command_budget(operators: Path) -> None:
    c = Console(operators, commands_per_minute=2)
    try:
        cookie, csrf = c.login("ana")
        for _ in range(5):
            assert c.act(cookie, csrf, args={"stream": 99})[0] == 400
        assert [c.act(cookie, csrf)[0] for _ in range(3)] == [200, 200, 429]
    finally:
        c.close()


def test_secret_files_other_users_may_read_are_refused(operators: Path, tmp_path: Path) -> None:
    from .test_console_access import _certificate

    os.chmod(operators, 0o644)
    with pytest.raises(ConfigError, match=r"chmod 600 .*operators\.json"):
        console_access("127.0.0.1", operators, False, None, None)
    os.chmod(operators, 0o600)
    assert console_access("127.0.0.1", operators, False, None, None)[0] is not None
    cert, key = _certificate(tmp_path)
    os.chmod(key, 0o640)
    with pytest.raises(ConfigError, match=r"TLS key .* its group"):
        console_access("127.0.0.1", operators, False, cert, key)
    os.chmod(key, 0o600)
    assert console_access("127.0.0.1", operators, False, cert, key)[1] is not None
    assert secret_file_problem(key) is None


def test_the_config_checker_says_the_same_of_secret_files(operators: Path, tmp_path: Path) -> None:
    """``coex config check`` refuses what the console would refuse; a command key file others
    may read is a warning (git keeps no modes: the examples' keys are 0644)."""
    from coex_apps.vehicle.config import check

    key = tmp_path / "coex.key"
    key.write_text("00" * 16)
    os.chmod(key, 0o644)
    os.chmod(operators, 0o644)
    head = ('[node]\nrole = "topside"\nid = 1\npeer = 2\ncommand_key_file = "coex.key"\n'
            '[[modems]]\nuri = "loopback://x"\n')
    f = tmp_path / "t.toml"
    f.write_text(head + f'[console]\noperators = "{operators.name}"\n'
                        'public_origins = ["https://ship.example", "ftp://x"]\n')
    _, problems = check(f, "topside")
    text = "\n".join(problems)
    assert "console.operators" in text and "chmod 600" in text
    assert "console.public_origins" in text and "ftp://x" in text and "'https://ship.example'" not in text
    f.write_text(head)
    cfg, problems = check(f, "topside")
    assert problems == [] and cfg is not None
    assert any(w.startswith("node.command_key_file") and "chmod 600" in w for w in cfg.warnings), cfg.warnings


def test_operators_file_anywhere_on_the_command_line(tmp_path: Path) -> None:
    path = str(tmp_path / "ops.json")
    r = subprocess.run([sys.executable, "-m", "coex_core.cli", "operators", "add", "ana", "--role", "operator",
                        "--file", path], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for args in (["operators", "list", "--file", path], ["operators", "--file", path, "list"]):
        r = subprocess.run([sys.executable, "-m", "coex_core.cli", *args], capture_output=True, text=True, timeout=60)
        assert r.stdout.split() == ["ana", "operator"], r.stderr


def test_freed_memory_is_given_back() -> None:
    assert trim_memory() is (sys.platform == "linux")


def test_big_pictures_are_drawn_in_bands_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    from coex_plugins import render

    rng = np.random.default_rng(3)
    z = rng.normal(size=(301, 257)).cumsum(0)
    z[rng.random(z.shape) < 0.2] = np.nan
    whole = render.elevation_rgba(z, -3, 3, 0.5)
    monkeypatch.setattr(render, "BAND_CELLS", 1000)
    assert np.array_equal(render.elevation_rgba(z, -3, 3, 0.5), whole)

"""The console under a flood from other machines (issue 52): does its operator stay served?

A console (the sample dive, behind sign-in: operators ana and bob, viewer vic) runs in its own
process on loopback; another process attacks it from addresses 127.0.x.y standing for other
machines on the ship's network, all at once:

* ``idle``: 300 sockets from 127.0.0.2 that never send a request (re-opened when closed);
* ``streams``: a viewer's 100 event streams at once (re-opened when refused or ended);
* ``windows``: a viewer's 40 map windows of 4 Mpx at once, again and again;
* ``guessers``: 50 addresses guessing ana's password (waiting as long as told to);
* ``pollers``: 100 pollers of ``/api/state``, once a second each (ten viewers' laptops).

Meanwhile, every ``--every`` seconds, the operator (ana, from 127.0.0.1, in the browser she
signed in with before: its device cookie) signs in, reads the state and sends an action, and
bob, who never signed in from his address before, signs in too; each answer must come within
``--bound`` seconds (the availability the console promises its operator). The server's
resident memory (RSS) is sampled before, during and after the flood. ``--idle-sockets N``
first measures RSS before, with and after N idle sockets (plain and TLS), spread over
addresses so that none is refused.

    python bench/console_flood.py [--seconds 30] [--every 2] [--idle-sockets 5000] [--quick]

Prints the figures and writes ``bench/results/console_flood.json``. ``tests/test_console_flood.py``
runs a short flood (``run_flood``) in CI. Timings depend on the machine's load: say so when
reporting them.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import signal
import socket
import ssl
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
from collections import Counter
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PASSWORDS = {"ana": "correct horse battery", "bob": "another operator 2", "vic": "viewer password 1"}
#: a 4 Mpx window of map level 0 (1 m cells), somewhere else each time (no picture is drawn twice)
WINDOW = "/map/0/window.png?x0={x}&y0=-1024&x1={x2}&y1=1024&step=1"


# ------------------------------------------------------------------ the console, in its own process
def serve_main(operators: str, tls: bool) -> None:
    """``console_flood.py serve``: the sample console; prints ``PORT PID`` and runs until
    stdin closes."""
    import logging
    import threading

    from coex_apps.console import ConsoleHub, ConsoleState, serve
    from coex_apps.console.access import Access, OperatorsFile
    from coex_apps.console.testing import feed_sample
    from coex_core.channel.schedule import Schedule

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
    feed_sample(state, t0=36000.0, images=1)  # the map, the series, a picture (quick to make)
    sent: list[Any] = []
    hub = ConsoleHub(state, sent.append, lambda: 36000.0)
    context = None
    if tls:
        from coex_apps.console.server import tls_context

        d = Path(operators).parent
        key = (["-newkey", "rsa:2048"] if os.environ.get("COEX_FLOOD_RSA") else
               ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"])  # (an ECDSA key: cheap handshakes)
        subprocess.run(["openssl", "req", "-x509", *key, "-nodes", "-keyout", str(d / "key.pem"),
                        "-out", str(d / "cert.pem"), "-days", "1", "-subj", "/CN=127.0.0.1"],
                       check=True, capture_output=True, timeout=60)
        os.chmod(d / "key.pem", 0o600)
        context = tls_context(str(d / "cert.pem"), str(d / "key.pem"))
    server = serve(hub, "127.0.0.1", 0, access=Access(OperatorsFile(operators)), tls=context)
    print(server.server_address[1], os.getpid(), flush=True)
    done = threading.Event()

    def until_stdin_closes() -> None:
        sys.stdin.read()
        done.set()

    threading.Thread(target=until_stdin_closes, daemon=True).start()
    signal.signal(signal.SIGTERM, lambda *a: done.set())
    done.wait()
    server.close()


class Console:
    """The console process: ``port``, ``pid``, :meth:`rss_mb`, :meth:`close`."""

    def __init__(self, workdir: Path, tls: bool = False) -> None:
        sys.path.insert(0, str(ROOT))
        from coex_apps.console.access import OperatorsFile

        ops = workdir / "operators.json"
        f = OperatorsFile(ops)
        f.add("ana", "operator", PASSWORDS["ana"])
        f.add("bob", "operator", PASSWORDS["bob"])
        f.add("vic", "viewer", PASSWORDS["vic"])
        f.save()
        self.log = (workdir / "console.log").open("w")
        self.proc = subprocess.Popen([sys.executable, os.environ.get("COEX_FLOOD_SERVE", __file__), "serve", str(ops)] + (["--tls"] if tls else []),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.log, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the console did not start (see console.log)")
        self.port, self.pid = map(int, line.split())
        self.tls = tls

    def rss_mb(self) -> float:
        text = Path(f"/proc/{self.pid}/status").read_text()
        return int(text.split("VmRSS:")[1].split()[0]) / 1024.0

    def runnable_seconds(self) -> float:
        """The seconds the console's threads have run or waited for a processor, in all (Linux
        ``schedstat``): it grows while the console has work, whether or not a loaded machine
        gives it the processor; 0.0 where there is no ``schedstat``."""
        total = 0
        for task in Path(f"/proc/{self.pid}/task").glob("*/schedstat"):
            try:
                run, wait = task.read_text().split()[:2]
            except (OSError, ValueError):
                continue  # a thread that ended meanwhile
            total += int(run) + int(wait)
        return total / 1e9

    def wait_quiet(self, window: float = 1.0, share: float = 0.1, cap: float = 240.0) -> float:
        """Wait until the console has gone quiet: in one ``window`` its threads were runnable
        (running or waiting for a processor) less than ``share`` of it, so the work the flood
        left (queued pictures, password checks, connections to close) is done. At most ``cap``
        seconds; returns the seconds waited. On a machine other work loads, the console runs its
        backlog later, not less: this waits for the work, not for a number of wall seconds."""
        start = time.monotonic()
        last = self.runnable_seconds()
        while time.monotonic() - start < cap:
            time.sleep(window)
            now = self.runnable_seconds()
            if now - last < share * window:
                break
            last = now
        return time.monotonic() - start

    def close(self) -> None:
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


# ------------------------------------------------------------------ a small HTTP client on asyncio
class Reply:
    def __init__(self, status: int, headers: dict[str, str], body: bytes) -> None:
        self.status, self.headers, self.body = status, headers, body

    def cookies(self) -> dict[str, str]:
        out = {}
        for k, v in self.headers.items():
            if k.startswith("set-cookie"):
                name, _, value = v.split(";")[0].partition("=")
                out[name.strip()] = value.strip()
        return out


async def _head(reader: asyncio.StreamReader) -> tuple[int, dict[str, str]]:
    raw = await reader.readuntil(b"\r\n\r\n")
    lines = raw.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers: dict[str, str] = {}
    for n, line in enumerate(lines[1:]):
        if ":" in line:
            k, _, v = line.partition(":")
            k = k.strip().lower()
            headers[f"{k}#{n}" if k in headers or k == "set-cookie" else k] = v.strip()
    return status, headers


async def request(port: int, method: str, path: str, *, source: str = "127.0.0.1", cookie: str = "",
                  body: bytes = b"", ctype: str = "", headers: dict[str, str] | None = None,
                  timeout: float = 30.0, tls: bool = False) -> Reply:
    """One request on a new connection (Connection: close)."""
    ctx = ssl._create_unverified_context() if tls else None
    reader, writer = await asyncio.wait_for(
        asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0), ssl=ctx), timeout)
    try:
        h = {"Host": f"127.0.0.1:{port}", "Connection": "close", **(headers or {})}
        if cookie:
            h["Cookie"] = cookie
        if body or method == "POST":
            h["Content-Length"] = str(len(body))
            h["Origin"] = f"{'https' if tls else 'http'}://127.0.0.1:{port}"
        if ctype:
            h["Content-Type"] = ctype
        writer.write(f"{method} {path} HTTP/1.1\r\n".encode() + "".join(f"{k}: {v}\r\n" for k, v in h.items()).encode()
                     + b"\r\n" + body)
        status, head = await asyncio.wait_for(_head(reader), timeout)
        data = await asyncio.wait_for(reader.read(), timeout)
        return Reply(status, head, data)
    finally:
        writer.close()


def form(**fields: str) -> bytes:
    return urllib.parse.urlencode(fields).encode()


async def sign_in(port: int, name: str, source: str = "127.0.0.1", device: str = "", tls: bool = False) -> Reply:
    return await request(port, "POST", "/login", source=source, body=form(name=name, password=PASSWORDS[name]),
                         ctype="application/x-www-form-urlencoded", cookie=f"coex_device={device}" if device else "",
                         tls=tls)


# ------------------------------------------------------------------ the attackers
async def attack(port: int, seconds: float, kinds: set[str], tls: bool) -> dict[str, Counter[str]]:
    """Run the attacks for ``seconds``; per attack, what the console answered."""
    stop = time.monotonic() + seconds
    counts: dict[str, Counter[str]] = {k: Counter() for k in kinds}

    async def viewer(source: str) -> str:
        r = await sign_in(port, "vic", source, tls=tls)
        assert r.status == 303, r.status
        return f"coex_session={r.cookies()['coex_session']}"

    async def idle(n: int) -> None:
        c = counts["idle"]
        while time.monotonic() < stop:
            try:
                reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=("127.0.0.2", 0))
            except OSError:
                c["connect failed"] += 1
                await asyncio.sleep(0.5)
                continue
            c["opened"] += 1
            try:
                got = await asyncio.wait_for(reader.read(64), max(0.1, stop - time.monotonic()))
                c["refused 503" if got.startswith(b"HTTP/1.1 503") else "closed by the console"] += 1
            except (TimeoutError, OSError):
                pass
            finally:
                writer.close()
            await asyncio.sleep(2.0 + random.random())  # and open another

    async def stream(cookie: str) -> None:
        c = counts["streams"]
        while time.monotonic() < stop:
            try:
                ctx = ssl._create_unverified_context() if tls else None
                reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=("127.0.0.3", 0), ssl=ctx)
                writer.write(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nCookie: {cookie}\r\n\r\n".encode())
                status, _ = await asyncio.wait_for(_head(reader), 30)
                c[str(status)] += 1
                if status == 200:
                    while time.monotonic() < stop:
                        try:
                            data = await asyncio.wait_for(reader.read(65536), max(0.1, stop - time.monotonic()))
                        except TimeoutError:
                            break  # the time is up
                        if not data:
                            break
                writer.close()
            except (TimeoutError, OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError) as exc:
                c[f"error {type(exc).__name__}"] += 1
            await asyncio.sleep(2.0 + random.random())  # and try again

    async def window(cookie: str) -> None:
        c = counts["windows"]
        while time.monotonic() < stop:
            try:
                x = random.randrange(-4096, 4096)
                r = await request(port, "GET", WINDOW.format(x=x, x2=x + 2048), source="127.0.0.4", cookie=cookie,
                                  tls=tls, timeout=60)
                c[str(r.status)] += 1
            except (TimeoutError, OSError, asyncio.IncompleteReadError) as exc:
                c[f"error {type(exc).__name__}"] += 1
            await asyncio.sleep(1.0 + random.random())

    async def guess(k: int) -> None:
        c = counts["guessers"]
        source = f"127.0.3.{k + 1}"
        n = 0
        while time.monotonic() < stop:
            n += 1
            try:
                r = await request(port, "POST", "/login", source=source, body=form(name="ana", password=f"guess {k} {n}"),
                                  ctype="application/x-www-form-urlencoded", tls=tls)
                c[str(r.status)] += 1
                wait = float(r.headers.get("retry-after", "0") or 0) if r.status == 429 else 0.2
            except (TimeoutError, OSError, asyncio.IncompleteReadError):
                c["error"] += 1
                wait = 1.0
            await asyncio.sleep(min(wait, max(0.0, stop - time.monotonic())) + 0.1 * random.random())

    async def poll(cookie: str, source: str) -> None:
        # a page polling once a second on its keep-alive connection (re-opened when closed)
        c = counts["pollers"]
        await asyncio.sleep(random.random())
        conn: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        while time.monotonic() < stop:
            t = time.monotonic()
            try:
                if conn is None:
                    ctx = ssl._create_unverified_context() if tls else None
                    conn = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0), ssl=ctx)
                reader, writer = conn
                writer.write(f"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nCookie: {cookie}\r\n\r\n".encode())
                status, head = await asyncio.wait_for(_head(reader), 30)
                await asyncio.wait_for(reader.readexactly(int(head.get("content-length", "0"))), 30)
                c[str(status)] += 1
                if head.get("connection", "").lower() == "close":
                    writer.close()
                    conn = None
            except (TimeoutError, OSError, asyncio.IncompleteReadError) as exc:
                c[f"error {type(exc).__name__}"] += 1
                if conn is not None:
                    conn[1].close()
                conn = None
            await asyncio.sleep(max(0.0, 1.0 - (time.monotonic() - t)))
        if conn is not None:
            conn[1].close()

    tasks = []
    if "idle" in kinds:
        tasks += [idle(n) for n in range(300)]
    if "streams" in kinds:
        cookie = await viewer("127.0.0.3")
        tasks += [stream(cookie) for _ in range(100)]
    if "windows" in kinds:
        cookie = await viewer("127.0.0.4")
        tasks += [window(cookie) for _ in range(40)]
    if "guessers" in kinds:
        tasks += [guess(k) for k in range(50)]
    if "pollers" in kinds:
        laptops = [(await viewer(f"127.0.4.{k + 1}"), f"127.0.4.{k + 1}") for k in range(10)]
        tasks += [poll(*laptops[k % 10]) for k in range(100)]
    running = [asyncio.ensure_future(t) for t in tasks]
    await asyncio.wait(running, timeout=max(0.0, stop - time.monotonic()) + 2.0)
    for t in running:  # what is still waiting for an answer when the time is up
        t.cancel()
    await asyncio.gather(*running, return_exceptions=True)
    return counts


def attack_main(port: int, seconds: float, kinds: str, tls: bool) -> None:
    """``console_flood.py attack``: run the attacks, print what the console answered (JSON)."""
    counts = asyncio.run(attack(port, seconds, set(kinds.split(",")), tls))
    print(json.dumps({k: dict(v) for k, v in counts.items()}), flush=True)


# ------------------------------------------------------------------ the operator, meanwhile
class KeepAlive:
    """A browser's keep-alive connection (re-opened when the console closed it)."""

    def __init__(self, port: int, source: str = "127.0.0.1", tls: bool = False) -> None:
        self.port, self.source, self.tls = port, source, tls
        self.conn: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    async def request(self, method: str, path: str, *, cookie: str = "", body: bytes = b"", ctype: str = "",
                      headers: dict[str, str] | None = None, timeout: float = 30.0) -> Reply:
        for attempt in (0, 1):
            if self.conn is None:
                ctx = ssl._create_unverified_context() if self.tls else None
                self.conn = await asyncio.wait_for(asyncio.open_connection(
                    "127.0.0.1", self.port, local_addr=(self.source, 0), ssl=ctx), timeout)
            reader, writer = self.conn
            h = {"Host": f"127.0.0.1:{self.port}", **(headers or {})}
            if cookie:
                h["Cookie"] = cookie
            if body or method == "POST":
                h["Content-Length"] = str(len(body))
                h["Origin"] = f"{'https' if self.tls else 'http'}://127.0.0.1:{self.port}"
            if ctype:
                h["Content-Type"] = ctype
            try:
                writer.write(f"{method} {path} HTTP/1.1\r\n".encode()
                             + "".join(f"{k}: {v}\r\n" for k, v in h.items()).encode() + b"\r\n" + body)
                status, head = await asyncio.wait_for(_head(reader), timeout)
            except (OSError, asyncio.IncompleteReadError):
                self.close()
                if attempt:
                    raise
                continue  # the console closed the idle connection meanwhile: a new one
            data = await asyncio.wait_for(reader.readexactly(int(head.get("content-length", "0"))), timeout)
            if head.get("connection", "").lower() == "close":
                self.close()
            return Reply(status, head, data)
        raise AssertionError("unreachable")

    def close(self) -> None:
        if self.conn is not None:
            self.conn[1].close()
            self.conn = None


async def operator_round(page: KeepAlive, device: str, bob_source: str, tls: bool) -> dict[str, Any]:
    """ana, on her page's keep-alive connection in the browser she signed in with before (its
    device cookie), signs in, reads the state, sends an action and loads a map picture; bob
    signs in meanwhile from an address he never used (a new connection). Status and seconds of
    each."""
    out: dict[str, Any] = {}

    async def bob() -> None:  # another browser, at the same time
        t = time.monotonic()
        r = await sign_in(page.port, "bob", bob_source, tls=tls)
        out["new_sign_in"] = (r.status, time.monotonic() - t)

    other = asyncio.ensure_future(bob())
    t = time.monotonic()
    r = await page.request("POST", "/login", body=form(name="ana", password=PASSWORDS["ana"]),
                           ctype="application/x-www-form-urlencoded", cookie=f"coex_device={device}")
    out["sign_in"] = (r.status, time.monotonic() - t)
    cookie = f"coex_session={r.cookies().get('coex_session', '')}"
    t = time.monotonic()
    r = await page.request("GET", "/api/whoami", cookie=cookie)
    csrf = json.loads(r.body).get("csrf", "") if r.status == 200 else ""
    r = await page.request("GET", "/api/state", cookie=cookie)
    out["state"] = (r.status, time.monotonic() - t)
    t = time.monotonic()
    r = await page.request("POST", "/api/action", cookie=cookie, ctype="application/json",
                           headers={"X-CSRF-Token": csrf},
                           body=json.dumps({"action": "queue_config", "args": {"stream": 3, "priority": 50}}).encode())
    out["action"] = (r.status, time.monotonic() - t)
    t = time.monotonic()
    r = await page.request("GET", "/map/0.png", cookie=cookie)
    out["picture"] = (r.status, time.monotonic() - t)
    await other
    return out


async def operator(port: int, device: str, tls: bool, rounds: int, every: float, until: float,
                   sample: Any) -> list[dict[str, Any]]:
    """``rounds`` warm-up rounds, then a round every ``every`` s until ``until`` (monotonic)."""
    page = KeepAlive(port, tls=tls)
    out = []
    try:
        for _ in range(rounds):
            await operator_round(page, device, "127.0.0.200", tls)
        n = 0
        while time.monotonic() < until - every / 2:
            n += 1
            start = time.monotonic()
            out.append(await operator_round(page, device, f"127.0.5.{n % 250 + 1}", tls))
            while time.monotonic() - start < every:
                sample()
                await asyncio.sleep(0.25)
    finally:
        page.close()
    return out


def run_flood(seconds: float = 20.0, every: float = 2.0, kinds: str = "idle,streams,windows,guessers,pollers",
              tls: bool = False, workdir: Path | None = None, settle: float = 12.0) -> dict[str, Any]:
    """Start a console, flood it for ``seconds`` while the operator acts every ``every`` s;
    returns the operator's rounds, what the attackers got and the console's RSS (before, the
    peak during, at the end, and after: once the console has gone quiet, at most ``settle``
    seconds later)."""
    tmp = tempfile.TemporaryDirectory() if workdir is None else None
    work = Path(tmp.name) if tmp is not None else Path(workdir)  # type: ignore[arg-type]
    phases = {"start": time.monotonic()}
    console = Console(work, tls=tls)
    phases["console up"] = time.monotonic()
    attacker = None
    try:
        device = asyncio.run(sign_in(console.port, "ana", tls=tls)).cookies()["coex_device"]  # before the dive
        asyncio.run(operator(console.port, device, tls, 2, every, 0.0, lambda: None))  # warm up
        rss_before = console.rss_mb()
        phases["warmed up"] = time.monotonic()
        attacker = subprocess.Popen([sys.executable, __file__, "attack", str(console.port), str(seconds), kinds]
                                    + (["--tls"] if tls else []), stdout=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        samples = [rss_before]
        sampling = threading.Event()

        def sample() -> None:
            while not sampling.wait(0.25):
                samples.append(console.rss_mb())

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        time.sleep(min(3.0, seconds / 4))  # the flood builds up
        rounds = asyncio.run(operator(console.port, device, tls, 0, every, t0 + seconds, lambda: None))
        out, _ = attacker.communicate(timeout=seconds + 120)
        counts = json.loads(out.strip().splitlines()[-1]) if out.strip() else {}
        phases["attack over"] = time.monotonic()
        sampling.set()
        sampler.join()
        peak = max(samples)
        rss_end = console.rss_mb()
        # idle sockets, streams and keep-alives end, the pictures and password checks queued
        # finish (on a loaded machine long after the attack: wait until the console is quiet),
        # then the upkeep gives memory back (at most ``settle`` seconds; sooner when it is back
        # within 10 MB of what it was before)
        quiet_after = console.wait_quiet()
        phases["console quiet"] = time.monotonic()
        end = time.monotonic() + settle
        rss_after = console.rss_mb()
        while time.monotonic() < end and rss_after > rss_before + 10:
            time.sleep(0.5)
            rss_after = console.rss_mb()
        phases["memory back"] = time.monotonic()
        return {"seconds": seconds, "kinds": kinds.split(","), "tls": tls, "rounds": rounds, "attackers": counts,
                "rss_mb": {"before": round(rss_before, 1), "peak_during": round(peak, 1),
                           "at_end": round(rss_end, 1), "after": round(rss_after, 1),
                           "quiet_after_seconds": round(quiet_after, 1),
                           "settle_seconds": round(phases["memory back"] - phases["console quiet"], 1)},
                "load_average": os.getloadavg(),
                "phases": {k: round(v - phases["start"], 1) for k, v in phases.items()}}
    finally:
        if attacker is not None and attacker.poll() is None:
            attacker.kill()
            attacker.wait()
        console.close()
        if tmp is not None:
            tmp.cleanup()


def worst(rounds: list[dict[str, Any]], what: str) -> tuple[list[int], float]:
    """The statuses of ``what`` over the rounds and its slowest answer (s)."""
    return [r[what][0] for r in rounds], max((r[what][1] for r in rounds), default=0.0)


# ------------------------------------------------------------------ idle sockets and memory
def idle_memory(n: int, tls: bool) -> dict[str, float]:
    """RSS of a console before, with and after ``n`` idle sockets (30 per address: none
    refused; beyond the 1024 connections allowed, the oldest idle ones make room)."""
    with tempfile.TemporaryDirectory() as d:
        console = Console(Path(d), tls=tls)
        try:
            time.sleep(1.0)
            before = console.rss_mb()
            socks = []
            peak = before
            for i in range(n):
                s = socket.socket()
                s.bind((f"127.0.{1 + i // 30 // 250}.{1 + (i // 30) % 250}", 0))
                s.connect(("127.0.0.1", console.port))
                socks.append(s)
                if i % 500 == 0:
                    peak = max(peak, console.rss_mb())
            time.sleep(2.0)
            peak = max(peak, console.rss_mb())
            for s in socks:
                s.close()
            time.sleep(3.0)
            closed = console.rss_mb()
            time.sleep(10.0)
            after = console.rss_mb()
            return {"sockets": n, "tls": tls, "before": round(before, 1), "peak_with_sockets": round(peak, 1),
                    "3s_after_close": round(closed, 1), "13s_after_close": round(after, 1)}
        finally:
            console.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--every", type=float, default=2.0)
    p.add_argument("--bound", type=float, default=3.0, help="seconds the operator's answers may take")
    p.add_argument("--idle-sockets", type=int, default=5000)
    p.add_argument("--quick", action="store_true", help="a 15 s flood and 1,000 idle sockets")
    p.add_argument("--tls", action="store_true", help="the flood over HTTPS")
    p.add_argument("--kinds", default="idle,streams,windows,guessers,pollers", help="the attacks to run")
    args = p.parse_args()
    if args.quick:
        args.seconds, args.idle_sockets = 15.0, 1000
    result: dict[str, Any] = {"load_average_at_start": os.getloadavg(), "cpus": os.cpu_count()}
    if args.idle_sockets:
        result["idle_sockets"] = [idle_memory(args.idle_sockets, tls) for tls in (False, True)]
        for r in result["idle_sockets"]:
            print(f"{r['sockets']} idle {'TLS' if r['tls'] else 'plain'} sockets: RSS {r['before']} MB before, "
                  f"{r['peak_with_sockets']} MB with them, {r['3s_after_close']} MB 3 s after they close, "
                  f"{r['13s_after_close']} MB 13 s after")
    flood = run_flood(args.seconds, args.every, kinds=args.kinds, tls=args.tls)
    result["flood"] = flood
    print(f"flood of {args.seconds:.0f} s ({', '.join(flood['kinds'])}{', TLS' if args.tls else ''}); "
          f"load average {flood['load_average'][0]:.1f}")
    ok = True
    for what in ("sign_in", "state", "action", "picture", "new_sign_in"):
        codes, slowest = worst(flood["rounds"], what)
        want = 303 if what in ("sign_in", "new_sign_in") else 200
        met = all(c == want for c in codes) and slowest <= args.bound
        if what in ("sign_in", "state", "action"):
            ok &= met
        print(f"  operator {what:12s} {len(codes)} times: answers {dict(Counter(codes))}, slowest {slowest:.2f} s"
              f"{'' if met else '  <-- NOT within the bound'}")
    for kind, counts in flood["attackers"].items():
        print(f"  attack {kind:9s} got {counts}")
    rss = flood["rss_mb"]
    print(f"  console RSS: {rss['before']} MB before, peak {rss['peak_during']} MB during, {rss['at_end']} MB at "
          f"the end, {rss['after']} MB {rss['settle_seconds']:.0f} s after it went quiet "
          f"({rss['quiet_after_seconds']:.0f} s after the end)")
    result["operator_within_bound"] = ok
    result["bound_seconds"] = args.bound
    out = ROOT / "bench" / "results" / "console_flood.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"operator served within {args.bound:g} s throughout: {ok}; written {out}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "serve":
        serve_main(sys.argv[2], "--tls" in sys.argv)
    elif len(sys.argv) > 1 and sys.argv[1] == "attack":
        attack_main(int(sys.argv[2]), float(sys.argv[3]), sys.argv[4], "--tls" in sys.argv)
    else:
        main()

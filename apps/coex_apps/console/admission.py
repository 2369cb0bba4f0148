"""Who gets in, and how much each may ask: the console's admission (docs/console.md, "The web
server"; issue 52).

The console is the door to a vehicle's thrusters: its operator must reach it whatever other
machines on the ship's network do. Everything here runs on the web server's one event loop, so
each check and the count it guards happen in one synchronous step (no ``await`` between them):
two requests arriving together cannot both pass a limit that only one fits.

* :class:`Doors`: the open connections, by client address. An address may hold at most
  ``connections_per_address`` connections (a trusted reverse proxy: ``connections``); all
  together at most ``connections``. A new connection beyond either limit takes the place of the
  oldest *idle* one (no request being answered: a keep-alive connection between requests, a
  request head still arriving, a TLS handshake) of the same address, or, the console being
  full, of the address holding the most; it is refused only when none is idle. A connection
  that carried an operator's request is never closed to make room. So idle or slow sockets,
  however many and however often re-opened, cost their sender its own places, never the
  operator's.
* :class:`Lanes`: requests being answered at once, per client address, per session and in all,
  with places kept for operators' sessions that viewers and anonymous clients cannot take; and
  the event streams alike (per session, per address, in all, with an operators' reserve).
* :class:`FairQueue`: work done in worker threads (pictures, password checks) queued per client
  and served in turn, one class before the next (an operator's pictures before a viewer's, a
  sign-in from a known browser before a stranger's), with bounded queues.
* :class:`Said`: refusals logged with the client address and the reason, a flood of them in one
  line per address and reason every ten seconds.
* :func:`trim_memory`: memory freed by closed connections, pictures and password checks is
  given back to the system (glibc keeps freed heap memory in its arenas otherwise).
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import functools
import logging
import os
import resource
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

from .state import MAP_WINDOW_CELLS

__all__ = ["Doors", "FairQueue", "Lanes", "Limits", "Said", "limit_arenas", "lower_priority", "raise_fd_limit",
           "trim_memory"]

log = logging.getLogger("coex_apps.console.server")


@dataclass(frozen=True)
class Limits:
    """What clients can make the console do (docs/console.md, "The web server").

    Connections and requests are counted per client address (with ``--trusted-proxy``, the
    address the proxy names) and per session; operators' sessions have places of their own."""

    #: open connections in all (event streams included); beyond, an idle one makes room
    connections: int = 1024
    #: open connections from one address (a trusted proxy: ``connections``)
    connections_per_address: int = 32
    #: seconds for a request's headers (and a TLS handshake) to arrive
    header_seconds: float = 10.0
    #: seconds an idle keep-alive connection stays open
    keep_alive_seconds: int = 5
    #: the largest request head (line and headers), bytes
    header_bytes: int = 16 * 1024
    #: the largest action body, bytes
    body_bytes: int = 64 * 1024
    #: seconds for a request's body to arrive once its head has (408 beyond)
    body_seconds: float = 10.0
    #: requests being answered at once for viewers and anonymous clients (503 beyond)
    requests: int = 128
    #: requests being answered at once for operators (their own places)
    operator_requests: int = 32
    #: requests being answered at once from one address (viewers and anonymous)
    requests_per_address: int = 16
    #: requests being answered at once for one session
    requests_per_session: int = 8
    #: pictures (map levels, map windows, images) drawn at once; more wait their turn
    renders: int = 2
    #: pictures waiting for viewers and anonymous clients; one more is refused (429)
    render_queue: int = 32
    #: pictures waiting for operators (their own places)
    operator_render_queue: int = 16
    #: pictures one session (without sign-in: one address) may have waiting or drawn
    renders_per_client: int = 6
    #: the largest map window, pixels
    window_pixels: int = MAP_WINDOW_CELLS
    #: event streams open at once, in all (429 beyond)
    streams: int = 64
    #: of ``streams``, the places only operators' sessions may take
    operator_streams: int = 16
    #: event streams of one session
    streams_per_session: int = 4
    #: event streams from one address
    streams_per_address: int = 8
    #: sign-ins waiting for a password check, per class (a known browser, an address without
    #: failures, the rest); one more is refused (429)
    sign_in_queue: tuple[int, int, int] = (16, 64, 32)


# ------------------------------------------------------------------ refusals, said once
class Said:
    """Log lines about clients, at most one per (address, kind) every ``every`` seconds: the
    first at once, the others counted and said in one line (``... and 250 more like it from
    127.0.0.2 in 10 s``). ``kind`` defaults to the text itself."""

    def __init__(self, every: float = 10.0, clock: Callable[[], float] = time.monotonic,
                 logger: logging.Logger = log, limit: int = 4096) -> None:
        self.every = every
        self.clock = clock
        self.log = logger
        self.limit = limit
        #: (address, kind) -> [first time, count since the line, level, text]
        self._open: OrderedDict[tuple[str, str], list[Any]] = OrderedDict()
        self._lock = threading.Lock()

    def __call__(self, address: str, text: str, level: int = logging.WARNING, kind: str | None = None) -> None:
        with self._lock:
            self._say(address, text, level, kind)

    def _say(self, address: str, text: str, level: int, kind: str | None) -> None:
        key = (address, text if kind is None else kind)
        now = self.clock()
        seen = self._open.get(key)
        if seen is not None and now - seen[0] >= self.every:
            self._flush_one(key, self._open.pop(key))
            seen = None
        if seen is None:
            self.log.log(level, "%s", text)
            self._open[key] = [now, 0, level, text]
            while len(self._open) > self.limit:  # a flood of distinct lines: say the oldest now
                self._flush_one(*self._open.popitem(last=False))
            return
        seen[1] += 1
        seen[3] = text

    def _flush_one(self, key: tuple[str, str], seen: list[Any]) -> None:
        if seen[1]:
            self.log.log(seen[2], "%s (and %d more like it from %s in %.0f s)", seen[3], seen[1], key[0],
                         max(self.clock() - seen[0], 0.0))

    def flush(self, force: bool = False) -> None:
        """Say the counts whose time has come (all of them with ``force``)."""
        now = self.clock()
        with self._lock:
            for key in [k for k, v in self._open.items() if force or now - v[0] >= self.every]:
                self._flush_one(key, self._open.pop(key))


# ------------------------------------------------------------------ connections
@dataclass(eq=False)
class Connection:
    """One admitted connection: its client address, and how to ask whether it is idle and to
    close it at once."""

    address: str
    port: int
    idle: Callable[[], bool]
    abort: Callable[[], None]
    opened: float = 0.0
    #: it carried a request of an operator's session: never closed to make room
    operator: bool = False
    #: counted in :class:`Doors` (False once released or evicted)
    open: bool = True


class Doors:
    """The connections open, by address (see the module's documentation). ``trusted(address)``
    is True for a reverse proxy's address (its connections carry many clients: only the total
    limits them). ``say`` logs refusals and evictions."""

    def __init__(self, limits: Limits, trusted: Callable[[str], bool] = lambda a: False,
                 say: Said | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self.total = max(1, limits.connections)
        self.trusted = trusted
        self.say = say or Said()
        self.clock = clock
        #: address -> (port -> connection), oldest first
        self.by_address: dict[str, dict[int, Connection]] = {}
        #: connections not marked operator, per address
        self.others: dict[str, int] = {}
        self.count = 0
        #: connections closed since :meth:`closed_since` was last asked (for :func:`trim_memory`)
        self.closed = 0
        self.refused = 0
        self.evicted = 0

    def admit(self, address: str, port: int, idle: Callable[[], bool],
              abort: Callable[[], None]) -> Connection | None:
        """A new connection from ``address``: its :class:`Connection` (room made if needed), or
        None when it is refused (then the caller closes it)."""
        group = self.by_address.get(address)
        cap = self.total if self.trusted(address) else max(1, self.limits.connections_per_address)
        if group is not None and self.others.get(address, 0) >= cap:
            victim = self._idle_in(group.values())
            if victim is None:
                self.refused += 1
                self.say(address, f"console refused a connection from {address}: {cap} connections "
                                  "from this address are busy already")
                return None
            self._evict(victim, f"console closed an idle connection from {address} to make room: "
                                f"{cap} connections from one address at most")
        if self.count >= self.total:
            victim = self._room()
            if victim is None:
                self.refused += 1
                self.say(address, f"console refused a connection from {address}: all {self.total} "
                                  "connections are busy")
                return None
            self._evict(victim, f"console closed an idle connection from {victim.address} to make room "
                                f"for {address}: {self.total} connections open at most")
        c = Connection(address, port, idle, abort, self.clock())
        self.by_address.setdefault(address, {})[port] = c
        self.others[address] = self.others.get(address, 0) + 1
        self.count += 1
        return c

    def _idle_in(self, conns: Iterable[Connection]) -> Connection | None:
        for c in conns:  # oldest first
            if not c.operator and c.idle():
                return c
        return None

    def _room(self) -> Connection | None:
        """The connection to close when the console is full: the oldest idle one of the
        address holding the most, else any idle one."""
        for address, _ in sorted(self.others.items(), key=lambda kv: -kv[1]):
            victim = self._idle_in(self.by_address.get(address, {}).values())
            if victim is not None:
                return victim
        return None

    def _evict(self, c: Connection, why: str) -> None:
        self.evicted += 1
        self.release(c)
        self.say(c.address, why, logging.INFO, kind="evicted")
        try:
            c.abort()
        except Exception:  # a transport already gone
            pass

    def release(self, c: Connection | None) -> None:
        """A connection closed (its count is given back once)."""
        if c is None or not c.open:
            return
        c.open = False
        group = self.by_address.get(c.address)
        if group is not None and group.get(c.port) is c:
            del group[c.port]
            if not group:
                del self.by_address[c.address]
        if not c.operator:
            n = self.others.get(c.address, 0) - 1
            if n > 0:
                self.others[c.address] = n
            else:
                self.others.pop(c.address, None)
        self.count -= 1
        self.closed += 1

    def find(self, address: str, port: int) -> Connection | None:
        group = self.by_address.get(address)
        return group.get(port) if group is not None else None

    def mark_operator(self, address: str, port: int) -> None:
        """The connection carried an operator's request: it is kept (and no longer counted
        against its address's limit)."""
        c = self.find(address, port)
        if c is not None and c.open and not c.operator:
            c.operator = True
            n = self.others.get(address, 0) - 1
            if n > 0:
                self.others[address] = n
            else:
                self.others.pop(address, None)

    def abort_all(self) -> None:
        for group in list(self.by_address.values()):
            for c in list(group.values()):
                self.release(c)
                try:
                    c.abort()
                except Exception:
                    pass


# ------------------------------------------------------------------ requests and streams
class _Counts:
    """Named counters with caps, taken and given back together."""

    def __init__(self) -> None:
        self.n: dict[tuple[str, str], int] = {}

    def get(self, kind: str, key: str) -> int:
        return self.n.get((kind, key), 0)

    def take(self, wanted: list[tuple[str, str, int, str]]) -> str | None:
        """``wanted``: (kind, key, cap, reason if full). None when every counter had room and
        was raised; else the first full one's reason (nothing raised)."""
        for kind, key, cap, why in wanted:
            if self.n.get((kind, key), 0) >= cap:
                return why
        for kind, key, _, _ in wanted:
            self.n[(kind, key)] = self.n.get((kind, key), 0) + 1
        return None

    def give(self, keys: Iterable[tuple[str, str]]) -> None:
        for k in keys:
            n = self.n.get(k, 0) - 1
            if n > 0:
                self.n[k] = n
            else:
                self.n.pop(k, None)


@dataclass(eq=False)
class Ticket:
    """Places taken in :class:`Lanes`; :meth:`release` gives them back (once)."""

    counts: _Counts
    keys: list[tuple[str, str]] = field(default_factory=list)

    def release(self) -> None:
        keys, self.keys = self.keys, []
        self.counts.give(keys)


class Lanes:
    """Requests being answered and event streams open, per address, per session and in all;
    an operator's session has places of its own (see :class:`Limits`). A session's key is its
    id (without sign-in: the client address)."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.counts = _Counts()

    def request(self, operator: bool, address: str, session: str | None) -> Ticket | str:
        """Places for one request: a :class:`Ticket`, or why there is none."""
        lim = self.limits
        wanted: list[tuple[str, str, int, str]] = []
        if operator:
            wanted.append(("req", "operator", lim.operator_requests,
                           f"{lim.operator_requests} operators' requests are being answered"))
        else:
            wanted.append(("req", "other", lim.requests, f"{lim.requests} requests are being answered"))
            wanted.append(("req-addr", address, lim.requests_per_address,
                           f"{lim.requests_per_address} requests from this address are being answered"))
        if session:
            wanted.append(("req-session", session, lim.requests_per_session,
                           f"{lim.requests_per_session} requests of this session are being answered"))
        why = self.counts.take(wanted)
        if why is not None:
            return why
        return Ticket(self.counts, [(k, key) for k, key, _, _ in wanted])

    def stream(self, operator: bool, address: str, session: str | None) -> Ticket | str:
        """Places for one event stream: a :class:`Ticket`, or why there is none (``session``
        None: a console without sign-in, where everyone is the operator)."""
        lim = self.limits
        others = max(0, lim.streams - lim.operator_streams)
        wanted: list[tuple[str, str, int, str]] = [
            ("streams", "all", lim.streams if operator else others,
             f"{self.counts.get('streams', 'all')} event streams are open already (at most "
             f"{lim.streams if operator else others}"
             f"{'' if operator else f', {lim.operator_streams} more kept for operators'})")]
        if session:
            wanted.append(("stream-session", session, lim.streams_per_session,
                           f"this session has {lim.streams_per_session} event streams open already (close a tab)"))
        if not operator:
            wanted.append(("stream-addr", address, lim.streams_per_address,
                           f"{lim.streams_per_address} event streams are open from this address already"))
        why = self.counts.take(wanted)
        if why is not None:
            return why
        return Ticket(self.counts, [(k, key) for k, key, _, _ in wanted])


# ------------------------------------------------------------------ fair work in threads
class Busy(Exception):
    """A :class:`FairQueue` has no room for one more job of that client or class."""


class _Job:
    __slots__ = ("args", "client", "fn", "future", "klass")

    def __init__(self, fn: Callable[..., Any], args: tuple[Any, ...], future: asyncio.Future[Any],
                 client: str, klass: int) -> None:
        self.fn, self.args, self.future, self.client, self.klass = fn, args, future, client, klass


class FairQueue:
    """At most ``running`` jobs at once; the others wait in class order (class 0 first) and,
    within a class, client by client in turn (a client with many jobs waiting does not delay
    another's first). ``waiting[k]`` jobs of class ``k`` may wait; ``per_client`` jobs of one
    client may wait or run. Beyond, :class:`Busy` (with the reason). Classes before ``low``
    run in ``executors[0]`` and may take every running place; the classes from ``low`` on run
    in ``executors[-1]`` and leave ``reserved`` places to the others (whose jobs then start at
    once, never behind theirs)."""

    def __init__(self, executors: Executor | list[Executor], running: int, waiting: tuple[int, ...],
                 per_client: int, what: str, reserved: int = 0, low: int = 1) -> None:
        self.executors = list(executors) if isinstance(executors, list) else [executors]
        self.running_max = max(1, running)
        self.low = max(1, low)
        #: running places the classes from ``low`` on may take
        self.others_max = max(1, self.running_max - max(0, reserved))
        self.waiting_max = tuple(max(0, w) for w in waiting)
        self.per_client = max(1, per_client)
        self.what = what
        #: per class: client -> its jobs waiting (clients in turn order)
        self.rings: list[OrderedDict[str, deque[_Job]]] = [OrderedDict() for _ in waiting]
        self.waiting = [0] * len(waiting)
        self.of_client: dict[str, int] = {}
        self.running = 0
        self.running_others = 0
        #: jobs done since :func:`trim_memory` last looked
        self.done = 0

    async def run(self, fn: Callable[..., Any], *args: Any, client: str, klass: int = 0) -> Any:
        klass = min(max(klass, 0), len(self.rings) - 1)
        if self.of_client.get(client, 0) >= self.per_client:
            raise Busy(f"{self.per_client} {self.what} of yours are waiting or being made: try again")
        if self.running >= self.running_max and self.waiting[klass] >= self.waiting_max[klass]:
            raise Busy(f"the console is busy making {self.running + sum(self.waiting)} {self.what}: try again")
        loop = asyncio.get_running_loop()
        job = _Job(fn, args, loop.create_future(), client, klass)
        self.of_client[client] = self.of_client.get(client, 0) + 1
        ring = self.rings[klass]
        ring.setdefault(client, deque()).append(job)
        self.waiting[klass] += 1
        self._dispatch()
        try:
            return await job.future
        except asyncio.CancelledError:
            self._forget(job)
            raise

    def _forget(self, job: _Job) -> None:
        """A job whose requester left: taken out if it has not started."""
        jobs = self.rings[job.klass].get(job.client)
        if jobs is not None and job in jobs:
            jobs.remove(job)
            if not jobs:
                del self.rings[job.klass][job.client]
            self.waiting[job.klass] -= 1
            self._done_with(job.client)

    def _done_with(self, client: str) -> None:
        n = self.of_client.get(client, 0) - 1
        if n > 0:
            self.of_client[client] = n
        else:
            self.of_client.pop(client, None)

    def _next(self) -> _Job | None:
        for klass, ring in enumerate(self.rings):
            if not ring or (klass >= self.low and self.running_others >= self.others_max):
                continue
            client, jobs = next(iter(ring.items()))
            job = jobs.popleft()
            del ring[client]
            if jobs:
                ring[client] = jobs  # to the back: the next client goes first
            self.waiting[klass] -= 1
            return job
        return None

    def _dispatch(self) -> None:
        loop = asyncio.get_running_loop()
        while self.running < self.running_max:
            job = self._next()
            if job is None:
                return
            self.running += 1
            if job.klass >= self.low:
                self.running_others += 1
            pool = self.executors[0] if job.klass < self.low else self.executors[-1]
            done = loop.run_in_executor(pool, job.fn, *job.args)
            done.add_done_callback(functools.partial(self._finished, job))

    def _finished(self, job: _Job, f: asyncio.Future[Any]) -> None:
        self.running -= 1
        if job.klass >= self.low:
            self.running_others -= 1
        self.done += 1
        self._done_with(job.client)
        if not job.future.done():
            if f.cancelled():
                job.future.cancel()
            elif f.exception() is not None:
                job.future.set_exception(f.exception())  # type: ignore[arg-type]
            else:
                job.future.set_result(f.result())
        elif not f.cancelled():
            f.exception()  # retrieved: nobody waits for it any more
        self._dispatch()


def lower_priority(niceness: int = 10) -> None:
    """Make the calling thread yield the processor to the others (Linux: threads have their own
    nice value): the heavy work of viewers and strangers (their pictures, their password
    checks) gives way to the web server's loop and the operator's work. A no-op elsewhere."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    except (AttributeError, OSError):
        pass


# ------------------------------------------------------------------ memory and descriptors
_libc: Any = None


def _glibc() -> Any:
    """The C library's ``malloc_trim`` and ``mallopt`` (glibc), or None."""
    global _libc
    if _libc is None:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            lib.malloc_trim.argtypes = [ctypes.c_size_t]
            lib.malloc_trim.restype = ctypes.c_int
            lib.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
            lib.mallopt.restype = ctypes.c_int
            _libc = lib
        except (OSError, AttributeError):
            _libc = False
    return _libc or None


def trim_memory() -> bool:
    """Give freed heap memory back to the system (glibc ``malloc_trim(0)``, all arenas). True
    if it ran (False where the C library has no ``malloc_trim``)."""
    lib = _glibc()
    if lib is None:
        return False
    lib.malloc_trim(0)
    return True


#: glibc's ``mallopt`` parameter for the number of malloc arenas
M_ARENA_MAX = -8


def limit_arenas(n: int = 2) -> bool:
    """At most ``n`` malloc arenas in this process (glibc ``mallopt(M_ARENA_MAX)``). glibc
    gives threads arenas of their own (up to eight per processor), each keeping what it freed:
    the console's worker threads drawing pictures and checking passwords held some 100 MB
    after a flood; with two arenas the memory goes back. True if set."""
    lib = _glibc()
    if lib is None:
        return False
    return bool(lib.mallopt(M_ARENA_MAX, max(1, n)))


def raise_fd_limit(want: int) -> int:
    """Raise this process's soft limit of open files towards ``want`` (never above the hard
    limit); returns the soft limit now."""
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (OSError, ValueError):
        return want
    if soft != resource.RLIM_INFINITY and soft < want:
        new = want if hard == resource.RLIM_INFINITY else min(want, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
            soft = new
        except (OSError, ValueError):
            pass
    return int(soft) if soft != resource.RLIM_INFINITY else want

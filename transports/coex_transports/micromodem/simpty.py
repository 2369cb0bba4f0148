"""The modems of a :class:`~.simnetwork.ModemNetwork` served on pseudo-terminals and TCP ports in
real time: what ``coex modem-sim`` runs (see :mod:`.simulator`)."""

from __future__ import annotations

import errno
import os
import selectors
import socket
import threading
import time
import tty
from collections.abc import Callable
from typing import Any

from coex_core.errors import ConfigError

from .simnetwork import ModemNetwork

__all__ = ['PtySimulator']

class PtySimulator:
    """Serve a :class:`ModemNetwork`'s modems on pseudo-terminals (and optional TCP ports).

    ``speed`` scales simulated time (2.0 = twice as fast as real time). The simulated clock
    starts at the real UTC time. Use :meth:`start` (background thread) and :meth:`stop`, or
    :meth:`serve_forever` in the foreground.
    """

    def __init__(
        self, network: ModemNetwork, *, tcp_ports: dict[int, int] | None = None, speed: float = 1.0,
        host: str = "127.0.0.1",
    ) -> None:
        if speed <= 0:
            raise ConfigError("speed must be positive")
        self.network = network
        self.speed = float(speed)
        self._sel = selectors.DefaultSelector()
        self._masters: dict[int, int] = {}
        self._slaves: dict[int, int] = {}
        self.paths: dict[int, str] = {}
        self.tcp_addresses: dict[int, tuple[str, int]] = {}
        self._listeners: dict[int, socket.socket] = {}
        self._clients: dict[int, list[socket.socket]] = {}
        self._pending: dict[int, bytearray] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        for node in network.modems:
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._masters[node] = master
            self._slaves[node] = slave
            self.paths[node] = os.ttyname(slave)
            self._pending[node] = bytearray()
            self._clients[node] = []
            self._sel.register(master, selectors.EVENT_READ, ("pty", node))
        for node, port in (tcp_ports or {}).items():
            if node not in network.modems:
                raise ConfigError(f"no modem {node} for TCP port {port}")
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind((host, port))
            srv.listen(4)
            srv.setblocking(False)
            self._listeners[node] = srv
            self.tcp_addresses[node] = srv.getsockname()[:2]
            self._sel.register(srv, selectors.EVENT_READ, ("listen", node))
        self._t0 = time.monotonic()
        self._epoch = time.time()
        network.clock.advance_to(self._epoch)
        self._epoch = network.clock.now

    def sim_now(self) -> float:
        return self._epoch + (time.monotonic() - self._t0) * self.speed

    def call(self, fn: Callable[[ModemNetwork], Any]) -> Any:
        """Run ``fn(network)`` on the simulation, safely from another thread."""
        with self._lock:
            return fn(self.network)

    def start(self) -> None:
        self._thread = threading.Thread(target=self.serve_forever, name="coex-modem-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self.close()

    def close(self) -> None:
        for fd in [*self._masters.values(), *self._slaves.values()]:
            try:
                os.close(fd)
            except OSError:
                pass
        self._masters.clear()
        self._slaves.clear()
        for s in [*self._listeners.values(), *(c for cs in self._clients.values() for c in cs)]:
            s.close()
        self._listeners.clear()
        self._clients.clear()
        self._sel.close()

    def serve_forever(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                now = self.sim_now()
                self.network.run_until(max(now, self.network.clock.now))
                self._flush_out()
                nxt = self.network.next_event()
            wait = 0.05 if nxt is None else min(0.05, max(0.0, (nxt - now) / self.speed))
            try:
                events = self._sel.select(timeout=wait)
            except (OSError, ValueError):
                break
            with self._lock:
                now = max(self.sim_now(), self.network.clock.now)
                for key, _ in events:
                    kind, node = key.data
                    if kind == "listen":
                        self._accept(node)
                    elif kind == "pty":
                        self._read_pty(node, now)
                    else:
                        self._read_client(key.fileobj, node, now)  # type: ignore[arg-type]

    def _accept(self, node: int) -> None:
        try:
            conn, _ = self._listeners[node].accept()
        except OSError:
            return
        conn.setblocking(False)
        self._clients[node].append(conn)
        self._sel.register(conn, selectors.EVENT_READ, ("tcp", node))

    def _read_pty(self, node: int, now: float) -> None:
        try:
            data = os.read(self._masters[node], 4096)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EIO):
                return
            raise
        if data:
            self.network.modems[node].feed(data, now)

    def _read_client(self, conn: socket.socket, node: int, now: float) -> None:
        try:
            data = conn.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._sel.unregister(conn)
            self._clients[node].remove(conn)
            conn.close()
            return
        self.network.modems[node].feed(data, now)

    def _flush_out(self) -> None:
        for node, modem in self.network.modems.items():
            out = modem.data_to_send()
            if out:
                for c in list(self._clients[node]):
                    try:
                        c.sendall(out)
                    except OSError:
                        pass
                buf = self._pending[node]
                buf += out
                if len(buf) > 1 << 16:
                    del buf[: len(buf) - (1 << 16)]  # nobody reads this pty: keep the newest
            buf = self._pending[node]
            if buf:
                try:
                    n = os.write(self._masters[node], bytes(buf))
                    del buf[:n]
                except OSError as exc:
                    if exc.errno not in (errno.EAGAIN, errno.EIO):
                        raise

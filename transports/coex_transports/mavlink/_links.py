"""Byte carriers under the MAVLink transport: UDP out/in, TCP client/server, serial (pyserial).

Each link moves raw MAVLink bytes; it knows nothing of MAVLink or CoEx. ``read(timeout)`` returns
one received chunk as ``(data, is_datagram)`` or ``None`` when nothing arrived in time.
"""

from __future__ import annotations

import abc
import select
import selectors
import socket
import sys
from collections import OrderedDict
from typing import Any

from coex_core.errors import ConfigError, LinkDown, TransportError

__all__ = ["Link", "SerialLink", "TcpClientLink", "TcpServerLink", "UdpInLink", "UdpOutLink"]

_RCVBUF = 1 << 20
_MAX_DATAGRAM = 65535
_MAX_PEERS = 8


class Link(abc.ABC):
    """A duplex byte carrier."""

    datagram = False

    @abc.abstractmethod
    def write(self, packet: bytes) -> None:
        """Send one MAVLink packet (raises :class:`TransportError` on failure)."""

    def can_write(self) -> bool:
        """Whether a write has somewhere to go (a UDP server before any peer spoke has not)."""
        return True

    @abc.abstractmethod
    def read(self, timeout: float | None) -> bytes | None:
        """Bytes received within ``timeout`` seconds (``None`` blocks), or ``None``."""

    def flush(self) -> None:  # noqa: B027 - most links have nothing buffered
        """Push buffered output to the wire."""

    @abc.abstractmethod
    def close(self) -> None: ...

    def describe(self) -> str:
        return type(self).__name__


def _resolve(host: str, port: int) -> tuple[str, int]:
    try:
        info = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except socket.gaierror as exc:
        raise ConfigError(f"cannot resolve host {host!r}: {exc}") from None
    addr = info[0][4]
    return str(addr[0]), int(addr[1])


class _SocketLink(Link):
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.sock.setblocking(False)
        self.sel = selectors.DefaultSelector()
        self.sel.register(sock, selectors.EVENT_READ)

    def _wait(self, timeout: float | None) -> bool:
        return bool(self.sel.select(None if timeout is None else max(0.0, timeout)))

    def close(self) -> None:
        self.sel.close()
        self.sock.close()


class UdpOutLink(_SocketLink):
    """``udpout:HOST:PORT``: send every packet to HOST:PORT; accept datagrams from anyone."""

    datagram = True

    def __init__(self, host: str, port: int) -> None:
        self.remote = _resolve(host, port)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
            sock.bind(("0.0.0.0", 0))
        except OSError as exc:
            sock.close()
            raise TransportError(f"udpout: cannot open a UDP socket: {exc}") from exc
        super().__init__(sock)

    def write(self, packet: bytes) -> None:
        try:
            self.sock.sendto(packet, self.remote)
        except ConnectionRefusedError:
            pass  # ICMP port unreachable from an earlier datagram: UDP is connectionless
        except OSError as exc:
            raise TransportError(f"udpout {self.remote[0]}:{self.remote[1]}: {exc}") from exc

    def read(self, timeout: float | None) -> bytes | None:
        while True:
            try:
                data, _ = self.sock.recvfrom(_MAX_DATAGRAM)
                return data
            except (BlockingIOError, InterruptedError):
                pass
            except ConnectionRefusedError:
                continue  # reported for an earlier send; nothing to read
            except OSError as exc:
                raise TransportError(f"udpout: receive failed: {exc}") from exc
            if not self._wait(timeout):
                return None
            timeout = 0.0 if timeout is not None else None

    def describe(self) -> str:
        return f"udpout:{self.remote[0]}:{self.remote[1]}"


class UdpInLink(_SocketLink):
    """``udpin:HOST:PORT``: listen on HOST:PORT; send to every peer heard from (most recent 8)."""

    datagram = True

    def __init__(self, host: str, port: int) -> None:
        local = _resolve(host, port)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF)
            sock.bind(local)
        except OSError as exc:
            sock.close()
            raise TransportError(f"udpin: cannot listen on {local[0]}:{local[1]}: {exc}") from exc
        super().__init__(sock)
        self.local = sock.getsockname()
        self.peers: OrderedDict[tuple[str, int], None] = OrderedDict()

    def can_write(self) -> bool:
        return bool(self.peers)

    def write(self, packet: bytes) -> None:
        if not self.peers:
            raise LinkDown(  # not a failure: the link is there, waiting for a peer to speak
                f"udpin {self.local[0]}:{self.local[1]}: no peer has sent anything yet, nowhere to send"
            )
        for peer in list(self.peers):
            try:
                self.sock.sendto(packet, peer)
            except ConnectionRefusedError:
                self.peers.pop(peer, None)
            except OSError as exc:
                raise TransportError(f"udpin: send to {peer[0]}:{peer[1]} failed: {exc}") from exc

    def read(self, timeout: float | None) -> bytes | None:
        while True:
            try:
                data, peer = self.sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                if not self._wait(timeout):
                    return None
                timeout = 0.0 if timeout is not None else None
                continue
            except ConnectionRefusedError:
                continue
            except OSError as exc:
                raise TransportError(f"udpin: receive failed: {exc}") from exc
            key = (str(peer[0]), int(peer[1]))
            self.peers.pop(key, None)
            self.peers[key] = None
            while len(self.peers) > _MAX_PEERS:
                self.peers.popitem(last=False)
            return data

    def describe(self) -> str:
        return f"udpin:{self.local[0]}:{self.local[1]}"


class TcpClientLink(_SocketLink):
    """``tcp:HOST:PORT``: a TCP client (MAVProxy, mavlink-router and SITL listen on TCP)."""

    def __init__(self, host: str, port: int, connect_timeout: float = 5.0) -> None:
        try:
            sock = socket.create_connection((host, port), timeout=connect_timeout)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            raise TransportError(f"tcp: cannot connect to {host}:{port}: {exc}") from exc
        super().__init__(sock)
        self.remote = (host, port)

    def write(self, packet: bytes) -> None:
        self.sock.setblocking(True)
        try:
            self.sock.sendall(packet)
        except OSError as exc:
            raise TransportError(f"tcp {self.remote[0]}:{self.remote[1]}: send failed: {exc}") from exc
        finally:
            self.sock.setblocking(False)

    def read(self, timeout: float | None) -> bytes | None:
        if not self._wait(timeout):
            return None
        try:
            data = self.sock.recv(_MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError as exc:
            raise TransportError(f"tcp {self.remote[0]}:{self.remote[1]}: receive failed: {exc}") from exc
        if not data:
            raise TransportError(f"tcp {self.remote[0]}:{self.remote[1]}: connection closed by peer")
        return data

    def describe(self) -> str:
        return f"tcp:{self.remote[0]}:{self.remote[1]}"


class TcpServerLink(Link):
    """``tcpin:HOST:PORT``: a TCP server; sends to every connected client, reads from all."""

    def __init__(self, host: str, port: int) -> None:
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.server.bind((host, port))
            self.server.listen(4)
        except OSError as exc:
            self.server.close()
            raise TransportError(f"tcpin: cannot listen on {host}:{port}: {exc}") from exc
        self.server.setblocking(False)
        self.local = self.server.getsockname()
        self.sel = selectors.DefaultSelector()
        self.sel.register(self.server, selectors.EVENT_READ, "server")
        self.clients: list[socket.socket] = []

    def can_write(self) -> bool:
        self._accept()
        return bool(self.clients)

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                raise TransportError(f"tcpin: accept failed: {exc}") from exc
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.setblocking(False)
            self.clients.append(conn)
            self.sel.register(conn, selectors.EVENT_READ, "client")

    def _drop(self, conn: socket.socket) -> None:
        if conn in self.clients:
            self.clients.remove(conn)
            self.sel.unregister(conn)
        conn.close()

    def write(self, packet: bytes) -> None:
        self._accept()
        if not self.clients:
            raise LinkDown(f"tcpin {self.local[0]}:{self.local[1]}: no client connected")
        for conn in list(self.clients):
            conn.setblocking(True)
            try:
                conn.sendall(packet)
            except OSError:
                self._drop(conn)
            else:
                conn.setblocking(False)
        if not self.clients:
            raise LinkDown(f"tcpin {self.local[0]}:{self.local[1]}: every client disconnected")

    def read(self, timeout: float | None) -> bytes | None:
        events: list[Any] = self.sel.select(None if timeout is None else max(0.0, timeout))
        for key, _ in events:
            if key.data == "server":
                self._accept()
                continue
            conn = key.fileobj
            assert isinstance(conn, socket.socket)
            try:
                data = conn.recv(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                self._drop(conn)
                continue
            if not data:
                self._drop(conn)
                continue
            return data
        return None

    def close(self) -> None:
        for conn in list(self.clients):
            self._drop(conn)
        self.sel.close()
        self.server.close()

    def describe(self) -> str:
        return f"tcpin:{self.local[0]}:{self.local[1]}"


class SerialLink(Link):
    """``serial:DEVICE[:BAUD]`` through pyserial (any ``serial_for_url`` URL works as DEVICE)."""

    def __init__(self, device: str, baud: int) -> None:
        try:
            import serial
        except ImportError as exc:  # pragma: no cover - pyserial ships with the mavlink extra
            raise ConfigError("the serial link needs pyserial: pip install pyserial") from exc
        self._serial_exception = serial.SerialException
        try:
            self.port = serial.serial_for_url(device, baudrate=baud, timeout=0, write_timeout=5.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"serial: cannot open {device} at {baud} Bd: {exc}") from exc
        self.device = device
        self.baud = baud
        # a real port (POSIX) is waited on with select, so the port is never reconfigured per
        # read; pyserial URL handlers without a descriptor use pyserial's own timeout instead
        self._fd: int | None = None
        if sys.platform != "win32":
            try:
                self._fd = int(self.port.fileno())
            except (AttributeError, OSError, ValueError, TypeError):
                self._fd = None

    def write(self, packet: bytes) -> None:
        try:
            self.port.write(packet)
        except (self._serial_exception, OSError) as exc:
            raise TransportError(f"serial {self.device}: write failed: {exc}") from exc

    def read(self, timeout: float | None) -> bytes | None:
        try:
            if self._fd is not None:
                ready, _, _ = select.select([self._fd], [], [], None if timeout is None else max(0.0, timeout))
                if not ready:
                    return None
                data = self.port.read(max(1, self.port.in_waiting))  # the port has timeout=0
                return bytes(data) if data else None
            self.port.timeout = timeout
            data = self.port.read(1)
            if not data:
                return None
            waiting = self.port.in_waiting
            if waiting:
                self.port.timeout = 0
                data += self.port.read(waiting)
        except (self._serial_exception, OSError) as exc:
            raise TransportError(f"serial {self.device}: read failed: {exc}") from exc
        return bytes(data)

    def flush(self) -> None:
        try:
            self.port.flush()
        except (self._serial_exception, OSError) as exc:
            raise TransportError(f"serial {self.device}: flush failed: {exc}") from exc

    def close(self) -> None:
        self.port.close()

    def describe(self) -> str:
        return f"serial:{self.device}:{self.baud}"

"""``MicromodemTransport``: the CoEx transport over a WHOI Micromodem's NMEA serial interface.

URIs (query options below)::

    micromodem:///dev/ttyUSB0?baud=19200&src=1&rate=5
    micromodem:socket://192.168.1.20:4001?src=2&dest=1
    micromodem:rfc2217://host:port   (any pyserial URL: loop://, spy://, ...)

Options: ``baud`` (19200), ``src`` (1), ``dest`` (0), ``rate`` (5), ``mode`` (``cycle`` or
``fdp``), ``ack`` (0), ``link`` (0, the link id in LinkStatus), ``firmware`` (``mm2`` or ``mm1``),
``base64`` (0), ``clock`` (1: set the modem clock at startup), ``reset`` (0: ``$CCCFG,ALL,0``
first), ``nvram`` (extra settings, ``NAME:VALUE`` joined by ``;``), ``keepalive`` (10 s),
``reply_timeout`` (2 s), ``retries`` (3), ``tx_timeout`` (60 s), ``max_attempts`` (3).

A background thread reads the port, runs the sans-I/O :class:`~.driver.MicromodemDriver` and
writes its sentences, so ``$CADRQ`` is answered promptly whatever the caller does. The MTU is the
frame size of the configured rate (256 B at rate 5). :meth:`send` queues one frame (queued frames
share packets); :meth:`send_packet` queues one multi-frame packet; :meth:`flush` waits until every
queued frame has left; :meth:`recv` returns received frames; :meth:`stats` and
:meth:`link_status` give the link statistics.

:meth:`MicromodemTransport.simulated` (or :meth:`.simulator.ModemNetwork.transport`) runs the
same driver against an in-process simulated modem on a simulated clock instead.
"""

from __future__ import annotations

import abc
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from coex_core.errors import ConfigError, TransportError, TransportTimeout
from coex_core.messages import LinkStatus
from coex_core.transport import Transport, UriInfo, parse_query

from .driver import DriverConfig, Event, MicromodemDriver

__all__ = ["MicromodemTransport", "parse_uri"]

_OPTIONS: dict[str, type] = {
    "baud": int, "src": int, "dest": int, "rate": int, "mode": str, "ack": bool, "link": int,
    "firmware": str, "base64": bool, "clock": bool, "reset": bool, "nvram": str, "keepalive": float,
    "reply_timeout": float, "retries": int, "tx_timeout": float, "max_attempts": int,
}


def parse_uri(uri: str) -> tuple[str, int, DriverConfig]:
    """Split a ``micromodem:`` URI into (pyserial port or URL, baud rate, driver config)."""
    if not uri.startswith("micromodem:"):
        raise ConfigError(f"not a micromodem URI: {uri!r}")
    rest = uri[len("micromodem:"):]
    query = ""
    if "?" in rest:
        rest, query = rest.split("?", 1)
    if rest.startswith("///"):
        port = rest[2:]  # micromodem:///dev/ttyUSB0 -> /dev/ttyUSB0
    else:
        port = rest
    if not port:
        raise ConfigError(f"no serial port in {uri!r}")
    opts = parse_query(query, _OPTIONS)
    baud = opts.pop("baud", 19200)
    nvram: list[tuple[str, str]] = []
    for item in filter(None, opts.pop("nvram", "").split(";")):
        name, sep, value = item.partition(":")
        if not sep or not name:
            raise ConfigError(f"nvram item {item!r} is not NAME:VALUE")
        nvram.append((name, value))
    mapping = {"clock": "set_clock", "reset": "reset_nvram"}
    kwargs = {mapping.get(k, k): v for k, v in opts.items()}
    return port, baud, DriverConfig(nvram=tuple(nvram), **kwargs)


def check_serial_url(url: str) -> None:
    """Parse a pyserial URL (``socket://host:port``, ``rfc2217://host:port``, ``loop://`` ...)
    with pyserial's own handler, without opening it; :class:`ConfigError` if it does not parse."""
    try:
        import serial
    except ImportError:  # pragma: no cover - the extra's dependency
        return
    try:
        handler = serial.serial_for_url(url, do_not_open=True)
        from_url = getattr(handler, "from_url", None)  # what the handler's open() parses first
        if callable(from_url):
            from_url(url)
    except (serial.SerialException, ValueError, TypeError) as exc:  # TypeError: socket:// without a port
        raise ConfigError(f"{url!r} is not a serial URL pyserial can open: "
                          f"{exc if not isinstance(exc, TypeError) else 'expected HOST:PORT'}") from None


class _Backend(abc.ABC):
    """How the driver meets its modem: a serial port on a thread, or a simulated network."""

    lock: Any

    def wake(self) -> None:
        """Let a waiter re-check its condition (nothing to do by default)."""
        return None

    @abc.abstractmethod
    def wait(self, ready: Callable[[], bool], timeout: float | None) -> bool:
        """Wait until ``ready()`` or ``timeout``; return ``ready()``."""

    def close(self) -> None:
        """Release the modem (nothing to do by default)."""
        return None

    def check(self) -> None:
        """Raise if the backend has failed (never, by default)."""
        return None


class _SerialBackend(_Backend):
    def __init__(self, driver: MicromodemDriver, port: Any) -> None:
        self.driver = driver
        self.port = port
        self.lock = threading.Condition()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        with self.lock:
            driver.start(time.time())
        self._thread = threading.Thread(target=self._run, name="coex-micromodem", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        port, driver = self.port, self.driver
        try:
            while not self._stop.is_set():
                with self.lock:
                    out = driver.data_to_send()
                if out:
                    port.write(out)
                waiting = getattr(port, "in_waiting", 0) or 1
                data = port.read(min(waiting, 4096))
                with self.lock:
                    now = time.time()
                    if data:
                        driver.feed(data, now)
                    driver.poll(now)
                    self.lock.notify_all()
        except Exception as exc:  # the port failed (unplugged, closed): report it to the caller
            if not self._stop.is_set():
                with self.lock:
                    self.error = exc
                    self.lock.notify_all()

    def check(self) -> None:
        if self.error is not None:
            raise TransportError(f"serial port failed: {self.error}") from self.error

    def wake(self) -> None:
        with self.lock:
            self.driver.poll(time.time())

    def wait(self, ready: Callable[[], bool], timeout: float | None) -> bool:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.lock:
            while not ready():
                self.check()
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self.lock.wait(0.1 if left is None else min(left, 0.1))
            return True

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        try:
            self.port.close()
        except Exception:
            pass


class _SimBackend(_Backend):
    """Single-threaded: waiting advances the network's simulated clock."""

    def __init__(self, driver: MicromodemDriver, network: Any, node: int) -> None:
        self.driver = driver
        self.network = network
        self.node = node
        self.lock = threading.RLock()
        self._closed = False
        network.attach(node, driver)
        driver.start(network.now)

    def wake(self) -> None:
        # nothing to do: the driver starts the packet at the next network step, so frames sent
        # back to back share a packet
        return

    def check(self) -> None:
        # the simulated cable was pulled (ModemNetwork.unplug): dead until closed and reopened
        if not self._closed and not self.network.attached(self.driver):
            raise TransportError(f"serial port failed: simulated modem {self.node} unplugged")

    def close(self) -> None:
        self._closed = True
        self.network.detach(self.driver)

    def wait(self, ready: Callable[[], bool], timeout: float | None) -> bool:
        if timeout is None:
            # nothing else can happen in a single-threaded simulation once the network is quiet
            self.network.run_while(lambda: not ready() and self.network.busy(), 1e9)
            return bool(ready())
        return bool(self.network.run_while(lambda: not ready(), timeout))


class MicromodemTransport(Transport):
    """CoEx frames over a WHOI Micromodem (see the module docstring)."""

    scheme = "micromodem"

    def __init__(self, driver: MicromodemDriver, backend: _Backend) -> None:
        super().__init__(driver.mtu)
        self.driver = driver
        self._backend = backend

    # ------------------------------------------------------------------------ creation
    @classmethod
    def from_uri(cls, uri: str) -> MicromodemTransport:
        port, baud, config = parse_uri(uri)
        return cls.open(port, config, baudrate=baud)

    @classmethod
    def check_uri(cls, uri: str) -> UriInfo:
        """The URI's options through :func:`parse_uri` (the driver's own checks), and a pyserial
        URL (``socket://``, ``rfc2217://`` ...) through pyserial's own URL parser, opening
        nothing; a device path is listed in ``paths``."""
        port, baud, config = parse_uri(uri)
        if baud <= 0:
            raise ConfigError(f"{uri!r}: baud must be positive, got {baud}")
        if "://" in port:
            check_serial_url(port)
            paths: tuple[str, ...] = ()
        else:
            paths = (port,)
        return UriInfo(uri, config.mtu, paths, config.rate, src=config.src, dest=config.dest)

    @classmethod
    def open(cls, port: str, config: DriverConfig | None = None, *, baudrate: int = 19200) -> MicromodemTransport:
        """Open a serial device path or pyserial URL and start the driver on it."""
        try:
            import serial
        except ImportError as exc:  # pragma: no cover - pyserial is the extra's dependency
            raise TransportError("the micromodem transport needs pyserial: pip install 'coexploration[micromodem]'") from exc
        try:
            ser = serial.serial_for_url(port, baudrate=baudrate, timeout=0.05, do_not_open=True)
            try:
                ser.rts = False  # Micromodem-2 output is garbled with RTS asserted and no flow control
            except Exception:
                pass
            ser.open()
        except (serial.SerialException, ValueError, OSError) as exc:
            raise TransportError(f"cannot open {port!r}: {exc}") from exc
        driver = MicromodemDriver(config or DriverConfig())
        return cls(driver, _SerialBackend(driver, ser))

    @classmethod
    def on_port(cls, port: Any, config: DriverConfig | None = None) -> MicromodemTransport:
        """Run the driver on an already open pyserial-like object (``read``/``write``/``close``)."""
        driver = MicromodemDriver(config or DriverConfig())
        return cls(driver, _SerialBackend(driver, port))

    @classmethod
    def simulated(cls, network: Any, node: int, **options: Any) -> MicromodemTransport:
        """The driver on ``node``'s modem of a :class:`~.simulator.ModemNetwork` (simulated time)."""
        options.setdefault("src", node)
        driver = MicromodemDriver(DriverConfig(**options))
        return cls(driver, _SimBackend(driver, network, node))

    # ---------------------------------------------------------------------- transport API
    def _send_internal(self, frame: bytes) -> None:
        self._backend.check()
        with self._backend.lock:
            self.driver.send_frame(frame)
        self._backend.wake()

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        self._backend.check()
        if timeout is not None and timeout < 0:
            timeout = 0.0
        got = self._backend.wait(lambda: self.driver.pending_received() > 0, timeout)
        if not got:
            return None
        with self._backend.lock:
            frame = self.driver.receive()
        return None if frame is None else frame.data

    def _close_internal(self) -> None:
        self._backend.close()

    def send_packet(self, frames: Sequence[bytes], rate: int | None = None, *, dest: int | None = None,
                    ack: bool | None = None) -> None:
        """Queue one packet of several frames at ``rate`` (default: the configured rate)."""
        if self.closed:
            raise TransportError("transport is closed")
        self._backend.check()
        with self._backend.lock:
            self.driver.send_packet(frames, rate, dest=dest, ack=ack)
        self._backend.wake()

    def ping(self, dest: int) -> None:
        """Two-way ping; the travel time shows up in :meth:`stats` (``last_owtt``) and :meth:`events`."""
        with self._backend.lock:
            self.driver.ping(dest, 0.0)
        self._backend.wake()

    def flush(self, timeout: float | None = 120.0) -> None:
        """Wait until every queued frame has left. Raises :class:`TransportTimeout` if frames are
        still queued after ``timeout`` seconds, and :class:`TransportError` if packets failed for
        good meanwhile (their frames are in :class:`~.driver.TxFailed` events)."""
        with self._backend.lock:
            failed_before = self.driver.failed_count
        if not self._backend.wait(lambda: self.driver.idle and self.driver.ready, timeout):
            raise TransportTimeout(f"frames still queued after {timeout} s")
        with self._backend.lock:
            failed = self.driver.failed_count - failed_before
            reason = self.driver.stats()["last_error"]
        if failed:
            raise TransportError(f"{failed} packet(s) could not be sent: {reason}")

    def wait_ready(self, timeout: float | None = 30.0) -> bool:
        """Wait for the end of the modem startup sequence."""
        return self._backend.wait(lambda: self.driver.ready, timeout)

    def stats(self) -> dict[str, Any]:
        with self._backend.lock:
            return self.driver.stats()

    def link_status(self) -> LinkStatus | None:
        """The latest receive statistics as a :class:`~coex_core.messages.LinkStatus` for topside."""
        with self._backend.lock:
            return self.driver.link_status()

    def events(self) -> list[Event]:
        """Take the driver events since the last call (frames, TxDone/TxFailed, acks, pings, ...)."""
        with self._backend.lock:
            out = list(self.driver.events)
            self.driver.events.clear()
        return out

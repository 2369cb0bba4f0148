"""``LcmTransport``: CoEx frames as ``coex.frame_t`` messages on LCM channels.

URI: ``lcm:<LCM provider URL>`` with CoEx options mixed into the provider's query, e.g.
``lcm:udpm://239.255.76.67:7667?ttl=0&channel=COEX`` or
``lcm:udpm://239.255.76.67:7667?ttl=0&tx=COEX_UP&rx=COEX_DOWN``. CoEx options (removed before the
URL reaches LCM):

``channel``  channel for both directions (default ``COEX``)
``tx``/``rx``  channel to publish on / to subscribe to (override ``channel``)
``mtu``      largest frame accepted by :meth:`send` (default 65536)
``share``    share one LCM instance with every end opened in this process with the same provider
             URL and share name (``memq://`` ends always share one, since memq is private to an
             instance)
``queue``    frames buffered per end before the oldest is dropped and counted (default 4096)
``decoded``  ``1`` to also publish ``coex.vehicle_status_t`` (channel ``COEX_VEHICLE_STATUS``) and
             ``coex.map_level_t`` (``COEX_MAP_LEVEL``) for every received frame, for LCM tools

Every other option (``ttl``, ``recv_buf_size``, ``speed``, ``mode`` ...) goes to LCM unchanged.
An empty provider (``lcm:``) means ``udpm://239.255.76.67:7667?ttl=0``; ``LCM_DEFAULT_URL`` is
never consulted.

An end ignores frames it published itself (each ``frame_t`` carries a random per-end
``origin``), so two ends may use one channel in both directions. Messages on the receive
channel that are not valid ``frame_t`` are counted in :meth:`LcmTransport.stats` (``bad``) and
logged, never returned.
"""

from __future__ import annotations

import ipaddress
import logging
import re
import secrets
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar
from urllib.parse import parse_qsl, urlencode, urlsplit

import lcm

from coex_core.errors import ConfigError, DecodeError, TransportError
from coex_core.transport import Transport, UriInfo

from ._codec import decode_frame, encode_frame

__all__ = ["DEFAULT_URL", "LcmConfig", "LcmTransport", "check_provider_url", "parse_lcm_uri"]

log = logging.getLogger(__name__)

DEFAULT_URL = "udpm://239.255.76.67:7667?ttl=0"
_MAX_CHANNEL = 63  # LCM_MAX_CHANNEL_NAME_LENGTH
_OPTIONS: dict[str, type] = {
    "channel": str, "tx": str, "rx": str, "mtu": int, "share": str, "queue": int, "decoded": bool,
}
#: the options each LCM provider takes (LCM itself only warns about others, and runs on without
#: them: a misspelt option must not pass silently)
PROVIDER_OPTIONS: dict[str, frozenset[str]] = {
    "udpm": frozenset({"ttl", "recv_buf_size", "transmit_only"}),
    "mpudpm": frozenset({"ttl", "recv_buf_size", "transmit_only", "nports"}),
    "file": frozenset({"speed", "mode", "start_timestamp"}),
    "memq": frozenset(),
    "tcpq": frozenset(),
}


@dataclass(frozen=True)
class LcmConfig:
    """Configuration of one :class:`LcmTransport` end."""

    #: LCM provider URL (``udpm://...``, ``memq://``, ``file://...``, ``tcpq://...``)
    url: str = DEFAULT_URL
    #: channel this end publishes frames on
    tx: str = "COEX"
    #: channel this end receives frames from
    rx: str = "COEX"
    #: largest frame :meth:`LcmTransport.send` accepts, bytes
    mtu: int = 65536
    #: share one LCM instance with other ends of this process opened with the same URL and name
    share: str | None = None
    #: frames buffered before the oldest is dropped (and counted)
    queue: int = 4096
    #: also publish decoded products of received frames: ``coex.vehicle_status_t`` on
    #: ``COEX_VEHICLE_STATUS`` and ``coex.map_level_t`` on ``COEX_MAP_LEVEL`` (for LCM tools)
    decoded: bool = False

    def __post_init__(self) -> None:
        for name in ("tx", "rx"):
            channel = getattr(self, name)
            if not channel or len(channel) > _MAX_CHANNEL:
                raise ConfigError(f"{name} channel must have 1..{_MAX_CHANNEL} characters, got {channel!r}")
        if self.mtu <= 0:
            raise ConfigError(f"mtu must be positive, got {self.mtu}")
        if self.queue <= 0:
            raise ConfigError(f"queue must be positive, got {self.queue}")
        if "://" not in self.url:
            raise ConfigError(f"not an LCM provider URL: {self.url!r}")

    @property
    def provider(self) -> str:
        """The provider name (``udpm``, ``memq``, ``file`` ...)."""
        return self.url.split("://", 1)[0]

    def swapped(self) -> LcmConfig:
        """The configuration of the other end: ``tx`` and ``rx`` exchanged."""
        return replace(self, tx=self.rx, rx=self.tx)


def check_provider_url(url: str) -> None:
    """An LCM provider URL's address, port and options as LCM will need them when it opens
    (:class:`ConfigError` naming what is wrong): LCM's own library only prints "Bad multicast
    port" and fails to open, which a daemon would retry for ever. ``udpm``/``mpudpm``: an IPv4
    multicast group (224.0.0.0/4), a port 1..65535, ``ttl`` 0..255; ``tcpq``: a host and a port
    1..65535; every provider: only its own options (:data:`PROVIDER_OPTIONS`)."""
    why = _provider_problem(url)
    if why is not None:
        raise ConfigError(f"{url!r}: {why}")


def _provider_problem(url: str) -> str | None:
    """What is wrong with an LCM provider URL (:func:`check_provider_url`), or None."""
    if "://" not in url:
        return f"not an LCM provider URL (e.g. {DEFAULT_URL})"
    parts = urlsplit(url)
    provider = parts.scheme
    if provider not in PROVIDER_OPTIONS:
        return f"unknown LCM provider {provider!r} (known: {', '.join(sorted(PROVIDER_OPTIONS))})"
    for key, _ in parse_qsl(parts.query, keep_blank_values=True):
        if key not in PROVIDER_OPTIONS[provider]:
            return (f"unknown option {key!r} ({provider} options: "
                    f"{', '.join(sorted(PROVIDER_OPTIONS[provider])) or 'none'})")
    if provider not in ("udpm", "mpudpm", "tcpq"):
        return None
    try:
        port = parts.port
    except ValueError:
        return f"the port must be 1..65535, got {parts.netloc.rpartition(':')[2]!r}"
    if port == 0:
        return "the port must be 1..65535, got 0"
    host = parts.hostname or ""
    if provider == "tcpq":
        return None if host else "tcpq needs a host and a port, e.g. tcpq://localhost:7700"
    multicast = "an IPv4 multicast address (224.0.0.0 to 239.255.255.255; LCM's default 239.255.76.67)"
    if host:
        try:
            group = ipaddress.ip_address(host)
        except ValueError:
            return f"{host!r} is not {multicast}"
        if group.version != 4 or not group.is_multicast:
            return f"{host} is not {multicast}"
    ttl = dict(parse_qsl(parts.query)).get("ttl")
    if ttl is not None and not (ttl.isdigit() and 0 <= int(ttl) <= 255):
        return f"ttl must be 0..255 (0: this computer only), got {ttl!r}"
    return None


def parse_lcm_uri(uri: str) -> LcmConfig:
    """Parse ``lcm:<provider URL>[?options]`` into an :class:`LcmConfig`."""
    if not uri.startswith("lcm:"):
        raise ConfigError(f"not an lcm URI: {uri!r}")
    rest = uri[len("lcm:"):]
    if rest.startswith("//") and "://" not in rest[2:]:  # "lcm://?channel=X" = default provider
        rest = rest[2:]
    if not rest or rest.startswith("?"):
        rest = DEFAULT_URL + ("&" + rest[1:] if rest.startswith("?") and rest[1:] else "")
    if "://" not in rest:
        raise ConfigError(f"{uri!r}: expected lcm:<provider>://..., e.g. lcm:{DEFAULT_URL}")
    parts = urlsplit(rest)
    ours: dict[str, Any] = {}
    theirs: list[tuple[str, str]] = []
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key in _OPTIONS:
            try:
                if _OPTIONS[key] is bool:
                    if value.lower() not in ("1", "0", "true", "false", "yes", "no"):
                        raise ValueError(value)
                    ours[key] = value.lower() in ("1", "true", "yes")
                else:
                    ours[key] = _OPTIONS[key](value)
            except ValueError:
                raise ConfigError(f"option {key}={value!r} is not a valid {_OPTIONS[key].__name__}") from None
        else:
            theirs.append((key, value))
    provider = parts.scheme
    if provider not in PROVIDER_OPTIONS:
        raise ConfigError(f"{uri!r}: unknown LCM provider {provider!r} (known: {', '.join(sorted(PROVIDER_OPTIONS))})")
    allowed = PROVIDER_OPTIONS[provider]
    for key, _ in theirs:
        if key not in allowed:
            raise ConfigError(
                f"{uri!r}: unknown option {key!r} (CoEx options: {', '.join(sorted(_OPTIONS))}; "
                f"{provider} options: {', '.join(sorted(allowed)) or 'none'})")
    query = urlencode(theirs, safe="/:")
    url = f"{parts.scheme}://{parts.netloc}{parts.path}" + (f"?{query}" if query else "")
    why = _provider_problem(url)
    if why is not None:
        raise ConfigError(f"{uri!r}: {why}")
    channel = ours.pop("channel", "COEX")
    return LcmConfig(
        url=url,
        tx=ours.pop("tx", channel),
        rx=ours.pop("rx", channel),
        mtu=ours.pop("mtu", 65536),
        share=ours.pop("share", None),
        queue=ours.pop("queue", 4096),
        decoded=ours.pop("decoded", False),
    )


@dataclass
class _Instance:
    """One ``lcm.LCM`` shared by the ends of this process that asked for it."""

    lcm: Any  # lcm.LCM, None once released
    key: tuple[str, str] | None
    users: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)
    exhausted: bool = False  # a file:// provider reached the end of its log


class LcmTransport(Transport):
    """One end of a CoEx link over LCM (see the module documentation for the URI)."""

    scheme = "lcm"
    _shared: ClassVar[dict[tuple[str, str], _Instance]] = {}
    _shared_lock: ClassVar[threading.Lock] = threading.Lock()

    def __init__(self, config: LcmConfig | None = None, *, instance: lcm.LCM | None = None) -> None:
        """Open an end; ``instance`` uses an existing ``lcm.LCM`` (the caller keeps owning it)."""
        self.config = config or LcmConfig()
        super().__init__(self.config.mtu)
        self.origin = secrets.randbits(63)
        self._queue: deque[bytes] = deque()
        self._counts = {"sent": 0, "received": 0, "own": 0, "bad": 0, "dropped": 0}
        if self.config.decoded:
            self._counts.update(decoded=0, undecodable=0)
        self._maps: Any = None  # MapLevelSummary of the decoded channels, created on first use
        self._inst = self._acquire(instance)
        try:
            # LCM subscribes by regular expression: escape it, rx is one exact channel name
            self._subscription = self._inst.lcm.subscribe(re.escape(self.config.rx), self._on_message)
            self._subscription.set_queue_capacity(max(self.config.queue, 30))
        except Exception:
            self._release()
            raise

    @classmethod
    def check_uri(cls, uri: str) -> UriInfo:
        """The URI through :func:`parse_lcm_uri` (every option known, by name), opening nothing;
        a ``file://`` log read back (mode ``r``, LCM's default) is listed in ``paths``."""
        cfg = parse_lcm_uri(uri)
        paths: tuple[str, ...] = ()
        if cfg.provider == "file":
            parts = urlsplit(cfg.url)
            mode = dict(parse_qsl(parts.query)).get("mode", "r")
            if mode == "r":
                paths = (parts.netloc + parts.path,)
        return UriInfo(uri, cfg.mtu, paths)

    # ------------------------------------------------------------------ instances
    def _acquire(self, instance: lcm.LCM | None) -> _Instance:
        if instance is not None:
            inst = _Instance(instance, None)
            inst.users = 1
            self._owns_lcm = False
            return inst
        self._owns_lcm = True
        share = self.config.share
        if share is None and self.config.provider == "memq":
            share = ""  # memq is private to an instance: ends of one process must share it
        if share is None:
            inst = _Instance(self._new_lcm(), None)
            inst.users = 1
            return inst
        key = (self.config.url, share)
        with self._shared_lock:
            shared = self._shared.get(key)
            if shared is None:
                shared = _Instance(self._new_lcm(), key)
                self._shared[key] = shared
            shared.users += 1
            return shared

    def _new_lcm(self) -> lcm.LCM:
        try:
            return lcm.LCM(self.config.url)
        except (RuntimeError, OSError) as exc:
            hint = ""
            if self.config.provider == "udpm":
                hint = " (udpm needs a multicast route, e.g. `ip route add 224.0.0.0/4 dev lo`)"
            raise TransportError(f"cannot open LCM {self.config.url!r}: {exc}{hint}") from exc

    def _release(self) -> None:
        inst = self._inst
        with self._shared_lock:
            inst.users -= 1
            last = inst.users <= 0
            if last and inst.key is not None:
                self._shared.pop(inst.key, None)
        if last and self._owns_lcm:
            inst.lcm = None  # lcm.LCM has no close(); dropping the last reference frees it

    # ------------------------------------------------------------------ transport
    def _on_message(self, channel: str, data: bytes) -> None:
        """LCM callback: queue a valid frame of another end; count and log anything else."""
        try:
            frame = decode_frame(data)
        except DecodeError as exc:
            self._counts["bad"] += 1
            log.warning("ignoring a bad message on LCM channel %s: %s", channel, exc)
            return
        if frame.origin == self.origin:
            self._counts["own"] += 1
            return
        if len(self._queue) >= self.config.queue:
            self._queue.popleft()
            self._counts["dropped"] += 1
            log.warning("LCM end on %s: receive queue full, dropped the oldest frame", channel)
        self._queue.append(frame.data)
        self._counts["received"] += 1
        if self.config.decoded:
            self._publish_decoded(frame.data)

    def _publish_decoded(self, data: bytes) -> None:
        """Publish the decoded types of one received frame (never disturbs frame delivery)."""
        from coex_core.messages import SubgridMessage, VehicleStatus
        from coex_core.wire import unpack

        from .products import (
            MAP_LEVEL_CHANNEL,
            VEHICLE_STATUS_CHANNEL,
            MapLevelSummary,
            vehicle_status_to_lcm,
        )

        try:
            messages = unpack(data)
        except DecodeError as exc:
            self._counts["undecodable"] += 1
            log.debug("frame not decodable for the decoded channels: %s", exc)
            return
        utime = time.time_ns() // 1000
        levels: set[int] = set()
        try:
            for message in messages:
                if isinstance(message, VehicleStatus):
                    self._inst.lcm.publish(VEHICLE_STATUS_CHANNEL, vehicle_status_to_lcm(message, utime).encode())
                    self._counts["decoded"] += 1
                elif isinstance(message, SubgridMessage):
                    if self._maps is None:
                        self._maps = MapLevelSummary()
                    levels.add(self._maps.add(message))
            for level in sorted(levels):
                assert self._maps is not None
                self._inst.lcm.publish(MAP_LEVEL_CHANNEL, self._maps.summary(level, utime).encode())
                self._counts["decoded"] += 1
        except Exception as exc:  # a decoded side channel must never cost a frame
            log.warning("publishing decoded products failed: %s", exc)

    def _send_internal(self, frame: bytes) -> None:
        data = encode_frame(frame, utime=time.time_ns() // 1000, origin=self.origin)
        try:
            self._inst.lcm.publish(self.config.tx, data)
        except (OSError, RuntimeError, ValueError) as exc:
            raise TransportError(f"LCM publish on {self.config.tx} failed: {exc}") from exc
        self._counts["sent"] += 1

    def _recv_internal(self, timeout: float | None) -> bytes | None:
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        first = True
        while True:
            if self._queue:
                return self._queue.popleft()
            if self._inst.exhausted:
                return None
            if deadline is None:
                wait_ms = 1000
            else:
                left = deadline - time.monotonic()
                if left <= 0 and not first:
                    return None
                wait_ms = max(0, min(1000, int(left * 1000)))  # 0: dispatch what is already there
            first = False
            self._handle(wait_ms)

    def _handle(self, wait_ms: int) -> None:
        inst = self._inst
        # one thread at a time dispatches a shared instance; the others wait their turn briefly
        if not inst.lock.acquire(timeout=wait_ms / 1000):
            return
        try:
            inst.lcm.handle_timeout(wait_ms)
        except OSError as exc:
            if self.config.provider == "file":
                inst.exhausted = True  # lcm_handle_timeout() returns -1 at the end of a log
                return
            raise TransportError(f"LCM receive failed: {exc}") from exc
        finally:
            inst.lock.release()

    def _close_internal(self) -> None:
        try:
            self._inst.lcm.unsubscribe(self._subscription)
        except Exception as exc:  # an instance that failed must still close
            log.debug("LCM unsubscribe failed: %s", exc)
        self._release()
        self._queue.clear()

    # ------------------------------------------------------------------ extras
    def fileno(self) -> int:
        """File descriptor that becomes readable when LCM has data (for ``select`` loops)."""
        if self.closed:
            raise TransportError("transport is closed")
        return int(self._inst.lcm.fileno())

    def pending(self) -> int:
        """Frames received and not yet returned by :meth:`recv`."""
        return len(self._queue)

    def stats(self) -> Mapping[str, Any]:
        """``sent``, ``received``, ``own`` (own frames ignored), ``bad`` (not a valid frame_t),
        ``dropped`` (receive queue overflow), the channels and the provider URL."""
        return {**self._counts, "tx": self.config.tx, "rx": self.config.rx, "url": self.config.url}

    @classmethod
    def from_uri(cls, uri: str) -> LcmTransport:
        return cls(parse_lcm_uri(uri))

    @classmethod
    def pair(cls, config: LcmConfig | None = None) -> tuple[LcmTransport, LcmTransport]:
        """Two connected ends on one shared LCM instance: ``a`` with ``config`` (default
        ``memq://``, ``tx=COEX_UP``, ``rx=COEX_DOWN``) and ``b`` with ``tx``/``rx`` swapped."""
        cfg = config or LcmConfig(url="memq://", tx="COEX_UP", rx="COEX_DOWN")
        cfg = replace(cfg, share=cfg.share if cfg.share is not None else f"pair-{secrets.token_hex(6)}")
        a = cls(cfg)
        try:
            b = cls(cfg.swapped())
        except Exception:
            a.close()
            raise
        return a, b

"""The channel manager: streams, the priority contest, packing, pulls, acks, TDMA, links.

Sans-I/O: every method takes ``now`` (float seconds, the shared clock of the deployment or a
simulated one). The only time source besides ``now`` is the optional ``clock`` callable the
caller passes in to measure how long modality senders take while a packet is built.

See ``docs/channel.md`` for the design (ack scheme, schedule switching, watchdog).

The class is assembled from one part per concern, each in its own module, each building on the
one before: :mod:`.links` (configuration and state), :mod:`.streams` (queues and entries),
:mod:`.tdma` (links, slots, schedule switches, watchdog), :mod:`.acks` (frame acks and
re-sends), :mod:`.packing` (the contest, sender pulls, frames), :mod:`.commands` (applying and
tracking commands), :mod:`.settings` (operator settings); the API is this class's.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from ..auth import CommandSigner, CommandVerifier, is_command
from ..errors import ConfigError
from ..messages import Message
from ..state import persistent
from ..tracker import State, Tracked
from .delivery import delivery_fields, peer_fields
from .events import Event
from .links import (
    CONTROL_STREAM,
    QUEUE_STATUS_STREAM,
    STATUS_STREAM,
    LinkConfig,
    Transmission,
    _Link,
    _Stream,
    default_streams,
)
from .policy import LOW_THROUGHPUT, NORMAL_THROUGHPUT, policy_fields
from .queue import StreamConfig
from .settings import SettingsMixin

__all__ = [
    "CONTROL_STREAM",
    "QUEUE_STATUS_STREAM",
    "STATUS_STREAM",
    "ChannelManager",
    "LinkConfig",
    "Transmission",
    "default_streams",
]


def _upgrade_manager(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (CoEx 0.1) had no delivery tracking, no loss estimates and no spare turns;
    version 2 no link-following policy; version 3 kept its commands awaiting an answer as bare
    messages (now the core tracker's entries, :mod:`coex_core.tracker`) and had no per-peer
    bookkeeping (a network of several nodes: frame destinations, per-peer loss and last heard,
    command destinations)."""
    if saved < 4:
        fields["_commands"] = {cid: c if isinstance(c, Tracked) else Tracked(c, State.SENT, None, 1)
                               for cid, c in dict(fields.get("_commands") or {}).items()}
        for k, v in peer_fields().items():
            fields.setdefault(k, v)
        fields.setdefault("_command_dst", {})
    if saved < 3:
        for k, v in policy_fields().items():
            fields.setdefault(k, v)
    if saved < 2:
        for k, v in delivery_fields().items():
            fields.setdefault(k, v)
        fields.setdefault("_spare_turn", {})
        stats = fields.setdefault("stats", {})
        for k in ("delivered", "lost", "spare_bytes", "redundant_bytes"):
            stats.setdefault(k, 0)
    return fields


#: the clock, the command test and the key holders come from the node it is restored into
@persistent("channel.ChannelManager", version=4, upgrade=_upgrade_manager,
            transient=("clock", "is_command", "signer", "verifier", "peer_signers", "peer_verifiers"))
class ChannelManager(SettingsMixin):
    """Queues, packing, TDMA and links of one node (vehicle or topside).

    ``clock`` (optional, e.g. ``time.perf_counter`` passed in by the runner) measures sender
    fill time: a sender slower than ``sender_budget`` seconds, or any sender once the packet has
    spent ``fill_budget`` seconds, is "no data" for the rest of that packet.
    ``queue_status_interval`` (s) makes the node send a :class:`QueueStatus` that often
    (``None``: never).
    ``command_key`` (at least 16 bytes, shared by topside and vehicle) turns on command
    authentication (spec section 10): frames this node sends that carry commands end with an
    ``AuthTrailer`` (13 bytes reserved while packing), signed by :attr:`signer`; the node checks
    received frames with :attr:`verifier`. Both counters are part of :meth:`export_settings`.
    ``peer_keys`` (a network of several nodes: peer node id -> the key this node shares with
    that peer alone) signs and checks the frames addressed to or coming from that peer (not
    broadcasts) with that key, each under its own counters (:attr:`peer_signers`,
    :attr:`peer_verifiers`); ``command_key`` is then the network key, for broadcast frames.
    """

    #: counters a restarted signer skips (frames it may have signed after its last save)
    COUNTER_MARGIN = 1024

    def __init__(
        self,
        node_id: int,
        links: Sequence[LinkConfig],
        streams: Iterable[StreamConfig] = (),
        *,
        clock: Callable[[], float] | None = None,
        fill_budget: float = 1.0,
        sender_budget: float = 0.25,
        queue_status_interval: float | None = None,
        ack_frames: bool = True,
        idle_interval: float = 1.0,
        command_key: bytes | None = None,
        peer_keys: Mapping[int, bytes] | None = None,
        low_throughput: float = LOW_THROUGHPUT,
        normal_throughput: float = NORMAL_THROUGHPUT,
    ) -> None:
        if not 1 <= node_id <= 15:
            raise ConfigError(f"node id {node_id} outside 1..15")
        if not links:
            raise ConfigError("a channel manager needs at least one link")
        self.node_id = node_id
        self.clock = clock
        self.fill_budget = float(fill_budget)
        self.sender_budget = float(sender_budget)
        self.queue_status_interval = queue_status_interval
        self.ack_frames = ack_frames
        self.idle_interval = float(idle_interval)
        self.signer = CommandSigner(command_key) if command_key is not None else None
        self.verifier = CommandVerifier(command_key) if command_key is not None else None
        if peer_keys and command_key is None:
            raise ConfigError("peer_keys need a command_key (the network key, for broadcast commands)")
        for peer in peer_keys or {}:
            if not 1 <= peer <= 15 or peer == node_id:
                raise ConfigError(f"peer key for {peer}: not another node's id 1..15")
        #: peer -> the signer and the verifier of the key shared with that peer alone
        self.peer_signers: dict[int, CommandSigner] = {p: CommandSigner(k) for p, k in (peer_keys or {}).items()}
        self.peer_verifiers: dict[int, CommandVerifier] = {
            p: CommandVerifier(k) for p, k in (peer_keys or {}).items()}
        #: which messages are commands (signed when sent, verified when received); the node
        #: extends it with its modalities' request types
        self.is_command: Callable[[Message], bool] = is_command
        self._links: dict[int, _Link] = {}
        for cfg in links:
            if cfg.link in self._links:
                raise ConfigError(f"link {cfg.link} configured twice")
            self._links[cfg.link] = _Link(cfg, cfg.schedule, cfg.enabled, cfg.muted, spare=cfg.spare)
        self._streams: dict[int, _Stream] = {}
        self._defaults: dict[int, StreamConfig] = {}
        given = {s.stream: s for s in streams}
        for s in default_streams():
            given.setdefault(s.stream, s)
        for sid in sorted(given):
            self.add_stream(given[sid])
        self._entry_ids = 0
        self._build_no = 0
        self._events: list[Event] = []
        #: (src, link) -> {seq: when received} of the frames to acknowledge
        self._to_ack: dict[tuple[int, int], dict[int, float]] = {}
        self._ack_times: dict[tuple[int, int, int], float] = {}  # of the acks being packed
        self._last_qs: float | None = None
        self._command_id = 0
        #: topside: sent commands awaiting their final CommandAck (the core tracker's entries)
        self._commands: dict[int, Tracked[Message]] = {}
        #: command id -> the node it was sent to (0: every node, None: the link's dst)
        self._command_dst: dict[int, int | None] = {}
        self.stats: dict[str, int] = {"packets": 0, "frames": 0, "used_bytes": 0, "capacity": 0,
                                      "acked": 0, "resent": 0, "sender_failures": 0,
                                      "signed": 0, "stale_acks": 0, "delivered": 0, "lost": 0,
                                      "spare_bytes": 0, "redundant_bytes": 0}
        self.sender_failures_by_stream: dict[str, int] = {}
        self._delivery_state()
        #: stream -> when its sender last gave spare work (the spare tier takes turns)
        self._spare_turn: dict[int, float] = {}
        if not 0.0 <= low_throughput <= normal_throughput:
            raise ConfigError("low_throughput must be >= 0 and at most normal_throughput")
        self._policy_state()
        #: the policy's thresholds (bytes per second, docs/channel.md)
        self.low_throughput = float(low_throughput)
        self.normal_throughput = float(normal_throughput)

    def _after_restore(self) -> None:
        """Loaded from saved state: no clock and no keys until the node it is restored into
        gives its own (:meth:`coex_core.node.Node.restore_state`)."""
        self.clock = None
        self.is_command = is_command
        self.signer = self.verifier = None
        self.peer_signers, self.peer_verifiers = {}, {}

    # ============================================================================ events
    def events(self) -> list[Event]:
        out, self._events = self._events, []
        return out

    def fill_ratio(self) -> float:
        """Useful (message) bytes / offered bytes over every packet built so far."""
        cap = self.stats["capacity"]
        return self.stats["used_bytes"] / cap if cap else 0.0

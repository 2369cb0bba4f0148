"""A sans-I/O CoEx node: a channel manager plus modality senders (subsea) and/or receivers
(topside), with routing of received messages by type.

Use::

    node = Node(manager)
    node.add_sender(ImageryModality, sender, StreamConfig(5, "images", priority=30))   # subsea
    node.add_receiver(ImageryModality, receiver)                                       # topside
    node.receive(link_id, frame_bytes, now)      # never raises for bad bytes
    for tx in node.poll(now): ...                # Transmission(link_id, rate, frames, ...)
    node.events()                                # products, acks, command results, bad frames

Routing of a received message: frame acks and command acks go to the manager; channel
commands (QueueConfig, ScheduleUpdate, LinkControl) are applied and answered with a
CommandAck; a type in some ``Modality.requests`` goes to that modality's sender (requests with a
``command_id`` get a CommandAck: ACCEPTED, or REJECTED when the sender raises
``RequestRejected``) and, unless the modality declares it ``routine`` (acks of data),
expedites the modality's stream so the answer leaves in the next transmission; a type in some
``Modality.messages`` goes to that modality's receiver; the rest (vehicle, queue and link
status ...) is reported as a :class:`Received` event. Modalities are found by the wire type
ids they declare (built-in types, and third-party ids: :mod:`coex_core.routing`); a node
refuses two modalities that claim one id.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from .auth import ReplayError, is_command
from .channel.events import (
    BadFrame,
    CommandResult,
    Event,
    LinkStats,
    ProductUpdated,
    Received,
    Rejected,
)
from .channel.manager import CONTROL_STREAM, STATUS_STREAM, ChannelManager, Transmission
from .channel.queue import StreamConfig
from .channel.schedule import Schedule
from .errors import AuthenticationError, CoexError, ConfigError, DecodeError, RequestRejected
from .messages import (
    AckStatus,
    AuthTrailer,
    CommandAck,
    FrameAck,
    LinkControl,
    LinkHealth,
    Message,
    Opaque,
    QueueConfig,
    ScheduleUpdate,
    SpareConfig,
    VehicleStatus,
)
from .messages import command_id as command_id_of
from .modality import Modality, ModalityReceiver, ModalitySender, modality_name
from .remap import RemappedReceiver, RemappedSender
from .routing import (
    Routes,
    check_remap,
    declared_ids,
    routine_ids,
    third_party,
    type_id,
)
from .state import StateError, dumps, dumps_parts, loads, loads_parts
from .storage import Storage
from .wire import unpack_frame

__all__ = ["Node", "Transmission"]

#: copies of a command that arrive within this many seconds came in one packet (redundant
#: copies in several frames): they are handled and answered once
DUPLICATE_SAME_PACKET = 1.0

_CHANNEL_COMMANDS = (QueueConfig, ScheduleUpdate, LinkControl, SpareConfig)


@dataclass
class _SenderSlot:
    name: str
    modality: type[Modality]
    sender: ModalitySender
    stream: int
    #: wire ids of its routine requests (they do not expedite the stream)
    routine: frozenset[int] = frozenset()


@dataclass
class _ReceiverSlot:
    name: str
    modality: type[Modality]
    receiver: ModalityReceiver
    stream: int
    #: the node whose messages it takes and to which its requests go (None: any node)
    peer: int | None = None

    @property
    def key(self) -> str:
        """Its name in saved state and storage: the modality's, ``@peer`` for a per-peer one."""
        return self.name if self.peer is None else f"{self.name}@{self.peer}"


def _modality_class(m: Modality | type[Modality]) -> type[Modality]:
    return m if isinstance(m, type) else type(m)


def _on_wire(ids: frozenset[int], remap: dict[int, int]) -> frozenset[int]:
    return frozenset(remap.get(i, i) for i in ids)


class Node:
    """One end of the link (vehicle or topside)."""

    def __init__(self, manager: ChannelManager, *, log: Callable[[str], None] | None = None,
                 stats_interval: float | None = 60.0) -> None:
        self.manager = manager
        self.node_id = manager.node_id
        self._senders: list[_SenderSlot] = []
        self._receivers: list[_ReceiverSlot] = []
        #: command id -> the receiver whose request carried it (its CommandAck goes back to it)
        self._command_owner: dict[int, _ReceiverSlot] = {}
        self._events: list[Event] = []
        self._log = log
        self.stats: dict[str, int] = {"frames": 0, "bad_frames": 0, "messages": 0, "rejected": 0,
                                      "foreign": 0, "duplicates": 0, "unauthenticated": 0}
        #: command id -> (command, status, time): a command received again (its frame ack was
        #: lost and topside re-sent it) is answered again but not applied twice.
        self._recent: dict[int, tuple[Message, AckStatus, float]] = {}
        self.duplicate_window = 3600.0
        #: messages taken from the latest packet (redundant copies of them in its other frames
        #: are dropped), and when
        self._packet_seen: dict[Message, float] = {}
        self.stats_interval = stats_interval
        self._last_stats: float | None = None
        self._bad_by_link: dict[int, int] = {}
        #: request types of the attached modalities: commands like those of ``auth.COMMAND_TYPES``
        self._request_types: tuple[type, ...] = ()
        self._request_opaque: frozenset[int] = frozenset()
        #: declared routing (:mod:`coex_core.routing`): wire type id -> sender (requests) or
        #: receiver (messages)
        self._request_routes = Routes("requests")
        self._message_routes = Routes("messages")
        #: per-peer receivers (a network of several nodes): peer -> its routes
        self._peer_routes: dict[int, Routes] = {}
        self._listeners: list[Callable[[list[Event]], Any]] = []
        manager.is_command = self.is_command

    def is_command(self, m: Message) -> bool:
        """Whether ``m`` is a topside-to-vehicle command (authenticated when a key is set): the
        channel commands, the core requests and acks, and every attached modality's requests."""
        if isinstance(m, Opaque):
            return m.type_id in self._request_opaque
        return is_command(m) or isinstance(m, self._request_types)

    def _add_requests(self, cls: type[Modality], remap: dict[int, int]) -> None:
        self._request_types = tuple({*self._request_types, *(t for t in cls.requests if t is not Opaque)})
        self._request_opaque = self._request_opaque | frozenset(
            i for i in _on_wire(declared_ids(cls, "requests"), remap) if third_party(i))

    # ===================================================================== composition
    def add_sender(self, modality: Modality | type[Modality], sender: ModalitySender,
                   stream: StreamConfig, *, ids: Mapping[int, int] | None = None) -> None:
        """Subsea: ``sender`` fills packets for ``stream`` and handles the modality's requests
        (routed by the type ids the modality declares, :mod:`coex_core.routing`). ``ids``
        remaps the modality's third-party ids on the wire (own id -> wire id; the topside
        node must remap them the same way). :class:`ConfigError` when another modality on this
        node already claims one of its request ids (the message names both)."""
        cls = _modality_class(modality)
        name = modality_name(cls)
        remap = check_remap(cls, ids)
        wire_ids = _on_wire(declared_ids(cls, "requests"), remap)
        slot = _SenderSlot(name, cls, RemappedSender(sender, remap) if remap else sender, stream.stream,
                           _on_wire(routine_ids(cls), remap))
        self._request_routes.claim(name, cls, wire_ids, slot)
        self.manager.add_stream(stream, slot.sender)
        self._add_requests(cls, remap)
        self._senders.append(slot)
        self._bind_peers(slot.sender)

    def _peer(self, name: str) -> ModalitySender | None:
        """The sender of the modality ``name`` on this node, inside any wrapper (None: none)."""
        for s in self._senders:
            if s.name == name:
                return _innermost(s.sender)  # type: ignore[no-any-return]
        return None

    def _bind_peers(self, sender: Any) -> None:
        _innermost(sender).bind_peers(self._peer)  # declared on ModalitySender

    def add_receiver(self, modality: Modality | type[Modality], receiver: ModalityReceiver,
                     stream: int = CONTROL_STREAM, *, ids: Mapping[int, int] | None = None,
                     peer: int | None = None) -> None:
        """Topside: ``receiver`` takes the modality's messages (routed by declared type ids);
        its requests (``poll``) go out on ``stream`` (default: the acked tier-0 control
        stream). ``ids`` as in :meth:`add_sender`. :class:`ConfigError` when another modality
        on this node already claims one of its message ids.

        ``peer`` (a network of several nodes): the receiver takes only the messages of node
        ``peer``, its requests go to that node alone, and its command answers count only from
        it; one receiver per modality and peer (a receiver without ``peer`` takes the messages
        of every node no per-peer receiver of the modality takes)."""
        cls = _modality_class(modality)
        name = modality_name(cls)
        remap = check_remap(cls, ids)
        wire_ids = _on_wire(declared_ids(cls, "messages"), remap)
        if peer is not None and not 1 <= peer <= 15:
            raise ConfigError(f"peer {peer} is not a node id 1..15")
        slot = _ReceiverSlot(name, cls, RemappedReceiver(receiver, remap) if remap else receiver, stream, peer)
        if peer is None:
            self._message_routes.claim(name, cls, wire_ids, slot)
        else:
            self._peer_routes.setdefault(peer, Routes("messages")).claim(name, cls, wire_ids, slot)
        self.manager.stream(stream)
        self._add_requests(cls, remap)
        slot.receiver.bind_command_ids(self.manager.next_command_id)  # one command id space per node
        self._receivers.append(slot)

    # ========================================================================= receive
    def receive(self, link_id: int, frame: bytes, now: float) -> list[Message]:
        """Take one received frame. Bad frames are counted and reported (:class:`BadFrame`),
        never raised. Returns the frame's messages (empty if it was not for this node)."""
        self.stats["frames"] += 1
        try:
            decoded = unpack_frame(frame)
        except DecodeError as exc:
            self.stats["bad_frames"] += 1
            self._bad_by_link[link_id] = self._bad_by_link.get(link_id, 0) + 1
            self._note(f"bad frame on link {link_id}: {exc}")
            self._events.append(BadFrame(now, link_id, str(exc), len(frame) if isinstance(frame, bytes | bytearray) else 0))
            return []
        h = decoded.header
        if h.src == self.node_id:
            self.stats["foreign"] += 1
            return []
        if h.dst not in (0, self.node_id):
            self._overheard(link_id, h, decoded.messages, now)
            return []
        messages = list(decoded.messages)
        replayed = False
        verifier = self.manager.verifier_for(h.src, h.dst)
        if verifier is not None:
            try:
                messages = verifier.verify(frame, h, messages, self.is_command)
            except AuthenticationError as exc:
                replayed = isinstance(exc, ReplayError)
                messages = self._unauthenticated(link_id, messages, exc, now)
        # a replayed frame is not acked: a genuine command that lost the race (frames
        # reordered) is then re-sent under a new counter
        ackable = not replayed and any(not isinstance(m, FrameAck) for m in decoded.messages)
        try:
            self.manager.on_frame(link_id, h, now, ackable)
        except CoexError as exc:
            self._note(f"frame bookkeeping failed: {exc}")
        # a frame's acks are applied after its other messages: a request packed earlier than
        # the ack (so it may ask for what the ack confirms) then meets the ack, and the sender
        # can drop what the ack answered (``ModalitySender.acked``)
        for m in sorted(messages, key=lambda m: isinstance(m, FrameAck)):  # stable: order kept
            self.stats["messages"] += 1
            try:
                self._route(link_id, h.src, m, now)
            except Exception as exc:  # one bad message never loses the others, never crashes
                self.stats["rejected"] += 1
                self._note(f"{type(m).__name__} failed: {exc}")
                self._events.append(Rejected(now, m, f"{type(exc).__name__}: {exc}"))
        return messages

    def _overheard(self, link_id: int, h: Any, messages: Any, now: float) -> None:
        """A frame addressed to another node (a network of several nodes): not consumed, not
        acknowledged. It still shows the network is alive (watchdog, the sender's schedule
        version and loss), and its frame acks that name this node apply: a frame ack is
        addressed by its ``node`` field (spec section 7)."""
        self.stats["foreign"] += 1
        try:
            self.manager.on_frame(link_id, h, now, ackable=False, addressed=False)
        except CoexError as exc:
            self._note(f"frame bookkeeping failed: {exc}")
        for m in messages:
            if isinstance(m, FrameAck) and m.node == self.node_id:
                self._acked(m, now, h.src)

    def _acked(self, ack: FrameAck, now: float, src: int | None = None) -> None:
        """Apply a frame ack, then tell each sender which of its messages were acknowledged."""
        for stream, message in self.manager.acknowledge(ack, now, src):
            for s in self._senders:
                if s.stream != stream:
                    continue
                try:
                    s.sender.acked(message, now)
                except Exception as exc:  # a sender's hook never stops the node
                    self.stats["rejected"] += 1
                    self._note(f"{s.name} sender failed on an ack: {type(exc).__name__}: {exc}")

    def _unauthenticated(self, link_id: int, messages: list[Message], exc: AuthenticationError,
                         now: float) -> list[Message]:
        """A frame failed authentication: its commands are rejected, logged and counted (and
        answered ``UNAUTHENTICATED`` unless it was a replay); the rest is returned."""
        self.stats["unauthenticated"] += 1
        self._note(f"commands rejected on link {link_id}: {exc}")
        rest: list[Message] = []
        for m in messages:
            if isinstance(m, AuthTrailer):
                continue
            if not self.is_command(m):
                rest.append(m)
                continue
            self._events.append(Rejected(now, m, f"{type(exc).__name__}: {exc}"))
            cid = command_id_of(m)
            if cid is not None and not isinstance(exc, ReplayError):
                self.manager.push(CONTROL_STREAM, CommandAck(int(cid), AckStatus.UNAUTHENTICATED), now)
        return rest

    def _route(self, link_id: int, src: int, m: Message, now: float) -> None:
        if isinstance(m, FrameAck):
            self._acked(m, now, src)
            return
        if self._copy_seen(m, now):
            self.stats["duplicates"] += 1  # a redundant copy from the same packet: handled once
            return
        if isinstance(m, CommandAck):
            known = self._command_owner.get(m.command_id)
            if (known is not None and known.peer not in (None, src)) or \
                    (known is None and not self.manager.answers(m.command_id, src)):
                self.stats["foreign"] += 1  # an answer to a command another node was sent
                return
            if m.status == AckStatus.PENDING:  # a standing request: its final answer follows
                owner = self._command_owner.get(m.command_id)
            else:
                owner = self._command_owner.pop(m.command_id, None)
            if owner is not None:
                # a modality request: its receiver tracks it (and may stop retrying it)
                for p in owner.receiver.receive(m, now) or ():
                    self._events.append(ProductUpdated(now, owner.name, p, owner.peer))
            self.manager.on_command_ack(m, now, src)  # emits CommandResult
            return
        if self._duplicate(m, now):
            return
        if isinstance(m, _CHANNEL_COMMANDS):
            ack = self.manager.apply(m, now)
            self._remember(m, ack.status, now)
            self.manager.push(CONTROL_STREAM, ack, now)
            return
        s = self._request_routes.owner(m)
        if s is not None:
            self._handle_request(s, m, now)
            return
        peer_routes = self._peer_routes.get(src)
        r = peer_routes.owner(m) if peer_routes is not None else None
        if r is None:
            r = self._message_routes.owner(m)
        if r is not None:
            for p in r.receiver.receive(m, now):
                self._events.append(ProductUpdated(now, r.name, p, r.peer))
            return
        self._events.append(Received(now, link_id, src, m))

    def _copy_seen(self, m: Message, now: float) -> bool:
        """Whether ``m`` is a copy of a message taken within :data:`DUPLICATE_SAME_PACKET`
        seconds (a sender under loss puts copies in several frames of one packet)."""
        seen = self._packet_seen
        if seen and now - max(seen.values()) > DUPLICATE_SAME_PACKET:
            seen.clear()
        try:
            t = seen.get(m)
        except TypeError:  # an unhashable message: never a copy
            return False
        if t is not None and now - t <= DUPLICATE_SAME_PACKET:
            return True
        seen[m] = now
        return False

    def _duplicate(self, m: Message, now: float) -> bool:
        cid = command_id_of(m)
        if cid is None:
            return False
        seen = self._recent.get(int(cid))
        if seen is None or seen[0] != m or now - seen[2] > self.duplicate_window:
            return False
        self.stats["duplicates"] += 1
        # a re-send (the first answer may have been lost): answer again (copies from one packet
        # never get here: _copy_seen drops them first)
        self.manager.push(CONTROL_STREAM, CommandAck(int(cid), seen[1]), now)
        return True

    def _remember(self, m: Message, status: AckStatus, now: float) -> None:
        cid = command_id_of(m)
        if cid is not None:
            self._recent[int(cid)] = (m, status, now)

    @staticmethod
    def _routine(m: Message, s: _SenderSlot) -> bool:
        """Routine traffic (the requests a modality declares ``routine``: ``ImageAck``,
        ``TimeSeriesAck`` ...) does not expedite the modality's stream."""
        return type_id(m) in s.routine

    def _handle_request(self, s: _SenderSlot, m: Message, now: float) -> None:
        cid = command_id_of(m)
        try:
            replies = s.sender.handle(m, now)
        except RequestRejected as exc:
            self.stats["rejected"] += 1
            self._events.append(Rejected(now, m, str(exc)))
            if cid is not None:
                self._remember(m, AckStatus.REJECTED, now)
                self.manager.push(CONTROL_STREAM, CommandAck(int(cid), AckStatus.REJECTED), now)
            return
        except Exception as exc:
            self.stats["rejected"] += 1
            self._note(f"{s.name} sender failed on {type(m).__name__}: {exc}")
            self._events.append(Rejected(now, m, f"{type(exc).__name__}: {exc}"))
            if cid is not None:
                self.manager.push(CONTROL_STREAM, CommandAck(int(cid), AckStatus.REJECTED), now)
            return
        replies = list(replies or ())
        if cid is not None:
            # the sender's own CommandAck for it (e.g. PENDING: it stands) replaces the default
            own = [r for r in replies if isinstance(r, CommandAck) and r.command_id == cid]
            status = own[0].status if own else AckStatus.ACCEPTED
            replies = [r for r in replies if not any(r is o for o in own)]
            self._remember(m, status, now)
            self.manager.push(CONTROL_STREAM, CommandAck(int(cid), status), now)
        if not self._routine(m, s):
            # an operator request (not a routine ack): its answer goes in the next transmission
            self.manager.expedite(s.stream)
        for r in replies:
            try:
                self.manager.push(s.stream, r, now)
            except CoexError as exc:
                self._events.append(Rejected(now, r, f"reply not sendable: {exc}"))

    # ============================================================================ send
    def link_stats(self, now: float) -> list[LinkStats]:
        """Per-link counters now."""
        out = []
        for link in self.manager.links:
            st = self.manager.link_state(link)
            out.append(LinkStats(now, link, st["frames_rx"], self._bad_by_link.get(link, 0),
                                 st["packets"], st["frames_tx"], st["schedule"], st["enabled"],
                                 st["muted"]))
        return out

    def poll(self, now: float) -> list[Transmission]:
        """Collect receivers' requests, then build a packet for every link that may send now."""
        if self.stats_interval is not None and (
                self._last_stats is None or now - self._last_stats >= self.stats_interval):
            self._last_stats = now
            self._events.extend(self.link_stats(now))
        for r in self._receivers:
            try:
                reqs = r.receiver.poll(now)
            except Exception as exc:
                self._note(f"{r.name} receiver poll failed: {exc}")
                continue
            for m in reqs:
                cid = command_id_of(m)
                if cid is not None:
                    self._command_owner[int(cid)] = r
            for m in reqs:
                self._supersede(r, m, now)
                try:
                    self.manager.push(r.stream, m, now, dst=r.peer)
                except CoexError as exc:
                    self._events.append(Rejected(now, m, f"request not sendable: {exc}"))
        return self.manager.poll(now)

    def _supersede(self, r: _ReceiverSlot, new: Message, now: float) -> None:
        """Withdraw from ``r``'s stream the earlier requests its receiver says ``new`` replaces."""
        def outdated(old: Message) -> bool:
            return old is not new and type(old) is type(new) and r.receiver.supersedes(old, new)

        try:
            self.manager.withdraw(r.stream, outdated, now, dst=r.peer)
        except Exception as exc:
            self._note(f"{r.name} receiver supersedes failed: {exc}")

    def next_event(self, now: float) -> float | None:
        """When :meth:`poll` should next be called (``None``: nothing scheduled)."""
        return self.manager.next_event(now)

    def events(self) -> list[Event]:
        """Everything that happened since the last call: node events then manager events.
        Every :meth:`subscribe`d listener sees them too, in this call (the thread that drives
        the node)."""
        out = self._events + self.manager.events()
        self._events = []
        for listener in list(self._listeners):
            try:
                listener(out)
            except Exception as exc:  # an observer (a console) must never cost the node
                self._note(f"event listener failed: {exc}")
        return out

    def subscribe(self, listener: Callable[[list[Event]], Any]) -> Callable[[], None]:
        """Call ``listener(events)`` with what every :meth:`events` call drains, whoever
        drains it (a runner, a demo loop): how an application (the console) watches a node
        that another loop drives. Returns a function that unsubscribes it."""
        self._listeners.append(listener)

        def unsubscribe() -> None:
            if listener in self._listeners:
                self._listeners.remove(listener)

        return unsubscribe

    def products(self) -> list[tuple[str, Any]]:
        return [(r.name, p) for r in self._receivers for p in r.receiver.products()]

    # ==================================================================== vehicle side
    def push_status(self, status: VehicleStatus, now: float) -> None:
        """Queue the newest vehicle status (strict tier 0, newest only)."""
        self.manager.push(STATUS_STREAM, status, now)

    def not_sent(self, tx: Transmission, now: float) -> None:
        """A transmission from :meth:`poll` that never left (its modem was down): what it carried
        is sent again as soon as the link is back (:meth:`ChannelManager.not_sent`)."""
        self.manager.not_sent(tx, now)

    def push_link_health(self, health: LinkHealth, now: float) -> None:
        """Queue a report of a modem's outages (control stream: tier 0, re-sent until a frame
        ack covers it, on whichever link is up). Push one when a modem goes down or comes back."""
        self.manager.push(CONTROL_STREAM, health, now)

    # ================================================================== topside helpers
    # In a network of several nodes, ``dst`` names the node a command is for (0: every node;
    # None: the link's ``LinkConfig.dst``); only that node's CommandAck answers it.
    def queue_config(self, stream: int, now: float, *, flush: bool = False,
                     enabled: bool | None = None, priority: int | None = None,
                     ttl: int | None = None, max_depth: int | None = None,
                     newest_first: bool | None = None, dst: int | None = None) -> int:
        """Send a QueueConfig; returns its command id (see :class:`CommandResult` events)."""
        cid = self.manager.next_command_id()
        msg = QueueConfig(cid, stream, flush, enabled, priority, ttl, max_depth, newest_first)
        return self.manager.send_command(msg, now, dst=dst)

    def link_control(self, link: int, now: float, *, enabled: bool = True, mute: bool = False,
                     dst: int | None = None) -> int:
        cid = self.manager.next_command_id()
        return self.manager.send_command(LinkControl(cid, link, enabled, mute), now, dst=dst)

    def spare_config(self, percent: int, now: float, *, link: int | None = None,
                     stream: int | None = None, dst: int | None = None) -> int:
        """Send a SpareConfig: cap spare traffic at ``percent`` of each packet (0: off) on
        ``link`` (every link when both are None) or for ``stream``; returns its command id."""
        cid = self.manager.next_command_id()
        return self.manager.send_command(SpareConfig(cid, link, stream, int(percent)), now, dst=dst)

    def schedule_update(self, link: int, schedule: Schedule, now: float,
                        activate_cycle: int | None = None, *,
                        peers: Iterable[int] | None = None) -> int:
        """Announce a new schedule; both ends switch at the announced cycle boundary. In a
        network of several nodes every node must agree first
        (:meth:`ChannelManager.propose_schedule`, ``peers``)."""
        return self.manager.propose_schedule(link, schedule, now, activate_cycle, peers=peers).command_id

    def request(self, message: Message, now: float, *, dst: int | None = None) -> int | None:
        """Send a modality request (or any message) on the control stream; a request with a
        ``command_id`` is tracked until the vehicle's CommandAck. ``dst``: the node it is for."""
        cid = command_id_of(message)
        if cid is not None:
            return self.manager.send_command(message, now, dst=dst)
        self.manager.push(CONTROL_STREAM, message, now, dst=dst)
        return None

    def command_results(self, events: list[Event]) -> list[CommandResult]:
        return [e for e in events if isinstance(e, CommandResult)]

    # ========================================================================== misc
    def sender(self, name: str) -> ModalitySender:
        """The sender of the modality called ``name`` (:class:`ConfigError` if none)."""
        for s in self._senders:
            if s.name == name:
                return s.sender
        raise ConfigError(f"no sender {name!r} on node {self.node_id}")

    def receiver(self, name: str, peer: int | None = None) -> ModalityReceiver:
        """The receiver of the modality called ``name`` (for node ``peer``, if per-peer;
        :class:`ConfigError` if none)."""
        for r in self._receivers:
            if r.name == name and r.peer == peer:
                return r.receiver
        raise ConfigError(f"no receiver {name!r}{'' if peer is None else f' for node {peer}'} "
                          f"on node {self.node_id}")

    def receivers(self) -> list[tuple[str, ModalityReceiver]]:
        """``(modality name, receiver)`` of every attached receiver, in attachment order."""
        return [(r.name, r.receiver) for r in self._receivers]

    def set_log(self, log: Callable[[str], None] | None) -> None:
        self._log = log

    def attach_storage(self, storage: Storage) -> None:
        """Give every modality its part of ``storage`` (:mod:`coex_core.storage`): senders
        ``tx/<name>/``, receivers ``rx/<name>/``. A runner with a store calls this after the
        node's saved state (if any) was loaded, and again whenever it restores the node."""
        for s in self._senders:
            _innermost(s.sender).attach_storage(storage.child(f"tx/{s.name}/"))
        for r in self._receivers:
            _innermost(r.receiver).attach_storage(storage.child(f"rx/{r.key}/"))

    def sync_storage(self) -> None:
        """Every modality writes to its storage what the storage does not have yet (before a
        snapshot: :meth:`export_state` calls it)."""
        for s in self._senders:
            _innermost(s.sender).sync_storage()
        for r in self._receivers:
            _innermost(r.receiver).sync_storage()

    # ===================================================================== saved state
    #: node fields that are state (the rest is structure, rebuilt by whoever builds the node)
    _STATE_FIELDS = ("stats", "_recent", "duplicate_window", "stats_interval", "_last_stats",
                     "_bad_by_link")

    def export_state(self, extra: Any = None) -> bytes:
        """The node's state as :mod:`coex_core.state` bytes (never pickle): its channel manager
        (queues, pending acks, sequence numbers, schedules, command ids), every modality
        sender and receiver (by modality name), its own counters and command bookkeeping, and
        ``extra`` (an application's state saved with it, e.g. the console's: objects it shares
        with the node stay shared). Keys, clocks and callbacks are not state."""
        return dumps(self._state_root(extra))

    def export_parts(self, extra: Any = None) -> tuple[bytes, dict[str, Any]]:
        """What :meth:`export_state` saves, as :func:`coex_core.state.dumps_parts` gives it: the
        document's text and its arrays by content (a store writes only the parts that changed
        since its last save)."""
        return dumps_parts(self._state_root(extra))

    def _state_root(self, extra: Any) -> dict[str, Any]:
        self.sync_storage()
        mgr = self.manager
        root = {
            "node_id": self.node_id,
            "node": {k: getattr(self, k) for k in self._STATE_FIELDS},
            "command_owner": {cid: r.key for cid, r in self._command_owner.items()},
            "manager": mgr,
            "auth": {"signed": mgr.signer.counter if mgr.signer is not None else None,
                     "accepted": mgr.verifier.counter if mgr.verifier is not None else None,
                     "rejected": mgr.verifier.rejected if mgr.verifier is not None else None,
                     # a network of several nodes: the counters of each peer's own key
                     "peers": {p: {"signed": mgr.peer_signers[p].counter,
                                   "accepted": mgr.peer_verifiers[p].counter,
                                   "rejected": mgr.peer_verifiers[p].rejected}
                               for p in sorted(mgr.peer_signers)}},
            "senders": {s.name: _innermost(s.sender) for s in self._senders},
            "receivers": {r.key: _innermost(r.receiver) for r in self._receivers},
            "extra": extra,
        }
        return root

    def restore_state(self, data: bytes) -> Any:
        """Load what :meth:`export_state` saved into this node, which must have been built the
        same way (node id, modalities; a sender or receiver wrapped by the application keeps
        its wrapper). Returns the saved ``extra``. :class:`~coex_core.state.StateError` when the
        state does not fit this node."""
        return self._restore_root(loads(data))

    def restore_parts(self, text: bytes, arrays: Mapping[str, Any]) -> Any:
        """:meth:`restore_state` from what :meth:`export_parts` gave."""
        return self._restore_root(loads_parts(text, arrays))

    def _restore_root(self, root: Any) -> Any:
        if root.get("node_id") != self.node_id:
            raise StateError(f"the saved state is node {root.get('node_id')}'s, not {self.node_id}'s")
        senders, receivers = dict(root["senders"]), dict(root["receivers"])
        if set(senders) != {s.name for s in self._senders} or \
                set(receivers) != {r.key for r in self._receivers}:
            raise StateError(f"the saved state has senders {sorted(senders)} and receivers "
                             f"{sorted(receivers)}; this node has "
                             f"{sorted(s.name for s in self._senders)} and "
                             f"{sorted(r.key for r in self._receivers)}")
        fresh, mgr = self.manager, root["manager"]
        if sorted(mgr.links) != sorted(fresh.links):
            raise StateError(f"the saved state has links {sorted(mgr.links)}, this node "
                             f"{sorted(fresh.links)}")
        mgr.clock, mgr.is_command = fresh.clock, self.is_command
        mgr.signer, mgr.verifier = fresh.signer, fresh.verifier
        mgr.peer_signers, mgr.peer_verifiers = fresh.peer_signers, fresh.peer_verifiers
        auth = root["auth"]
        for p, c in (auth.get("peers") or {}).items():
            if p in mgr.peer_signers:
                mgr.peer_signers[p].counter = int(c["signed"])
                mgr.peer_verifiers[p].counter = int(c["accepted"])
                mgr.peer_verifiers[p].rejected = int(c["rejected"] or 0)
        if mgr.signer is not None and auth["signed"] is not None:
            mgr.signer.counter = int(auth["signed"])
        if mgr.verifier is not None and auth["accepted"] is not None:
            mgr.verifier.counter = int(auth["accepted"])
            mgr.verifier.rejected = int(auth["rejected"] or 0)
        for s in self._senders:
            s.sender = _install(s.sender, senders[s.name])
            self._bind_peers(s.sender)
        for r in self._receivers:
            r.receiver = _install(r.receiver, receivers[r.key])
            r.receiver.bind_command_ids(mgr.next_command_id)
        by_stream = {s.stream: s.sender for s in self._senders}
        for sid, st in mgr._streams.items():
            old = fresh._streams.get(sid)
            st.sender = by_stream.get(sid, old.sender if old is not None else None)
        self.manager = mgr
        for k, v in root["node"].items():
            setattr(self, k, v)
        slots = {r.key: r for r in self._receivers}
        self._command_owner = {int(cid): slots[name] for cid, name in root["command_owner"].items()
                               if name in slots}
        return root["extra"]

    def _note(self, text: str) -> None:
        if self._log is not None:
            try:
                self._log(text)
            except Exception:  # logging must never take the node down
                pass


def _wrappers(part: Any) -> list[Any]:
    """``part`` and the senders or receivers it wraps (``inner``), outermost first."""
    chain = [part]
    while isinstance(chain[-1], ModalitySender | ModalityReceiver) \
            and isinstance(chain[-1].inner, ModalitySender | ModalityReceiver) and len(chain) < 8:
        chain.append(chain[-1].inner)  # declared on both bases (None: wraps none)
    return chain


def _innermost(part: Any) -> Any:
    """The sender or receiver inside an application's wrappers: its state."""
    return _wrappers(part)[-1]


def _install(current: Any, restored: Any) -> Any:
    """``restored`` in place of the innermost part of ``current`` (its wrappers stay)."""
    chain = _wrappers(current)
    if len(chain) == 1:
        return restored
    chain[-2].inner = restored
    return current


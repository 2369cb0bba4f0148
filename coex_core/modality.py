"""Abstract bases of a data modality (bathymetry, imagery, time series, third-party ...).

A modality has two sides that never do I/O and never read a clock: time enters as ``now``
(float seconds) and data leaves as :class:`~coex_core.messages.Message` objects.

* The **subsea side** (:class:`ModalitySender`) takes sensor data (:meth:`~ModalitySender.ingest`),
  answers "give me at most N bytes for this packet" (:meth:`~ModalitySender.fill`) and handles
  topside requests (:meth:`~ModalitySender.handle`).
* The **topside side** (:class:`ModalityReceiver`) takes received messages
  (:meth:`~ModalityReceiver.receive`), builds products (:meth:`~ModalityReceiver.products`) and
  creates requests (:meth:`~ModalityReceiver.poll` and modality-specific request methods).

A plugin's entry point (group ``coex.modalities``) names a :class:`Modality` subclass, which
creates both sides.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from .messages import Message
from .storage import Storage

__all__ = ["Modality", "ModalityReceiver", "ModalitySender", "Product"]


@dataclass(frozen=True)
class Product:
    """Something a receiver made that a person or a tool can use.

    ``kind`` names it (``"map-level"``, ``"image"``, ``"series"`` ...), ``key`` identifies it
    within the kind, ``version`` increases whenever it improves, ``data`` holds the payload
    (numpy arrays, bytes ...) and ``meta`` describes it (JSON-serialisable)."""

    kind: str
    key: str
    version: int
    data: Any = None
    meta: Mapping[str, Any] = field(default_factory=dict)


class _OutOfCore:
    """The optional out-of-core hooks both sides of a modality share."""

    def attach_storage(self, storage: Storage) -> None:
        """The node's runner gives the modality its out-of-core storage
        (:mod:`coex_core.storage`): a modality whose state can outgrow memory keeps there what it
        is not working on. Called after the modality's saved state (if any) was loaded. Optional
        (default: the storage is not used)."""

    def sync_storage(self) -> None:
        """Before every snapshot of the node: write to the attached storage whatever is held in
        memory that the storage does not have yet. Optional."""


class ModalitySender(_OutOfCore, abc.ABC):
    """The subsea side of a modality.

    Contract:

    * :meth:`fill` returns messages whose encoded sizes (``coex_core.wire.encoded_size``) add up
      to at most ``max_bytes``; it returns ``[]`` when it has nothing that fits. It must be
      cheap: the channel manager calls it while building a packet and gives up on a sender that
      raises or overruns its deadline (that sender then counts as "no data" for the packet).
    * :meth:`handle` accepts only the message types listed in ``Modality.requests``; anything
      else, and any request out of bounds, raises :class:`~coex_core.errors.RequestRejected`
      and leaves the sender unchanged. It may return messages to send at once (acks).
    * Bad sensor input given to :meth:`ingest` raises a :class:`~coex_core.errors.CoexError`
      subclass and loses nothing already ingested.
    """

    @abc.abstractmethod
    def ingest(self, data: Any, now: float) -> None:
        """Take sensor data captured at or before ``now``."""

    @abc.abstractmethod
    def fill(self, max_bytes: int, now: float) -> list[Message]:
        """Messages to send now, at most ``max_bytes`` encoded in total."""

    @abc.abstractmethod
    def handle(self, message: Message, now: float) -> list[Message]:
        """Handle a topside request; return any immediate replies."""

    def pending_bytes(self) -> int:
        """An estimate of the bytes still waiting to be sent (0 when idle)."""
        return 0

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        """Spare work: messages worth sending only when nothing else waits (re-sends of what
        was lost, refinements beyond the set-point), at most ``max_bytes`` encoded in total,
        with :meth:`fill`'s contract. The channel manager asks for it below every tier, within
        the link's and the stream's spare share (``LinkConfig.spare``, ``StreamConfig.spare``:
        0 switches it off, and then it is never called). Optional (default: none). What it
        returns is packed at once, not queued: a message that does not fit is dropped (counted
        as ``overrun``)."""
        return []

    def spare_bytes(self) -> int:
        """An estimate of the spare work available now, in bytes (0: none). Optional."""
        return 0

    def ready_bytes(self, now: float) -> int:
        """An estimate of the bytes :meth:`fill` and :meth:`spare` could give now (what waits
        for an ack that is still due excluded). The channel manager reports it as the backlog
        after each packet (``Transmission.backlog``): a packet sent while work was ready should
        be full. Optional (default: :meth:`pending_bytes` plus :meth:`spare_bytes`)."""
        return self.pending_bytes() + self.spare_bytes()

    def lost(self, message: Message, now: float) -> None:
        """No frame that carried ``message`` (which this sender produced, on a stream that is
        not ``ack_required``) was acknowledged within the link's ack timeout: it probably did not
        arrive (or its ack did not). Optional: a sender may offer it again as spare work. It must
        not raise (if it does, the manager counts it and nothing else changes)."""

    def journal_form(self, data: Any) -> Any:
        """What a store journals of an input before :meth:`ingest` takes it (and what is
        ingested): plain data that :mod:`coex_core.state` can save (numbers, strings, arrays,
        containers, registered classes). Optional (default: the input itself); a sender that
        accepts other objects (a ROS message) converts them here."""
        return data

    def acked(self, message: Message, now: float) -> None:
        """The other side acknowledged a frame that carried ``message``, which this sender
        produced (called by the node when the frame ack arrives; on streams without
        ``ack_required`` too, see :meth:`lost`). Optional: a sender may use it to drop a queued
        copy that is no longer needed. It must not raise (if it does, the node logs and counts
        it, and nothing else changes)."""

    def focus(self, x: float, y: float, radius: float, now: float) -> int:
        """Something on the vehicle (a detection, :mod:`coex_core.detect`) points at ``(x, y)``
        (metres east and north of the origin): send the finest data held within ``radius``
        metres of it next, as a region request from topside would have it (what topside is
        known to hold left out), before background data elsewhere, without waiting for the
        request. Returns how many messages it queued for it. Optional (default: nothing, 0).
        It must not raise."""
        return 0

    def detector_view(self) -> object | None:
        """What onboard detectors of this modality look at (:mod:`coex_core.detect`): one view
        of the data this sender holds on the vehicle, of a type detectors declare as their
        ``view`` (the bathymetry sender's map is a :class:`~coex_core.detect.MapView`, the
        imagery sender's frames :class:`~coex_core.detect.ImageFrames`; a third-party modality
        documents its own). Optional (default: None, nothing for detectors). It must not
        raise, and it is called every few seconds: a view, not a copy."""
        return None

    def throughput(self, bytes_per_second: float, low: bool, now: float) -> None:
        """The channel's measure of the link, before each packet it builds: the bytes per
        second this node's frames deliver (its slots' capacity less the measured frame loss,
        every enabled link together) and whether the channel's policy finds it ``low``
        (``docs/channel.md``, priorities that follow the link). Optional: a sender may then
        send what decides first (the bathymetry sender keeps its finest level away from the
        background while the link is low). It must not raise."""

    #: the sender this one wraps, when it is a wrapper an application put around a modality's
    #: sender (remapped ids, a recorder, a fault injector): the node saves, restores, binds and
    #: gives storage to the innermost sender, and a restore puts the restored one in the
    #: innermost wrapper's ``inner``. None (the default): it wraps none.
    inner: ModalitySender | None = None
    #: how this sender reaches the other senders of its node (:meth:`bind_peers`)
    _peers: Callable[[str], ModalitySender | None] | None = None
    #: not saved with the sender's state (:mod:`coex_core.state`): the node binds it again
    _state_transient: ClassVar[tuple[str, ...]] = ("_peers",)

    def bind_peers(self, peer: Callable[[str], ModalitySender | None]) -> None:
        """The node calls this when the sender is added (and again after a restore):
        ``peer(name)`` is the sender of the modality ``name`` on the same node (None: none).
        A sender that works on what another modality holds on the vehicle (the detections
        modality looks at the bathymetry sender's map) finds it through :meth:`peer`."""
        self._peers = peer

    def peer(self, name: str) -> ModalitySender | None:
        """The sender of the modality ``name`` on this sender's node (None: none, or not bound)."""
        return None if self._peers is None else self._peers(name)


class ModalityReceiver(_OutOfCore, abc.ABC):
    """The topside side of a modality.

    Contract: :meth:`receive` accepts the message types listed in ``Modality.messages``, never
    raises for a valid message (duplicates and stale data are ignored), and returns the
    products it changed. :meth:`poll` returns requests to send to the vehicle (acks, retries
    of unanswered requests); it returns each request once per call that should send it.
    """

    @abc.abstractmethod
    def receive(self, message: Message, now: float) -> list[Product]:
        """Take one received message; return the products it improved."""

    @abc.abstractmethod
    def poll(self, now: float) -> list[Message]:
        """Requests and acks to send to the vehicle now."""

    @abc.abstractmethod
    def products(self) -> list[Product]:
        """Every current product."""

    #: the receiver this one wraps (as :attr:`ModalitySender.inner`); None (the default): none
    inner: ModalityReceiver | None = None
    #: where this receiver's command ids come from (:meth:`bind_command_ids`)
    _command_ids: Callable[[], int] | None = None
    #: not saved with the receiver's state (:mod:`coex_core.state`): the node binds it again
    _state_transient: ClassVar[tuple[str, ...]] = ("_command_ids",)
    _own_command_id: int = 0

    def bind_command_ids(self, allocate: Callable[[], int]) -> None:
        """The node calls this when the receiver is added: every ``command_id`` the receiver
        puts on a request must then come from ``allocate()`` (:meth:`next_command_id`), so that
        one node has one id space and a CommandAck answers exactly one command, whether the
        node, the console or a receiver sent it."""
        self._command_ids = allocate

    def next_command_id(self) -> int:
        """A command id for a new request (the node's, once bound; else the receiver's own)."""
        if self._command_ids is not None:
            return int(self._command_ids())
        self._own_command_id = (self._own_command_id + 1) % 256
        return self._own_command_id

    def view(self, product: Product) -> Mapping[str, Any] | None:
        """What the topside console shows of one of this receiver's products in its generic
        panel (modalities it has no panel of its own for): a small JSON-safe mapping of labels
        to values. Optional (default: None, the console shows the product's plain metadata)."""
        return None

    def supersedes(self, old: Message, new: Message) -> bool:
        """Whether ``new``, a request :meth:`poll` just returned, makes ``old``, an earlier one
        still in the channel (queued, or sent and not yet acknowledged), useless. Optional
        (default: never). The node then withdraws ``old`` before queueing ``new``, so the channel
        does not re-send an outdated request after the fresh one (a retry of a region request
        carries what topside holds now). It must not raise (if it does, the node logs it and
        withdraws nothing)."""
        return False


class Modality(abc.ABC):
    """A modality plugin: its name, its message types, and factories for both sides.

    ``messages`` are the types its sender emits and its receiver takes; ``requests`` are the
    types its receiver emits and its sender handles. ``config`` is a plain mapping (from a
    command line or a file); an invalid one raises :class:`~coex_core.errors.ConfigError`.
    """

    name: ClassVar[str]
    version: ClassVar[str] = "0"
    #: built-in message types its sender emits and its receiver takes
    messages: ClassVar[tuple[type[Message], ...]] = ()
    #: built-in message types its receiver emits and its sender handles (requests, acks)
    requests: ClassVar[tuple[type[Message], ...]] = ()
    #: third-party type ids (:class:`~coex_core.messages.Opaque`, spec section 5: 96..32767)
    #: its sender emits and its receiver takes; a node routes those ids, and only those, to it
    message_ids: ClassVar[tuple[int, ...]] = ()
    #: third-party type ids its receiver emits and its sender handles
    request_ids: ClassVar[tuple[int, ...]] = ()
    #: the requests that are routine (acks of data, types or third-party ids): handled without
    #: expediting the stream; every other request makes its answer leave in the next packet
    routine: ClassVar[tuple[type[Message] | int, ...]] = ()
    #: bytes a sender may still send per hour once everything it holds is acknowledged
    #: (progress reports, heartbeats); the conformance suite holds it to this
    keepalive_bytes_per_hour: ClassVar[int] = 0

    @abc.abstractmethod
    def sender(self, config: Mapping[str, Any] | None = None) -> ModalitySender:
        """A new subsea side."""

    @abc.abstractmethod
    def receiver(self, config: Mapping[str, Any] | None = None) -> ModalityReceiver:
        """A new topside side."""

    @classmethod
    def decode_body(cls, type_id: int, body: bytes) -> Any:
        """The value of a third-party body: ``type_id`` is one of ``message_ids`` /
        ``request_ids``; raises :class:`~coex_core.errors.DecodeError` for any other id and for
        a damaged body. One encoding per value: ``encode_body(t, decode_body(t, b)) == b``.
        A modality that declares third-party ids gives this and :meth:`encode_body`
        (docs/plugins.md, "The body codec"); the default decodes nothing."""
        from .errors import DecodeError

        raise DecodeError(f"{cls.__name__} has no body codec (decode_body): type id {type_id} is not decoded")

    @classmethod
    def encode_body(cls, type_id: int, value: Any) -> bytes:
        """The body bytes of ``value`` under ``type_id`` (the inverse of :meth:`decode_body`);
        raises :class:`~coex_core.errors.EncodeError` for an id the modality does not declare.
        The default encodes nothing."""
        from .errors import EncodeError

        raise EncodeError(f"{cls.__name__} has no body codec (encode_body): type id {type_id} is not encoded")

    @classmethod
    def handles(cls, message: Message) -> bool:
        """Whether ``message`` is one of this modality's messages or requests (by type, or by
        declared third-party id)."""
        from .routing import declared_ids, type_id

        tid = type_id(message)
        return tid is not None and any(tid in declared_ids(cls, kind) for kind in ("messages", "requests"))


def modality_name(cls: type[Modality]) -> str:
    """The name a modality class declares (``Modality.name``, required); a
    :class:`~coex_core.errors.ConfigError` naming the class when it declares none."""
    try:
        return cls.name
    except AttributeError:
        from .errors import ConfigError

        raise ConfigError(f"modality {cls.__qualname__} declares no name (Modality.name)") from None


def total_size(messages: Sequence[Message]) -> int:
    """Encoded size of several messages."""
    from .wire import encoded_size

    return sum(encoded_size(m) for m in messages)

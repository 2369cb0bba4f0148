"""A deterministic two-way simulation of an imagery transfer over lossy links (no clock, no I/O).

Used by ``coex image roundtrip`` and ``coex image region`` (:func:`region_transfer`), the tests
and the benchmark. Each round the vehicle fills one
frame of at most ``mtu`` bytes; topside takes what arrives and answers with acks and requests in
as many frames as they need; the vehicle handles those and its immediate replies (command acks)
go down in one more frame. Loss is drawn per frame from seeded models: independent
(:class:`Bernoulli`) or bursty (:class:`Burst`: the channel simulator's
:class:`~coex_core.acoustic.GilbertElliott` with its own random stream).
"""

from __future__ import annotations

import abc
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from coex import (
    EncodeError,
    GilbertElliott,
    ModalityReceiver,
    ModalitySender,
    Product,
    RequestRejected,
    wire,
)
from coex.messages import FrameHeader, Message

__all__ = ["Bernoulli", "Burst", "LossModel", "RegionRun", "Transfer", "WireEvent", "region_transfer"]


class LossModel(abc.ABC):
    """Decides, frame by frame, whether a frame is lost."""

    @abc.abstractmethod
    def lost(self) -> bool:
        """Whether the next frame is lost."""


class Bernoulli(LossModel):
    """Each frame is lost independently with probability ``p``."""

    def __init__(self, p: float, seed: int = 0) -> None:
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"loss must be in [0, 1], got {p}")
        self.p = p
        self.rng = random.Random(seed)

    def lost(self) -> bool:
        return self.p > 0 and self.rng.random() < self.p


class Burst(LossModel):
    """Burst loss: the acoustic channel's two-state :class:`~coex_core.acoustic.GilbertElliott`
    model (the one loss model of CoEx), stepped once per frame with a seeded random stream."""

    def __init__(self, model: GilbertElliott | None = None, seed: int = 0) -> None:
        self.model = model if model is not None else GilbertElliott(
            p_good_bad=0.1, p_bad_good=0.25, loss_good=0.05, loss_bad=0.95)
        self.rng = random.Random(seed)

    def lost(self) -> bool:
        return self.model.step(self.rng)


@dataclass
class WireEvent:
    """One message on the wire, in send order."""

    direction: str  # "down" (vehicle to ship) or "up"
    frame: int
    message: Message
    size: int
    lost: bool
    now: float
    wire_total: int  # cumulative wire bytes (both directions, frame headers included)
    down_total: int  # cumulative vehicle-to-ship wire bytes


@dataclass
class Transfer:
    sender: ModalitySender
    receiver: ModalityReceiver
    mtu: int = 256
    down: LossModel = field(default_factory=lambda: Bernoulli(0.0))
    up: LossModel = field(default_factory=lambda: Bernoulli(0.0))
    round_seconds: float = 5.0
    now: float = 0.0
    events: list[WireEvent] = field(default_factory=list)
    on_message: Callable[[WireEvent, list[Product]], None] | None = None

    def __post_init__(self) -> None:
        if self.mtu < 32:
            raise ValueError("the MTU must be at least 32 bytes")
        self._frame = 0
        self._wire = 0
        self._down = 0

    def _send_frame(self, direction: str, messages: list[Message]) -> None:
        if not messages:
            return
        header = FrameHeader(src=2 if direction == "down" else 1, dst=1 if direction == "down" else 2,
                             seq=self._frame % 256)
        frame = wire.pack(messages, self.mtu, header)
        lost = (self.down if direction == "down" else self.up).lost()
        self._frame += 1
        first = True
        for m in messages:
            size = wire.encoded_size(m)
            extra = wire.header_size(header) if first else 0
            first = False
            self._wire += size + extra
            if direction == "down":
                self._down += size + extra
            ev = WireEvent(direction, self._frame - 1, m, size, lost, self.now, self._wire, self._down)
            self.events.append(ev)
            if lost:
                if self.on_message:
                    self.on_message(ev, [])
                continue
            if direction == "down":
                products = self.receiver.receive(m, self.now)
                if self.on_message:
                    self.on_message(ev, products)
            else:
                if self.on_message:
                    self.on_message(ev, [])
                try:
                    self._replies.extend(self.sender.handle(m, self.now))
                except RequestRejected:
                    pass
        _ = frame

    def _frames(self, messages: list[Message]) -> list[list[Message]]:
        batches: list[list[Message]] = []
        batch: list[Message] = []
        used = wire.header_size()
        for m in messages:
            size = wire.encoded_size(m)
            if used + size > self.mtu and batch:
                batches.append(batch)
                batch, used = [], wire.header_size()
            batch.append(m)
            used += size
        if batch:
            batches.append(batch)
        return batches

    def step(self) -> None:
        self.now += self.round_seconds
        self._replies: list[Message] = []
        out = self.sender.fill(self.mtu - wire.header_size(), self.now)
        self._send_frame("down", out)
        for batch in self._frames(self.receiver.poll(self.now)):
            self._send_frame("up", batch)
        for batch in self._frames(self._replies):
            try:
                self._send_frame("down", batch)
            except EncodeError:
                pass

    def run(self, done: Callable[[], bool], max_rounds: int) -> int:
        """Step until ``done()``; return the rounds used (raises ``TimeoutError`` after ``max_rounds``)."""
        for i in range(max_rounds):
            if done():
                return i
            self.step()
        if done():
            return max_rounds
        raise TimeoutError(f"transfer not done after {max_rounds} rounds")


@dataclass
class RegionRun:
    """What :func:`region_transfer` did: the transfer, both sides, the image id, the vehicle-to-
    ship wire bytes before the request (``base_bytes``) and after it (``region_bytes``), what
    topside showed before and after (None: nothing decodable), the request, the region's entry
    in the image product (``state``, ``served``, ``layers_complete`` ...) and the crop that
    answered it, if the vehicle made one."""

    transfer: Transfer
    sender: Any
    receiver: Any
    image_id: int
    base_bytes: int
    region_bytes: int
    before: Any
    after: Any
    request: Message
    region: dict[str, Any]
    #: the vehicle's crop answering the request (its ``enc`` and ``crop``), None when it sent
    #: the region's packets
    crop: Any = None
    #: of ``region_bytes``, the frames that carried only the vehicle's answers (``CommandAck``),
    #: and the ``TransferProgress`` reports, which a request for more of the whole image would
    #: cost as well
    answer_bytes: int = 0
    progress_bytes: int = 0


def region_transfer(image: Any, box: tuple[int, int, int, int], kind: str = "quality", value: float = 30.0, *,
                    mtu: int = 64, base: str = "none", loss: float = 0.0, seed: int = 0,
                    max_rounds: int = 20000, sender_config: dict[str, Any] | None = None) -> RegionRun:
    """Send one image to its ``base`` goal over a simulated link of ``mtu``-byte frames (each
    lost with probability ``loss`` both ways, seeded), then ask for the rectangle ``box`` at a
    goal with one ``ImageRegionRequest`` and run until the vehicle answered and, when it
    accepted, has nothing more to send. ``sender_config`` adds sender options (``crops``
    ...). Raises ``ConfigError`` for an absurd request (before it is sent) and
    ``TimeoutError`` after ``max_rounds`` rounds of either phase."""
    from coex.messages import AckStatus, CommandAck, TransferProgress

    from . import ImageInput, ImageryModality

    modality = ImageryModality()
    sender = modality.sender({"default_goal": base, "progress_interval": 1e9, **(sender_config or {})})
    receiver = modality.receiver({"max_ack_bytes": min(81, mtu - wire.header_size())})
    sender.ingest(ImageInput(image, time=0.0), 0.0)
    (image_id, _tx), = sender.images.items()
    t = Transfer(sender, receiver, mtu=mtu, down=Bernoulli(loss, seed), up=Bernoulli(loss, seed + 1))
    t.run(lambda: image_id in receiver.images and not sender.order(), max_rounds)
    t.step()  # the last acks

    def down() -> int:
        return max((e.down_total for e in t.events if e.direction == "down"), default=0)

    before, base_bytes = receiver.image(image_id), down()
    request = receiver.request_region(image_id, box, kind, value, t.now)
    start = len(t.events)

    def answered() -> CommandAck | None:
        return next((e.message for e in t.events[start:] if e.direction == "down" and not e.lost
                     and isinstance(e.message, CommandAck) and e.message.command_id == request.command_id), None)

    t.run(lambda: (a := answered()) is not None and (a.status != AckStatus.ACCEPTED or not sender.order()),
          max_rounds)
    t.step()
    product = next(p for p in receiver.products() if p.kind == "image" and p.meta.get("image_id") == image_id)
    crop = next((c for c in sender.images.values() if (o := c.crop) is not None
                 and o.parent == image_id and o.command_id == request.command_id), None)
    frames: dict[int, list[WireEvent]] = {}
    for e in t.events[start:]:
        if e.direction == "down":
            frames.setdefault(e.frame, []).append(e)
    answers = sum(wire.header_size() + sum(e.size for e in es) for es in frames.values()
                  if all(isinstance(e.message, CommandAck) for e in es))
    progress = sum(e.size for es in frames.values() for e in es if isinstance(e.message, TransferProgress))
    return RegionRun(t, sender, receiver, image_id, base_bytes, down() - base_bytes, before,
                     receiver.image(image_id), request, product.meta["regions"][-1], crop, answers, progress)

"""A deterministic two-way simulation of an imagery transfer over lossy links (no clock, no I/O):
the core's one sender↔receiver loop (:class:`coex_core.loopback.RoundTrip`, whose
:class:`~coex_core.loopback.LossModel`, :class:`~coex_core.loopback.Bernoulli` and
:class:`~coex_core.loopback.WireEvent` this module re-exports) as :class:`Transfer`.

Used by ``coex image roundtrip`` and ``coex image region`` (:func:`region_transfer`), the tests
and the benchmark. Each round the vehicle fills one
frame of at most ``mtu`` bytes; topside takes what arrives and answers with acks and requests in
as many frames as they need; the vehicle handles those and its immediate replies (command acks)
go down in one more frame. Loss is drawn per frame from seeded models: independent
(:class:`Bernoulli`) or bursty (:class:`Burst`: the channel simulator's
:class:`~coex_core.acoustic.GilbertElliott` with its own random stream).
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from coex import (
    Bernoulli,
    GilbertElliott,
    LossModel,
    ModalityReceiver,
    ModalitySender,
    Product,
    RequestRejected,
    RoundTrip,
    WireEvent,
    wire,
)
from coex.messages import Message

__all__ = ["Bernoulli", "Burst", "LossModel", "RegionRun", "Transfer", "WireEvent", "region_transfer"]


class Burst(LossModel):
    """Burst loss: the acoustic channel's two-state :class:`~coex_core.acoustic.GilbertElliott`
    model (the one loss model of CoEx), stepped once per frame with a seeded random stream."""

    def __init__(self, model: GilbertElliott | None = None, seed: int = 0) -> None:
        self.model = model if model is not None else GilbertElliott(
            p_good_bad=0.1, p_bad_good=0.25, loss_good=0.05, loss_bad=0.95)
        self.rng = random.Random(seed)

    def lost(self) -> bool:
        return self.model.step(self.rng)


class Transfer(RoundTrip):
    """:class:`~coex_core.loopback.RoundTrip` as ``coex image`` runs it: each side gets the
    other's objects, the vehicle's answers arrive in the same round."""

    def __init__(self, sender: ModalitySender, receiver: ModalityReceiver, mtu: int = 256,
                 down: LossModel | None = None, up: LossModel | None = None, round_seconds: float = 5.0,
                 now: float = 0.0, on_message: Callable[[WireEvent, list[Product]], None] | None = None) -> None:
        if mtu < 32:
            raise ValueError("the MTU must be at least 32 bytes")
        super().__init__(sender, receiver, mtu=mtu, down=down, up=up, round_seconds=round_seconds, now=now,
                         rejects=(RequestRejected,), on_message=on_message)


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

"""A sender and a receiver joined by a lossy in-memory link, driven round by round.

Each round: the sender fills one frame (``frame_budget`` bytes) that crosses the forward link,
the receiver takes what arrives and polls for requests that cross the return link in one frame,
and the sender handles them. Frames are real wire frames (``coex_core.wire.pack``/``unpack``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from coex_core import wire
from coex_core.errors import EncodeError, RequestRejected
from coex_core.loopback import LoopbackLink
from coex_core.messages import FrameHeader, Message
from coex_core.modality import ModalityReceiver, ModalitySender


@dataclass
class LinkedPair:
    sender: ModalitySender
    receiver: ModalityReceiver
    loss: float = 0.3
    seed: int = 1
    frame_budget: int = 256
    round_seconds: float = 5.0
    now: float = 0.0
    sent_messages: list[Message] = field(default_factory=list)
    received_messages: list[Message] = field(default_factory=list)
    requests: list[Message] = field(default_factory=list)
    rejected: list[Message] = field(default_factory=list)

    def __post_init__(self) -> None:
        rate = 1e9  # timing is this harness's business, not the link's
        self.down = LoopbackLink(mtu=self.frame_budget, bytes_per_s=rate, loss=self.loss, seed=self.seed)
        self.up = LoopbackLink(mtu=self.frame_budget, bytes_per_s=rate, loss=self.loss, seed=self.seed + 1000)
        self._seq = 0

    def _frames(self, messages: list[Message]) -> list[bytes]:
        """Pack messages greedily into frames of at most ``frame_budget`` bytes."""
        frames, batch, used = [], [], wire.header_size()
        for m in messages:
            size = wire.encoded_size(m)
            if used + size > self.frame_budget and batch:
                frames.append(self._pack(batch))
                batch, used = [], wire.header_size()
            batch.append(m)
            used += size
        if batch:
            frames.append(self._pack(batch))
        return frames

    def _pack(self, batch: list[Message]) -> bytes:
        self._seq = (self._seq + 1) % 256
        return wire.pack(batch, self.frame_budget, FrameHeader(src=2, dst=1, seq=self._seq))

    def step(self) -> None:
        self.now += self.round_seconds
        budget = self.frame_budget - wire.header_size()
        out = self.sender.fill(budget, self.now)
        total = sum(wire.encoded_size(m) for m in out)
        if total > budget:
            raise AssertionError(f"sender returned {total} B for a budget of {budget} B")
        self.sent_messages.extend(out)
        if out:
            self.down.a.send(wire.pack(out, self.frame_budget, FrameHeader(src=2, dst=1)))
        while (frame := self.down.b.recv(timeout=1.0)) is not None:
            for m in wire.unpack(frame):
                self.received_messages.append(m)
                self.receiver.receive(m, self.now)
        reqs = self.receiver.poll(self.now)
        self.requests.extend(reqs)
        for frame in self._frames(reqs):
            self.up.a.send(frame)
        while (frame := self.up.b.recv(timeout=1.0)) is not None:
            for m in wire.unpack(frame):
                try:
                    for reply in self.sender.handle(m, self.now):
                        self._deliver_reply(reply)
                except RequestRejected:
                    self.rejected.append(m)

    def _deliver_reply(self, reply: Message) -> None:
        try:
            frame = wire.pack([reply], self.frame_budget)
        except EncodeError:
            return
        self.down.a.send(frame)


def run_until(
    pair: LinkedPair, done: Callable[[], bool], max_rounds: int
) -> int:
    """Step until ``done()``; return the rounds used, or raise AssertionError after ``max_rounds``."""
    for i in range(max_rounds):
        if done():
            return i
        pair.step()
    if done():
        return max_rounds
    raise AssertionError(f"not converged after {max_rounds} rounds ({pair.now:.0f} simulated s)")


def ingest_all(sender: ModalitySender, inputs: Any) -> float:
    last = 0.0
    for now, data in inputs:
        sender.ingest(data, now)
        last = max(last, now)
    return last


_ = Mapping

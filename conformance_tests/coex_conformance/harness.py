"""A sender and a receiver joined by a lossy in-memory link, driven round by round: the core's
one sender↔receiver loop (:class:`coex.RoundTrip`) as the kit runs it.

Each round: the sender fills one frame (``frame_budget`` bytes) that crosses the forward link,
the receiver takes what arrives and polls for requests that cross the return link in frames,
and the sender handles them. Frames are real wire frames (``coex.wire.pack``/``unpack``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from coex import Bernoulli, Message, ModalityReceiver, ModalitySender, RoundTrip


class LinkedPair(RoundTrip):
    """:class:`~coex.RoundTrip` as the conformance kit runs it: each side gets the
    messages decoded from the frame's bytes, a sender that fills beyond ``frame_budget`` fails
    the test, and the sender's answers go down one a frame with the next round's frame."""

    def __init__(self, sender: ModalitySender, receiver: ModalityReceiver, loss: float = 0.3, seed: int = 1,
                 frame_budget: int = 256, round_seconds: float = 5.0, now: float = 0.0) -> None:
        super().__init__(sender, receiver, mtu=frame_budget, down=Bernoulli(loss, seed),
                         up=Bernoulli(loss, seed + 1000), round_seconds=round_seconds, now=now, decode=True,
                         replies_next_round=True, overfill=AssertionError)
        self.loss = loss
        self.seed = seed
        self.frame_budget = frame_budget

    @property
    def sent_messages(self) -> list[Message]:
        return self.sent

    @property
    def received_messages(self) -> list[Message]:
        return self.received


def run_until(
    pair: LinkedPair, done: Callable[[], bool], max_rounds: int
) -> int:
    """Step until ``done()``; return the rounds used, or raise AssertionError after ``max_rounds``."""
    try:
        return pair.run(done, max_rounds)
    except TimeoutError:
        raise AssertionError(f"not converged after {max_rounds} rounds ({pair.now:.0f} simulated s)") from None


def ingest_all(sender: ModalitySender, inputs: Any) -> float:
    last = 0.0
    for now, data in inputs:
        sender.ingest(data, now)
        last = max(last, now)
    return last



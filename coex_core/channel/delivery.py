"""Delivery of modality messages and measured frame loss of a channel manager.

* **Delivery tracking.** Every message a modality sender produced (pulled by ``fill`` or
  ``spare``) on a stream that is not ``ack_required`` is remembered under the frames that carried
  it. When a :class:`~coex_core.messages.FrameAck` covers one of those frames, the node passes the
  message to ``ModalitySender.acked``; when none of them is acknowledged, the manager passes it
  to ``ModalitySender.lost``: as soon as a frame ack shows that the peer, acknowledging frames of
  a later packet, did not receive them (a node acknowledges every frame it received in its next
  transmission), or else after the link's ``ack_timeout``. So a sender knows what
  reached topside without a modality-specific ack (the bathymetry sender re-sends lost subgrids
  from its spare work).
* **Frame loss.** Each link measures the loss of its own frames from the frame acks (a frame
  that carried anything but frame acks and was not acknowledged, by the same rule, counts as
  lost; this is round-trip loss, a little above one-way loss), over the last
  :data:`LOSS_WINDOW` frames, and, before it has heard enough acks, the loss of the peer's frames
  it receives (gaps in their sequence numbers). :meth:`copies` turns the estimate into the
  number of copies an urgent message gets when capacity is spare.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

from ..messages import FrameHeader, Message
from ..state import persistent
from .events import SenderFailed
from .tdma import LinksMixin

__all__ = ["LOSS_WINDOW", "REDUNDANCY_TARGET", "DeliveryMixin"]

#: frames (sent, or received from the peer) that the loss estimate looks back over
LOSS_WINDOW = 256
#: a jump in the peer's seqs up to this many frames counts as loss (larger: a restart, an outage)
MAX_GAP = 64
#: fewest outcomes before an estimate is trusted
MIN_OUTCOMES = 8
#: messages given to ``lost`` that a late ack can still turn into ``acked``
LOST_REMEMBERED = 4096
#: an urgent message gets enough copies that all are lost with at most this probability
REDUNDANCY_TARGET = 0.05


@persistent("channel.Delivery")
@dataclass
class _Delivery:
    """A modality message in flight: its stream, when it counts as lost, the frames that carry it."""

    stream: int
    message: Message
    deadline: float
    frames: list[tuple[int, int]] = field(default_factory=list)


class DeliveryMixin(LinksMixin):
    def _delivery_state(self) -> None:
        """Create the delivery and loss bookkeeping (``__init__``, and a manager restored from a
        store saved before it existed)."""
        if getattr(self, "_deliveries", None) is not None:
            return
        #: token -> message in flight
        self._deliveries: dict[int, _Delivery] = {}
        self._delivery_ids = 0
        #: link -> seq -> tokens carried by that frame
        self._delivery_frames: dict[int, dict[int, list[int]]] = {}
        #: link -> tokens in the order their deadlines fall (one ack timeout per link)
        self._delivery_order: dict[int, deque[int]] = {}
        #: link -> seq -> (sent at, deadline) of every sent frame the peer should acknowledge
        self._frame_watch: dict[int, dict[int, tuple[float, float]]] = {}
        #: link -> recent outcomes of our frames (1 acknowledged, 0 not)
        self._tx_outcomes: dict[int, deque[int]] = {}
        #: link -> recent outcomes of the peer's frames (1 received, 0 a gap in its seqs)
        self._rx_outcomes: dict[int, deque[int]] = {}
        #: (src, link) -> seq of the newest frame heard from that peer
        self._rx_last: dict[tuple[int, int], int] = {}
        #: token -> messages given to ``lost`` whose frames' late ack may still come: it then
        #: goes to ``acked`` (so the sender does not send again what arrived)
        self._lost_recs: OrderedDict[int, _Delivery] = OrderedDict()

    def _after_restore(self) -> None:
        self._delivery_state()
        for k in ("delivered", "lost", "spare_bytes", "redundant_bytes"):
            self.stats.setdefault(k, 0)
        if getattr(self, "_lost_recs", None) is None:
            self._lost_recs = OrderedDict()
        if getattr(self, "_spare_turn", None) is None:
            self._spare_turn: dict[int, float] = {}

    # ----------------------------------------------------------------------- tracking
    def _track(self, link: int, stream: int, message: Message, now: float, token: int | None = None) -> int:
        """Remember ``message`` (from ``stream``'s sender) as sent; returns its token (pass it
        again for a copy in another frame, then :meth:`_carried` records each frame)."""
        if token is not None:
            return token
        self._delivery_ids += 1
        st = self._links[link]
        self._deliveries[self._delivery_ids] = _Delivery(stream, message, now + st.ack_timeout)
        self._delivery_order.setdefault(link, deque()).append(self._delivery_ids)
        return self._delivery_ids

    def _carried(self, link: int, seq: int, token: int) -> None:
        rec = self._deliveries.get(token)
        if rec is None:
            return
        rec.frames.append((link, seq))
        self._delivery_frames.setdefault(link, {}).setdefault(seq, []).append(token)

    def _watch_frame(self, link: int, seq: int, now: float) -> None:
        self._frame_watch.setdefault(link, {})[seq] = (now, now + self._links[link].ack_timeout)

    def _forget_frame(self, link: int, seq: int) -> None:
        """``seq`` is used again: the old frame's ack can no longer be told apart."""
        self._delivery_frames.get(link, {}).pop(seq, None)
        if self._frame_watch.get(link, {}).pop(seq, None) is not None:
            self._outcome(self._tx_outcomes, link, 0)

    def _delivered(self, link: int, seqs: list[int], now: float) -> list[tuple[int, Message]]:
        """The frames ``seqs`` on ``link`` were acknowledged (one FrameAck): the modality
        messages they delivered. The peer acknowledges every frame it received in its next
        transmission, so a watched frame sent in a packet before the newest one this ack covers,
        and not acknowledged, was lost: its messages go to their senders' ``lost`` at once,
        without waiting for the ack timeout."""
        watch = self._frame_watch.get(link, {})
        newest = -math.inf
        out = []
        fates: list[tuple[float, int]] = []  # (sent, 1 acked / 0 lost), recorded in send order
        for seq in seqs:
            w = watch.pop(seq, None)
            if w is not None:
                fates.append((w[0], 1))
                newest = max(newest, w[0])
            for token in self._delivery_frames.get(link, {}).pop(seq, ()):
                rec = self._deliveries.pop(token, None)
                if rec is None:
                    rec = self._lost_recs.pop(token, None)  # a late ack: it arrived after all
                    if rec is not None:
                        self.stats["late_acks"] = self.stats.get("late_acks", 0) + 1
                if rec is not None:
                    self.stats["delivered"] += 1
                    out.append((rec.stream, rec.message))
        # strictly earlier packets only: frames of the newest acknowledged packet may still be
        # on their way through the peer's receiver (it may build its ack between two frames)
        for seq in [q for q, (sent, _) in watch.items() if sent < newest]:
            fates.append((watch.pop(seq)[0], 0))
            self._frame_lost(link, seq, now)
        for _, ok in sorted(fates):
            self._outcome(self._tx_outcomes, link, ok)
        return out

    def _frame_lost(self, link: int, seq: int, now: float) -> None:
        """Frame ``seq`` on ``link`` did not arrive: a message none of whose frames arrived is
        lost. (The frame's tokens stay recorded until its seq is used again: a late ack of it
        still counts.)"""
        for token in self._delivery_frames.get(link, {}).get(seq, ()):
            rec = self._deliveries.get(token)
            if rec is None:
                continue
            if (link, seq) in rec.frames:
                rec.frames.remove((link, seq))
            if not rec.frames:
                del self._deliveries[token]
                self.stats["lost_inferred"] = self.stats.get("lost_inferred", 0) + 1
                self._lost(rec, now, token)

    def _lost(self, rec: _Delivery, now: float, token: int) -> None:
        self._lost_recs[token] = rec
        while len(self._lost_recs) > LOST_REMEMBERED:
            self._lost_recs.popitem(last=False)
        self.stats["lost"] += 1
        s = self._streams.get(rec.stream)
        if s is None or s.sender is None:
            return
        try:
            s.sender.lost(rec.message, now)  # declared on ModalitySender (default: nothing)
        except Exception as exc:  # a sender's hook never stops the channel
            self.stats["sender_failures"] += 1
            self._events.append(SenderFailed(now, rec.stream, f"lost() failed: {type(exc).__name__}: {exc}"))

    def _expire_deliveries(self, now: float) -> None:
        """Messages none of whose frames was acknowledged in time go to their sender's ``lost``;
        frames never acknowledged count towards the link's loss."""
        for order in self._delivery_order.values():
            while order:
                rec = self._deliveries.get(order[0])
                if rec is not None and rec.deadline > now:
                    break
                token = order.popleft()
                if rec is None:
                    continue  # delivered, or already found lost
                del self._deliveries[token]
                self._lost(rec, now, token)
        for link, watch in self._frame_watch.items():
            late = [seq for seq, (_, t) in watch.items() if t <= now]
            for seq in late:
                del watch[seq]
                self._outcome(self._tx_outcomes, link, 0)

    def _tick(self, now: float) -> None:
        super()._tick(now)
        self._expire_deliveries(now)

    # --------------------------------------------------------------------------- loss
    @staticmethod
    def _outcome(book: dict[int, deque[int]], link: int, ok: int) -> None:
        book.setdefault(link, deque(maxlen=LOSS_WINDOW)).append(ok)

    def _heard(self, link: int, header: FrameHeader) -> None:
        """A good frame from the peer: a gap in its seqs counts as frames lost on the way in."""
        key = (header.src, link)
        last = self._rx_last.get(key)
        self._rx_last[key] = header.seq
        if last is not None:
            gap = (header.seq - last - 1) % 256
            if gap < MAX_GAP:  # a larger jump is a restart or a long outage, not loss
                for _ in range(gap):
                    self._outcome(self._rx_outcomes, link, 0)
        self._outcome(self._rx_outcomes, link, 1)

    def link_state(self, link: int) -> dict[str, Any]:
        """:meth:`LinksMixin.link_state`, with the measured frame ``loss`` and the ``copies`` an
        urgent message gets now."""
        out = super().link_state(link)
        out["loss"] = self.frame_loss(link)
        out["copies"] = self.copies(link)
        return out

    def frame_loss(self, link: int) -> float | None:
        """The measured frame loss on ``link``: of our frames (from the peer's frame acks) once
        :data:`MIN_OUTCOMES` are known, else of the peer's frames; ``None`` before either."""
        for book in (self._tx_outcomes, self._rx_outcomes):
            seen = book.get(link)
            if seen is not None and len(seen) >= MIN_OUTCOMES:
                return 1.0 - sum(seen) / len(seen)
        return None

    def copies(self, link: int) -> int:
        """How many frames of a packet an urgent message (a frame ack, a tier-0 message, the
        first answer to a request) goes in when capacity is spare: enough that all of them are
        lost with probability at most :data:`REDUNDANCY_TARGET` at the measured loss, at most the
        link's frames per packet, and 1 with spare traffic off or no loss measured."""
        st = self._link(link)
        p = self.frame_loss(link)
        if st.spare <= 0 or p is None or p <= REDUNDANCY_TARGET:
            return 1
        if p >= 1.0:
            return st.cfg.n_frames
        return max(1, min(st.cfg.n_frames, math.ceil(math.log(REDUNDANCY_TARGET) / math.log(p))))

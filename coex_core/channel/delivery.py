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
from .tdma import LinksMixin

__all__ = ["LOSS_WINDOW", "REDUNDANCY_TARGET", "DeliveryMixin"]

#: frames (sent, or received from the peer) that the loss estimate looks back over
LOSS_WINDOW = 256
#: a jump in the peer's seqs up to this many frames counts as loss (larger: a restart, an outage)
MAX_GAP = 64
#: fewest outcomes before an estimate is trusted
MIN_OUTCOMES = 8
#: messages given to ``lost`` that a late ack can still turn into ``acked``, at most (a message is
#: forgotten sooner, when the seqs of the frames that carried it are used again)
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


def delivery_fields() -> dict[str, Any]:
    """The delivery and loss bookkeeping of a new manager, by attribute (also what
    ``channel.ChannelManager`` version 1, saved before it existed, is upgraded with)."""
    return {
        #: token -> message in flight
        "_deliveries": {},
        "_delivery_ids": 0,
        #: link -> seq -> tokens carried by that frame
        "_delivery_frames": {},
        #: link -> tokens in the order their deadlines fall (one ack timeout per link)
        "_delivery_order": {},
        #: link -> seq -> (sent at, deadline) of every sent frame the peer should acknowledge
        "_frame_watch": {},
        #: link -> recent outcomes of our frames (1 acknowledged, 0 not)
        "_tx_outcomes": {},
        #: link -> recent outcomes of the peer's frames (1 received, 0 a gap in its seqs)
        "_rx_outcomes": {},
        #: (src, link) -> seq of the newest frame heard from that peer
        "_rx_last": {},
        #: token -> messages given to ``lost`` whose frames' late ack may still come: it then
        #: goes to ``acked`` (so the sender does not send again what arrived)
        "_lost_recs": OrderedDict(),
    }


def peer_fields() -> dict[str, Any]:
    """The per-peer bookkeeping of a network of several nodes (also what
    ``channel.ChannelManager`` version 3, saved before it existed, is upgraded with)."""
    return {
        #: link -> seq -> the node a watched frame was addressed to (0: broadcast)
        "_frame_dst": {},
        #: (link, peer) -> recent outcomes of our frames addressed to ``peer`` (0: broadcast)
        "_peer_tx": {},
        #: (link, peer) -> recent outcomes of ``peer``'s frames (1 received, 0 a gap)
        "_peer_rx": {},
        #: (link, peer) -> when a good frame of ``peer`` was last heard (addressed to us or not)
        "_peer_heard": {},
    }


class DeliveryMixin(LinksMixin):
    _deliveries: dict[int, _Delivery]
    _delivery_ids: int
    _delivery_frames: dict[int, dict[int, list[int]]]
    _delivery_order: dict[int, deque[int]]
    _frame_watch: dict[int, dict[int, tuple[float, float]]]
    _tx_outcomes: dict[int, deque[int]]
    _rx_outcomes: dict[int, deque[int]]
    _rx_last: dict[tuple[int, int], int]
    _lost_recs: OrderedDict[int, _Delivery]
    _frame_dst: dict[int, dict[int, int]]
    _peer_tx: dict[tuple[int, int], deque[int]]
    _peer_rx: dict[tuple[int, int], deque[int]]
    _peer_heard: dict[tuple[int, int], float]
    #: stream -> when its sender last got spare capacity (the spare tier takes turns)
    _spare_turn: dict[int, float]

    def _delivery_state(self) -> None:
        """Create the delivery and loss bookkeeping (``__init__``)."""
        for k, v in {**delivery_fields(), **peer_fields()}.items():
            setattr(self, k, v)

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

    def _watch_frame(self, link: int, seq: int, now: float, dst: int = 0) -> None:
        self._frame_watch.setdefault(link, {})[seq] = (now, now + self._links[link].ack_timeout)
        self._frame_dst.setdefault(link, {})[seq] = dst

    def _tx_outcome(self, link: int, seq: int, ok: int) -> None:
        """The fate of our frame ``seq``: the link's loss, and that of the frame's destination."""
        self._outcome(self._tx_outcomes, link, ok)
        peer = self._frame_dst.get(link, {}).pop(seq, None)
        if peer is not None:
            self._outcome(self._peer_tx, (link, peer), ok)

    def _answerable(self, link: int, seq: int, src: int | None) -> bool:
        """Whether node ``src`` was to acknowledge our frame ``seq``: it was addressed to it, or
        to every node (or ``src`` or the frame's destination is not known)."""
        dst = self._frame_dst.get(link, {}).get(seq)
        return src is None or dst is None or dst in (0, src)

    def _forget_frame(self, link: int, seq: int) -> None:
        """``seq`` is used again: the old frame's ack can no longer be told apart, so a message
        given to ``lost`` that no other recorded frame carried can no longer be acknowledged late:
        it is forgotten (the saved state holds only what an ack can still reach)."""
        tokens = self._delivery_frames.get(link, {}).pop(seq, ())
        for token in tokens:
            if token in self._lost_recs and not any(
                    token in carried for frames in self._delivery_frames.values() for carried in frames.values()):
                del self._lost_recs[token]
        if self._frame_watch.get(link, {}).pop(seq, None) is not None:
            self._tx_outcome(link, seq, 0)

    def _delivered(self, link: int, seqs: list[int], now: float,
                   src: int | None = None) -> list[tuple[int, Message]]:
        """The frames ``seqs`` on ``link`` were acknowledged (one FrameAck, by node ``src``):
        the modality messages they delivered. The peer acknowledges every frame it received in
        its next transmission, so a watched frame addressed to it (or broadcast) sent in a
        packet before the newest one this ack covers, and not acknowledged, was lost: its
        messages go to their senders' ``lost`` at once, without waiting for the ack timeout.
        (Frames addressed to other nodes wait for their own acks.)"""
        watch = self._frame_watch.get(link, {})
        newest = -math.inf
        out = []
        fates: list[tuple[float, int, int]] = []  # (sent, seq, 1 acked / 0 lost), in send order
        for seq in seqs:
            w = watch.pop(seq, None)
            if w is not None:
                fates.append((w[0], seq, 1))
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
        for seq in [q for q, (sent, _) in watch.items() if sent < newest and self._answerable(link, q, src)]:
            fates.append((watch.pop(seq)[0], seq, 0))
            self._frame_lost(link, seq, now)
        for _, seq, ok in sorted(fates):
            self._tx_outcome(link, seq, ok)
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
            self._sender_failed(now, rec.stream, f"lost() failed: {type(exc).__name__}: {exc}")

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
                self._tx_outcome(link, seq, 0)

    def _tick(self, now: float) -> None:
        super()._tick(now)
        self._expire_deliveries(now)

    # --------------------------------------------------------------------------- loss
    @staticmethod
    def _outcome(book: dict[Any, deque[int]], key: Any, ok: int) -> None:
        book.setdefault(key, deque(maxlen=LOSS_WINDOW)).append(ok)

    def _heard(self, link: int, header: FrameHeader, now: float | None = None) -> None:
        """A good frame from the peer: a gap in its seqs counts as frames lost on the way in
        (for the link, and for that peer)."""
        key = (header.src, link)
        peer = (link, header.src)
        if now is not None:
            self._peer_heard[peer] = now
        last = self._rx_last.get(key)
        self._rx_last[key] = header.seq
        if last is not None:
            gap = (header.seq - last - 1) % 256
            if gap < MAX_GAP:  # a larger jump is a restart or a long outage, not loss
                for _ in range(gap):
                    self._outcome(self._rx_outcomes, link, 0)
                    self._outcome(self._peer_rx, peer, 0)
        self._outcome(self._rx_outcomes, link, 1)
        self._outcome(self._peer_rx, peer, 1)

    def link_state(self, link: int) -> dict[str, Any]:
        """:meth:`LinksMixin.link_state`, with the measured frame ``loss`` and the ``copies`` an
        urgent message gets now."""
        out = super().link_state(link)
        out["loss"] = self.frame_loss(link)
        out["copies"] = self.copies(link)
        out["peers"] = {p: {"loss": self.frame_loss(link, p), "last_heard": self._peer_heard.get((link, p))}
                        for p in self.peers(link)}
        return out

    def peers(self, link: int) -> list[int]:
        """The nodes heard on ``link`` or sent frames to (0: broadcast), by id."""
        keys = set(self._peer_tx) | set(self._peer_rx) | set(self._peer_heard)
        return sorted({p for lk, p in keys if lk == link})

    def last_heard(self, link: int, peer: int) -> float | None:
        """When a good frame of node ``peer`` was last heard on ``link`` (``None``: never)."""
        return self._peer_heard.get((link, peer))

    def frame_loss(self, link: int, peer: int | None = None) -> float | None:
        """The measured frame loss on ``link``: of our frames (from the peer's frame acks) once
        :data:`MIN_OUTCOMES` are known, else of the peer's frames; ``None`` before either.
        With ``peer``, the loss between this node and that one: of our frames addressed to it
        (``peer`` 0: our broadcast frames), else of its frames."""
        books: tuple[tuple[dict[Any, deque[int]], Any], ...] = (
            ((self._tx_outcomes, link), (self._rx_outcomes, link)) if peer is None else
            ((self._peer_tx, (link, peer)), (self._peer_rx, (link, peer))))
        for book, key in books:
            seen = book.get(key)
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

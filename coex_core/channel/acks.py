"""Frame acknowledgements of a channel manager: what to ack, what an ack clears, re-sends.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math

from ..messages import (
    FrameAck,
    FrameAckEntry,
    FrameHeader,
    Message,
)
from .delivery import DeliveryMixin
from .events import Acked
from .links import (
    MAX_ACK_ENTRIES,
    SEQ_MODULUS,
)

__all__ = ["AcksMixin"]


class AcksMixin(DeliveryMixin):
    # ============================================================================== acks
    def on_ack(self, ack: FrameAck, now: float, src: int | None = None) -> int:
        """Apply a :class:`FrameAck` (received on any link, from node ``src`` if known): every
        ack-required message packed in an acknowledged frame leaves its queue, and every link's
        pending records. Returns the number of ack-required messages cleared."""
        return len(self._acknowledge(ack, now, src)[0])

    def acknowledge(self, ack: FrameAck, now: float, src: int | None = None) -> list[tuple[int, Message]]:
        """:meth:`on_ack`, returning the ``(stream, message)`` pairs it cleared (each also gives
        an :class:`Acked` event), then the modality messages of other streams that the
        acknowledged frames delivered (see :mod:`.delivery`); the node gives each to the
        sender that produced it (``ModalitySender.acked``). ``src`` (the node whose frame
        carried the ack) keeps the loss inference to the frames that node was to acknowledge."""
        cleared, delivered = self._acknowledge(ack, now, src)
        return cleared + delivered

    def _acknowledge(self, ack: FrameAck, now: float, src: int | None = None
                     ) -> tuple[list[tuple[int, Message]], list[tuple[int, Message]]]:
        if ack.node != self.node_id or ack.link not in self._links:
            return [], []
        st = self._links[ack.link]
        cleared: list[tuple[int, Message]] = []
        delivered: list[tuple[int, Message]] = []
        seqs = [(ent.seq + i) % SEQ_MODULUS for ent in ack.entries for i in range(8) if ent.frames >> i & 1]
        delivered.extend(self._delivered(ack.link, seqs, now, src))
        for ent in ack.entries:
            for i in range(8):
                if not ent.frames >> i & 1:
                    continue
                seq = (ent.seq + i) % SEQ_MODULUS
                for sid, eid in st.sent.pop(seq, []):
                    e = self._find(sid, eid)
                    if e is None:
                        continue
                    q = self._streams[sid].queue
                    self._forget(e)
                    q.entries.remove(e)
                    cleared.append((sid, e.message))
                    self.stats["acked"] += 1
                    self._events.append(Acked(now, sid, e.message, now - (e.first_sent or now), ack.link))
        return cleared, delivered

    def on_frame(self, link: int, header: FrameHeader, now: float, ackable: bool = True,
                 addressed: bool = True) -> None:
        """Bookkeeping for a good frame received on ``link``: the watchdog, the peer's schedule
        version, and (if ``ackable``) the frame ack to send back. A frame addressed to another
        node (``addressed`` False: overheard in a network of several nodes) counts for the
        watchdog, the sender's loss and schedule version, and is neither counted as received
        nor acknowledged."""
        st = self._links.get(link)
        if st is None or header.src == self.node_id:
            return
        st.last_heard = now
        self._heard(link, header, now)
        if not addressed:
            ackable = False
        else:
            st.frames_rx += 1
        if self.ack_frames and ackable:
            seqs = self._to_ack.setdefault((header.src, link), {})
            seqs[header.seq] = now  # a newer use of a seq: the ack names the newest
            for other in self._links.values():
                other.idle_until = -math.inf
        v = header.schedule
        if v == st.current.version:
            return
        for cid, prop in list(st.proposed.items()):
            if prop.schedule.version == v:  # the vehicle switched: our proposal was accepted
                st.proposed.pop(cid)
                self._switch(link, prop.schedule, now, "peer")
                return
        if st.pending is not None and st.pending.schedule.version == v:
            self._switch(link, st.pending.schedule, now, "peer")
            return
        settled = st.switched_at is None or now - st.switched_at >= st.current.cycle
        if v == st.safe.version and settled:  # the peer's watchdog fired
            self._fallback(link, now, "peer")

    def _take_acks(self, now: float) -> list[Message]:
        """The frame acks to send now. A frame received longer ago than its link's
        ``ack_timeout`` is not acknowledged any more: its sender has made its messages sendable
        again by then, and may have reused the seq (after 256 frames), so a late ack could
        clear messages of a newer frame that never arrived (a restarted node replaying its
        journal, a long outage)."""
        out: list[Message] = []
        self._ack_times = {}
        for (src, link), pending in sorted(self._to_ack.items()):
            st = self._links.get(link)
            horizon = st.ack_timeout if st is not None else math.inf
            seqs = []
            for seq, t in pending.items():
                if now - t > horizon:
                    self.stats["stale_acks"] += 1
                    continue
                seqs.append(seq)
                self._ack_times[(src, link, seq)] = t
            if not seqs:
                continue
            entries: list[FrameAckEntry] = []
            for seq in seqs:
                for k, ent in enumerate(entries):
                    d = (seq - ent.seq) % SEQ_MODULUS
                    if d < 8:
                        entries[k] = FrameAckEntry(ent.seq, ent.frames | 1 << d)
                        break
                else:
                    entries.append(FrameAckEntry(seq, 1))
            for i in range(0, len(entries), MAX_ACK_ENTRIES):
                out.append(FrameAck(src, link, tuple(entries[i:i + MAX_ACK_ENTRIES])))
        self._to_ack.clear()
        return out

    def _requeue_ack(self, ack: Message, now: float) -> None:
        assert isinstance(ack, FrameAck)
        seqs = self._to_ack.setdefault((ack.node, ack.link), {})
        for ent in ack.entries:
            for i in range(8):
                seq = (ent.seq + i) % SEQ_MODULUS
                if ent.frames >> i & 1 and seq not in seqs:
                    seqs[seq] = self._ack_times.get((ack.node, ack.link, seq), now)

"""Packet building of a channel manager: the priority contest, pulls from senders, frames.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math

from ..auth import TRAILER_BYTES
from ..errors import CoexError, EncodeError
from ..messages import (
    FrameHeader,
    Message,
)
from ..wire import encoded_size, header_size, pack
from .acks import AcksMixin
from .events import (
    Dropped,
    SenderFailed,
)
from .links import (
    SEQ_MODULUS,
    Transmission,
    _Link,
)
from .queue import Entry, StreamQueue
from .schedule import SlotWindow

__all__ = ["PackingMixin"]


class PackingMixin(AcksMixin):
    # ============================================================================= build
    def poll(self, now: float) -> list[Transmission]:
        """Housekeeping, then one packet for every link that may transmit now."""
        self._tick(now)
        out = []
        for link in sorted(self._links):
            if self.can_transmit(link, now):
                tx = self.build(link, now)
                if tx is not None:
                    out.append(tx)
                else:
                    self._links[link].idle_until = now + self.idle_interval
        return out

    def build(self, link: int, now: float) -> Transmission | None:
        """Pack one packet for ``link`` now (``None`` when there is nothing to send).

        Order per frame: pending frame acks, then the contest (tier first, then value), then
        pulls from modality senders when no queued message fits."""
        st = self._link(link)
        cfg = st.cfg
        self._build_no += 1
        w = self._window(st, now)
        hdr_bytes = header_size(FrameHeader(crc=cfg.crc))
        # stream -> largest budget for which it had nothing (inf: failed or slow, skip it)
        exhausted: dict[int, float] = {}
        t0 = self.clock() if self.clock is not None else 0.0
        acks = self._take_acks(now)
        signer = self.signer
        reserve = TRAILER_BYTES if signer is not None and any(
            self.is_command(e.message) for e in self._all_entries()) else 0
        frames_msgs: list[tuple[list[Message], list[Entry]]] = []
        used = 0
        for _ in range(cfg.n_frames):
            left = cfg.fbytes - hdr_bytes - reserve
            msgs: list[Message] = []
            taken: list[Entry] = []
            while acks and encoded_size(acks[0]) <= left:
                a = acks.pop(0)
                msgs.append(a)
                left -= encoded_size(a)
            while left > 0:
                pick = self._contest(link, w, left, now)
                if pick is None:
                    if not self._pull(link, w, left, now, exhausted, t0):
                        break
                    continue
                q, e = pick
                msgs.append(e.message)
                taken.append(e)
                left -= e.size
                q.last_access = now
                self._mark_taken(q, e, now)
            if not msgs:
                break
            used += cfg.fbytes - hdr_bytes - reserve - left
            frames_msgs.append((msgs, taken))
        if acks:  # acks that did not fit go back for the next packet
            for a in acks:
                self._requeue_ack(a, now)
        if not frames_msgs:
            return None
        for _, taken in frames_msgs:
            for e in taken:
                self._streams[e.stream].queue.expedite = False
        frames: list[bytes] = []
        seq0 = st.seq
        n_msgs = 0
        for i, (msgs, taken) in enumerate(frames_msgs):
            seq = (seq0 + i) % SEQ_MODULUS
            self._claim_seq(st, link, seq)
            header = FrameHeader(src=self.node_id, dst=cfg.dst, seq=seq, schedule=st.current.version,
                                 crc=cfg.crc)
            if signer is not None and any(self.is_command(m) for m in msgs):
                frames.append(signer.pack(msgs, cfg.fbytes, header))
                self.stats["signed"] += 1
            else:
                frames.append(pack(msgs, cfg.fbytes, header))
            n_msgs += len(msgs)
            refs = []
            for e in taken:
                q = self._streams[e.stream].queue
                if q.config.ack_required:
                    e.pending[(link, seq)] = now
                    e.ready_at = max(e.ready_at, now + st.ack_timeout)
                    refs.append((e.stream, e.id))
            if refs:
                st.sent[seq] = refs
        st.seq = (seq0 + len(frames)) % SEQ_MODULUS
        duration = cfg.airtime(len(frames))
        st.busy_until = now + duration
        st.packets += 1
        st.frames_tx += len(frames)
        capacity = cfg.n_frames * cfg.fbytes
        self.stats["packets"] += 1
        self.stats["frames"] += len(frames)
        self.stats["used_bytes"] += used
        self.stats["capacity"] += capacity
        return Transmission(link, cfg.rate, tuple(frames), seq0, now, duration, w.index, w.cycle,
                            capacity, used, n_msgs, st.current.version)

    def _claim_seq(self, st: _Link, link: int, seq: int) -> None:
        """Reusing a seq forgets the old frame's pending records (its ack can no longer be told
        apart); those messages become sendable again."""
        old = st.sent.pop(seq, None)
        if not old:
            return
        for sid, eid in old:
            e = self._find(sid, eid)
            if e is not None:
                e.pending.pop((link, seq), None)
                self._recompute_ready(e)

    def _mark_taken(self, q: StreamQueue, e: Entry, now: float) -> None:
        if e.first_sent is None:
            e.first_sent = now
        else:
            self.stats["resent"] += 1
        e.sends += 1
        if q.config.ack_required:
            e.hold = self._build_no  # not again in this packet; pending records follow
        else:
            q.entries.remove(e)

    def _eligible(self, q: StreamQueue, link: int, w: SlotWindow, now: float) -> bool:
        c = q.config
        if not c.enabled or (c.links is not None and link not in c.links):
            return False
        if c.tier > 0:
            if c.priority < w.slot.min_priority:
                return False
            if w.slot.tags and not (w.slot.tags & c.tags):
                return False
        return not q.in_blackout(now)

    def _sendable(self, e: Entry, now: float, link: int) -> bool:
        if e.hold == self._build_no or now < e.ready_at:
            return False
        if e.pending:  # every send timed out: avoid the links that failed it if others exist
            e.failed_links.update(lk for lk, _ in e.pending)
        if link in e.failed_links:
            usable = [k for k, st in self._links.items() if st.enabled and not st.muted]
            if all(k in e.failed_links for k in usable):
                e.failed_links.clear()
            else:
                return False
        return True

    def _contest(self, link: int, w: SlotWindow, left: int, now: float) -> tuple[StreamQueue, Entry] | None:
        best: tuple[tuple[float, ...], StreamQueue, Entry] | None = None
        for sid in sorted(self._streams):
            q = self._streams[sid].queue
            if not q.entries or not self._eligible(q, link, w, now):
                continue
            entry = None
            cap = q.config.max_bytes_on(link)
            room = left if cap is None else min(left, cap)
            for e in q.ordered():
                if e.size <= room and self._sendable(e, now, link):
                    entry = e
                    break
            if entry is None:
                continue
            last = q.last_access if q.last_access is not None else -math.inf
            # tier 0 is ordered by priority alone (status before queue status); other tiers
            # compete by value
            value = float(q.config.priority) if q.config.tier == 0 else q.score(now)
            if q.expedite:
                value = math.inf
            key = (-q.config.tier, value, q.config.priority, -last, -sid)
            if best is None or key > best[0]:
                best = (key, q, entry)
        if best is None:
            return None
        # an entry re-sent after its ack timeout keeps its old records: a late ack of the old
        # frame still clears it
        return best[1], best[2]

    def _pull(self, link: int, w: SlotWindow, left: int, now: float, exhausted: dict[int, float],
              t0: float) -> bool:
        """Ask modality senders (best score first) for at most ``left`` bytes. Returns whether a
        usable message was queued."""
        if self.clock is not None and self.clock() - t0 > self.fill_budget:
            return False
        cands = []
        for sid, s in self._streams.items():
            if s.sender is None or left <= exhausted.get(sid, -1) or not self._eligible(s.queue, link, w, now):
                continue
            q = s.queue
            score = math.inf if q.expedite else q.score(now)
            cands.append(((q.config.tier, -score, -q.config.priority, sid), s))
        for _, s in sorted(cands, key=lambda c: c[0]):
            q = s.queue
            sender = s.sender
            assert sender is not None
            cap = q.config.max_bytes_on(link)
            ask = left if cap is None else min(left, cap)
            if ask <= 0:
                continue
            start = self.clock() if self.clock is not None else 0.0
            try:
                got = sender.fill(ask, now)
                if not isinstance(got, list | tuple):
                    raise TypeError(f"fill returned {type(got).__name__}, not a list")
            except Exception as exc:  # a failing sender must never stop the packet
                exhausted[q.id] = math.inf
                self.stats["sender_failures"] += 1
                self._events.append(SenderFailed(now, q.id, f"{type(exc).__name__}: {exc}"))
                continue
            slow = self.clock is not None and self.clock() - start > self.sender_budget
            fits = False
            for m in got:
                try:
                    size = encoded_size(m)
                except (EncodeError, CoexError, TypeError, ValueError) as exc:
                    q.count_drop("encode")
                    self._events.append(Dropped(now, q.id, "encode"))
                    self._events.append(SenderFailed(now, q.id, f"unencodable message: {exc}"))
                    continue
                e = self._new_entry(q, m, size, now)
                if slow:
                    e.hold = self._build_no
                q.push(e, bypass_depth=True)
                if size <= ask and not slow:
                    fits = True
            if slow:
                exhausted[q.id] = math.inf
                self.stats["sender_failures"] += 1
                self._events.append(SenderFailed(now, q.id, "fill overran its deadline", slow=True))
                continue
            if fits:
                return True
            exhausted[q.id] = max(exhausted.get(q.id, -1), left)
            if self.clock is not None and self.clock() - t0 > self.fill_budget:
                return False
        return False

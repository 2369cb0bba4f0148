"""Packet building of a channel manager: the priority contest, pulls from senders, frames.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math

from ..auth import TRAILER_BYTES
from ..errors import CoexError, EncodeError
from ..messages import (
    FrameAck,
    FrameHeader,
    Message,
)
from ..wire import encoded_size, header_size, pack
from .events import (
    Dropped,
)
from .links import (
    SEQ_MODULUS,
    Transmission,
    _Link,
)
from .policy import PolicyMixin
from .queue import Entry, StreamQueue
from .schedule import SlotWindow

__all__ = ["PackingMixin"]


class _FrameBuild:
    """A frame being packed: its messages, the queue entries among them, the bytes left."""

    __slots__ = ("left", "msgs", "spare", "spare_open", "taken")

    def __init__(self, room: int) -> None:
        self.left = room
        self.msgs: list[Message] = []
        self.taken: list[Entry] = []
        #: (stream, message) of the spare-tier messages it carries
        self.spare: list[tuple[int, Message]] = []
        self.spare_open = True

    def add(self, m: Message, size: int, entry: Entry | None = None) -> None:
        self.msgs.append(m)
        self.left -= size
        if entry is not None:
            self.taken.append(entry)


class PackingMixin(PolicyMixin):
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
        pulls from modality senders when no queued message fits (:meth:`_fill_frames`). Then,
        within the link's spare share: extra copies of the packet's urgent messages (frame
        acks, tier-0 messages, the first answer to a request) in other frames, as many as the
        measured loss calls for (:meth:`copies`); then the spare tier
        (``ModalitySender.spare``) fills what is left. The frames are then sealed
        (:meth:`_seal`) and the packet counted (:meth:`_transmission`)."""
        st = self._link(link)
        cfg = st.cfg
        self._build_no += 1
        self._follow_link(now)  # the senders learn the measured throughput first
        w = self._window(st, now)
        t0 = self.clock() if self.clock is not None else 0.0
        acks = self._take_acks(now)
        reserve = TRAILER_BYTES if (self.signer is not None or self.peer_signers) and any(
            self.is_command(e.message) for e in self._all_entries()) else 0
        room = cfg.fbytes - header_size(FrameHeader(crc=cfg.crc)) - reserve
        # the node this packet is for: the link's ``dst`` unless the contest's winner is
        # addressed to another (a network of several nodes: one destination per packet)
        dst = self._packet_dst(link, w, room, now)
        own = dst == cfg.dst  # senders' pulls and spare work go to the link's destination
        # room kept in each frame for the extra copies of the urgent messages known now (frame
        # acks, tier-0 messages, replies queued on an expedited stream), so that background
        # traffic cannot crowd them out; unused, it goes to the spare tier
        keep = self._copy_reserve(link, acks, room, now, dst)
        frames_b, urgent = self._fill_frames(link, w, room, keep, acks, own, now, t0, dst)
        if not frames_b and st.spare <= 0:
            return None  # nothing but spare work, and no spare tier to fill an empty packet
        spare_budget = int(st.spare * cfg.n_frames * room)
        redundant = self._add_copies(link, frames_b, urgent, room, spare_budget)
        spare = self._fill_spare(link, w, frames_b, room, spare_budget - redundant, now, t0) if own else 0
        frames_b = [fb for fb in frames_b if fb.msgs]
        if not frames_b:
            return None
        seq0 = st.seq
        frames = self._seal(link, frames_b, dst, now)
        used = sum(room - fb.left for fb in frames_b)
        return self._transmission(link, w, frames, seq0, sum(len(fb.msgs) for fb in frames_b), used, spare,
                                  redundant, now)

    def _fill_frames(self, link: int, w: SlotWindow, room: int, keep: int, acks: list[Message], own: bool,
                     now: float, t0: float, dst: int
                     ) -> tuple[list[_FrameBuild], list[tuple[Message, int, Entry | None]]]:
        """The packet's frames, each filled with the pending frame acks, then the contest's
        winners, then pulls from the senders (``own``: the packet goes to the link's own
        destination) within ``room - keep`` bytes; and its urgent messages (``(message, size,
        entry)``: frame acks, tier-0 messages, answers on an expedited stream). Acks that did not
        fit go back for the next packet; a stream that had an entry taken is no longer
        expedited."""
        cfg = self._links[link].cfg
        # stream -> largest budget for which it had nothing (inf: failed or slow, skip it)
        exhausted: dict[int, float] = {}
        frames_b: list[_FrameBuild] = []
        urgent: list[tuple[Message, int, Entry | None]] = []  # message, size, its entry
        for _ in range(cfg.n_frames):
            fb = _FrameBuild(room)
            while acks and encoded_size(acks[0]) <= fb.left:
                a = acks.pop(0)
                fb.add(a, encoded_size(a))
                urgent.append((a, encoded_size(a), None))
            while fb.left > 0:
                pick = self._contest(link, w, fb.left, now, keep, dst)
                if pick is None:
                    if not own or fb.left - keep <= 0 or \
                            not self._pull(link, w, fb.left - keep, now, exhausted, t0):
                        break
                    continue
                q, e = pick
                fb.add(e.message, e.size, e)
                q.last_access = now
                if q.config.tier == 0 or q.expedite:
                    urgent.append((e.message, e.size, e))
                self._mark_taken(q, e, now)
            if not fb.msgs:
                break
            frames_b.append(fb)
        for a in acks:  # acks that did not fit go back for the next packet
            self._requeue_ack(a, now)
        for fb in frames_b:
            for e in fb.taken:
                self._streams[e.stream].queue.expedite = False
        return frames_b, urgent

    def _seal(self, link: int, frames_b: list[_FrameBuild], dst: int, now: float) -> list[bytes]:
        """The frames' bytes (signed when they carry a command and a key is set), each under the
        link's next sequence number, with what waits for their acks: the ack-required entries
        they carry (re-sent after the link's ack timeout unless acknowledged), the senders'
        messages whose delivery the senders are told (one token shared by a message's copies),
        and the frames whose loss is measured."""
        st = self._links[link]
        cfg = st.cfg
        signer = self.signer_for(dst)
        frames: list[bytes] = []
        seq0 = st.seq
        tokens: dict[int, int] = {}  # id(message) -> delivery token, shared by its copies
        for i, fb in enumerate(frames_b):
            seq = (seq0 + i) % SEQ_MODULUS
            self._claim_seq(st, link, seq)
            header = FrameHeader(src=self.node_id, dst=dst, seq=seq, schedule=st.current.version,
                                 crc=cfg.crc)
            if signer is not None and any(self.is_command(m) for m in fb.msgs):
                frames.append(signer.pack(fb.msgs, cfg.fbytes, header))
                self.stats["signed"] += 1
            else:
                frames.append(pack(fb.msgs, cfg.fbytes, header))
            refs = []
            tracked = list(fb.spare)
            for e in fb.taken:
                q = self._streams[e.stream].queue
                if q.config.ack_required:
                    e.pending[(link, seq)] = now
                    e.ready_at = max(e.ready_at, now + st.ack_timeout)
                    refs.append((e.stream, e.id))
                elif self._streams[e.stream].sender is not None:
                    tracked.append((e.stream, e.message))
            if refs:
                st.sent[seq] = refs
            for sid, m in tracked:
                token = tokens[id(m)] = self._track(link, sid, m, now, tokens.get(id(m)))
                self._carried(link, seq, token)
            if any(not isinstance(m, FrameAck) for m in fb.msgs):
                self._watch_frame(link, seq, now, dst)
        st.seq = (seq0 + len(frames)) % SEQ_MODULUS
        return frames

    def _transmission(self, link: int, w: SlotWindow, frames: list[bytes], seq0: int, n_msgs: int, used: int,
                      spare: int, redundant: int, now: float) -> Transmission:
        """The sealed packet as a :class:`Transmission`, counted in the link's and the manager's
        statistics; the link is busy for its airtime."""
        st = self._links[link]
        cfg = st.cfg
        duration = cfg.airtime(len(frames))
        st.busy_until = now + duration
        st.packets += 1
        st.frames_tx += len(frames)
        capacity = cfg.n_frames * cfg.fbytes
        self.stats["packets"] += 1
        self.stats["frames"] += len(frames)
        self.stats["used_bytes"] += used
        self.stats["capacity"] += capacity
        self.stats["spare_bytes"] += spare
        self.stats["redundant_bytes"] += redundant
        return Transmission(link, cfg.rate, tuple(frames), seq0, now, duration, w.index, w.cycle,
                            capacity, used, n_msgs, st.current.version, spare, redundant,
                            self.backlog(now))

    def backlog(self, now: float) -> int:
        """Bytes of work ready to go: queued messages plus what every sender could give now
        (``ModalitySender.ready_bytes``; spare work only where spare traffic is on)."""
        n = sum(s.queue.queued_bytes() for s in self._streams.values() if s.queue.config.enabled)
        spare_on = any(st.spare > 0 for st in self._links.values())
        for sid, s in self._streams.items():
            if s.sender is None or not s.queue.config.enabled:
                continue
            try:
                if spare_on and s.queue.config.spare > 0:
                    n += int(s.sender.ready_bytes(now))
                else:
                    n += int(s.sender.ready_bytes(now)) - int(s.sender.spare_bytes())
            except Exception as exc:  # an estimate must never stop a packet: counted and told, by name
                self._sender_failed(now, sid, f"ready_bytes() failed: {type(exc).__name__}: {exc}")
                continue
        return max(n, 0)

    def _add_copies(self, link: int, frames_b: list[_FrameBuild],
                    urgent: list[tuple[Message, int, Entry | None]], room: int, budget: int) -> int:
        """Put extra copies of the packet's urgent messages into other frames (existing ones with
        room, then new ones up to the link's frames per packet), within ``budget`` bytes;
        returns the bytes added. Copies go round by round (every urgent message gets its second
        copy before any gets a third), so one large message cannot take the room of the others.
        A copy of an ack-required message is recorded under its frame too, so an ack of any copy
        clears it."""
        k = self.copies(link)
        n_frames = self._links[link].cfg.n_frames
        if k <= 1 or not urgent or budget <= 0:
            return 0
        added = 0
        for _ in range(k - 1):
            placed = False
            for m, size, entry in urgent:
                if added + size > budget:
                    continue
                have = [i for i, fb in enumerate(frames_b) if any(x is m for x in fb.msgs)]
                if len(have) >= k:
                    continue
                start = have[-1] if have else 0
                order = list(range(start + 1, len(frames_b))) + list(range(0, start + 1))
                target = next((frames_b[j] for j in order if j not in have and frames_b[j].left >= size), None)
                if target is None:
                    if len(frames_b) >= n_frames or size > room:
                        continue
                    target = _FrameBuild(room)
                    frames_b.append(target)
                target.add(m, size, entry)
                added += size
                placed = True
            if not placed:
                break
        return added

    def _fill_spare(self, link: int, w: SlotWindow, frames_b: list[_FrameBuild], room: int, budget: int,
                    now: float, t0: float) -> int:
        """The spare tier: below everything else, senders' ``spare(max_bytes, now)`` fill what is
        left of the packet, within the link's spare share (``budget``) and each stream's
        (``StreamConfig.spare``); returns the spare bytes packed. Senders take turns: the one
        that gave spare work longest ago (weighted by priority) is asked first."""
        cfg = self._links[link].cfg
        if budget <= 0:
            return 0
        # (a sender without spare work answers spare() with nothing: the declared default)
        cands = [sid for sid, s in self._streams.items()
                 if s.sender is not None and s.queue.config.spare > 0 and self._eligible(s.queue, link, w, now)]
        if not cands:
            return 0
        total = 0
        per_stream = {sid: int(self._streams[sid].queue.config.spare * cfg.n_frames * room) for sid in cands}
        exhausted: dict[int, float] = {}
        while True:
            fb = next((f for f in frames_b if f.left > 0 and f.spare_open), None)
            if fb is None:
                if len(frames_b) >= cfg.n_frames or total >= budget:
                    break
                fb = _FrameBuild(room)
                frames_b.append(fb)
            if self.clock is not None and self.clock() - t0 > self.fill_budget:
                break
            left = min(fb.left, budget - total)
            order = sorted(
                (sid for sid in cands if left > exhausted.get(sid, -1) and per_stream[sid] > 0),
                key=lambda sid: (-(self._streams[sid].queue.config.priority_now(self._low)
                                   * (now - self._spare_turn.get(sid, -math.inf) + 1.0)), sid))
            got_any = False
            for sid in order:
                ask = min(left, per_stream[sid])
                cap = self._streams[sid].queue.config.max_bytes_on(link)
                if cap is not None:
                    ask = min(ask, cap)
                if ask <= 0:
                    continue
                packed = self._take_spare(sid, fb, ask, now, exhausted)
                if packed:
                    per_stream[sid] -= packed
                    total += packed
                    self._spare_turn[sid] = now
                    got_any = True
                    break
                exhausted[sid] = max(exhausted.get(sid, -1), left)
            if not got_any:
                fb.spare_open = False  # nobody has spare work that fits this frame
        return total

    def _take_spare(self, sid: int, fb: _FrameBuild, ask: int, now: float, exhausted: dict[int, float]) -> int:
        """Ask stream ``sid``'s sender for at most ``ask`` bytes of spare work and pack what fits
        into ``fb``; returns the bytes packed. A sender that fails is told as
        :class:`SenderFailed` and not asked again for this packet (``exhausted``); a message that
        does not encode, or goes beyond what was asked, is dropped (spare work can be made
        again) and counted."""
        s = self._streams[sid]
        sender = s.sender
        assert sender is not None
        try:
            got = sender.spare(ask, now)
            if not isinstance(got, list | tuple):
                raise TypeError(f"spare returned {type(got).__name__}, not a list")
        except Exception as exc:  # a failing sender must never stop the packet
            exhausted[sid] = math.inf
            self._sender_failed(now, sid, f"spare: {type(exc).__name__}: {exc}")
            return 0
        packed = 0
        for m in got:
            try:
                size = encoded_size(m)
            except (EncodeError, CoexError, TypeError, ValueError) as exc:
                s.queue.count_drop("encode")
                self._events.append(Dropped(now, sid, "encode"))
                self._sender_failed(now, sid, f"unencodable spare message: {exc}")
                continue
            if size > fb.left or packed + size > ask:
                # more than asked for: spare work can be made again, so it is dropped
                s.queue.count_drop("overrun")
                self._events.append(Dropped(now, sid, "overrun"))
                continue
            fb.add(m, size)
            fb.spare.append((sid, m))
            packed += size
        return packed

    def _claim_seq(self, st: _Link, link: int, seq: int) -> None:
        """Reusing a seq forgets the old frame's pending records (its ack can no longer be told
        apart); those messages become sendable again."""
        self._forget_frame(link, seq)
        old = st.sent.pop(seq, None)
        if not old:
            return
        for sid, eid in old:
            e = self._find(sid, eid)
            if e is not None:
                e.pending.pop((link, seq), None)
                self._recompute_ready(e)

    def not_sent(self, tx: Transmission, now: float) -> None:
        """``tx`` never left: its modem was down (the transport raised
        :class:`~coex_core.errors.LinkDown`). Its frames are not counted against the link's
        acoustic loss; acknowledged streams' messages are sendable again at once, and the
        messages of modalities go to their senders' ``lost`` now, instead of after the ack
        timeout."""
        st = self._links.get(tx.link_id)
        if st is None:
            return
        for i in range(len(tx.frames)):
            seq = (tx.seq + i) % SEQ_MODULUS
            self._frame_watch.get(tx.link_id, {}).pop(seq, None)  # not an acoustic loss
            self._frame_dst.get(tx.link_id, {}).pop(seq, None)
            for sid, eid in st.sent.pop(seq, None) or ():
                e = self._find(sid, eid)
                if e is not None:
                    e.pending.pop((tx.link_id, seq), None)
                    self._recompute_ready(e)
            self._frame_lost(tx.link_id, seq, now)
        self.stats["not_sent_frames"] = self.stats.get("not_sent_frames", 0) + len(tx.frames)

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

    def _dst_of(self, e: Entry, link: int) -> int:
        """The node ``e`` is for when it goes out on ``link``."""
        return self._links[link].cfg.dst if e.dst is None else e.dst

    def _packet_dst(self, link: int, w: SlotWindow, room: int, now: float) -> int:
        """The destination of the packet built now on ``link``: that of the message the
        contest picks first (the link's ``dst`` when no queued message is sendable)."""
        pick = self._contest(link, w, room, now)
        return self._links[link].cfg.dst if pick is None else self._dst_of(pick[1], link)

    def _copy_reserve(self, link: int, acks: list[Message], room: int, now: float,
                      dst: int | None = None) -> int:
        """Bytes per frame that only urgent messages (tier 0, expedited streams) may use: room
        for ``copies - 1`` extra copies of the urgent messages waiting now, spread over the
        other frames (at most half a frame)."""
        st = self._links[link]
        k = self.copies(link)
        n = st.cfg.n_frames
        if k <= 1 or n <= 1 or st.spare <= 0:
            return 0
        w = self._window(st, now)
        urgent = sum(encoded_size(a) for a in acks)
        for s in self._streams.values():
            q = s.queue
            if (q.config.tier == 0 or q.expedite) and q.entries and self._eligible(q, link, w, now):
                urgent += sum(e.size for e in q.entries if self._sendable(e, now, link)
                              and (dst is None or self._dst_of(e, link) == dst))
        return min(room // 2, math.ceil((k - 1) * urgent / (n - 1)))

    def _contest(self, link: int, w: SlotWindow, left: int, now: float,
                 keep: int = 0, dst: int | None = None) -> tuple[StreamQueue, Entry] | None:
        """The message to pack next: ``keep`` bytes of ``left`` are for urgent messages only;
        with ``dst``, only messages for that node compete."""
        best: tuple[tuple[float, ...], StreamQueue, Entry] | None = None
        for sid in sorted(self._streams):
            q = self._streams[sid].queue
            if not q.entries or not self._eligible(q, link, w, now):
                continue
            entry = None
            cap = q.config.max_bytes_on(link)
            room = left if q.config.tier == 0 or q.expedite else left - keep
            room = room if cap is None else min(room, cap)
            for e in q.ordered():
                if e.size <= room and self._sendable(e, now, link) and (
                        dst is None or self._dst_of(e, link) == dst):
                    entry = e
                    break
            if entry is None:
                continue
            last = q.last_access if q.last_access is not None else -math.inf
            # tier 0 is ordered by priority alone (status before queue status); other tiers
            # compete by value
            prio = q.config.priority_now(self._low)
            value = float(prio) if q.config.tier == 0 else q.score(now, self._low)
            if q.expedite:
                value = math.inf
            key = (-q.config.tier, value, prio, -last, -sid)
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
            score = math.inf if q.expedite else q.score(now, self._low)
            cands.append(((q.config.tier, -score, -q.config.priority_now(self._low), sid), s))
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
                self._sender_failed(now, q.id, f"{type(exc).__name__}: {exc}")
                continue
            slow = self.clock is not None and self.clock() - start > self.sender_budget
            fits = False
            for m in got:
                try:
                    size = encoded_size(m)
                except (EncodeError, CoexError, TypeError, ValueError) as exc:
                    q.count_drop("encode")
                    self._events.append(Dropped(now, q.id, "encode"))
                    self._sender_failed(now, q.id, f"unencodable message: {exc}")
                    continue
                e = self._new_entry(q, m, size, now)
                if slow:
                    e.hold = self._build_no
                q.push(e, bypass_depth=True)
                if size <= ask and not slow:
                    fits = True
            if slow:
                exhausted[q.id] = math.inf
                self._sender_failed(now, q.id, "fill overran its deadline", slow=True)
                continue
            if fits:
                return True
            exhausted[q.id] = max(exhausted.get(q.id, -1), left)
            if self.clock is not None and self.clock() - t0 > self.fill_budget:
                return False
        return False

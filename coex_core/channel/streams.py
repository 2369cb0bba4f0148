"""Stream queues of a channel manager: add, push, flush, withdraw.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

from ..errors import ConfigError
from ..messages import (
    Message,
    QueueStatus,
    StreamStatus,
)
from ..modality import ModalitySender
from ..timefmt import to_stamp
from ..wire import encoded_size
from .events import Dropped
from .links import (
    _ManagerState,
    _Stream,
)
from .queue import Entry, StreamConfig, StreamQueue

__all__ = ["StreamsMixin"]


class StreamsMixin(_ManagerState):
    # =========================================================================== streams
    def add_stream(self, config: StreamConfig, sender: ModalitySender | None = None) -> StreamQueue:
        """Add (or replace the settings of) a stream; ``sender`` is asked to fill packets."""
        old = self._streams.get(config.stream)
        q = StreamQueue(config)
        if old is not None:
            q.entries = old.queue.entries
            q.last_access = old.queue.last_access
            sender = sender or old.sender
        self._streams[config.stream] = _Stream(q, sender)
        self._defaults[config.stream] = config
        return q

    def expedite(self, stream: int) -> None:
        """Serve ``stream`` first in the next packet (an operator request was just handed to
        its modality): it wins its tier's contest and is asked first for data."""
        self.stream(stream).expedite = True
        for st in self._links.values():
            st.idle_until = -math.inf

    def stream(self, stream: int) -> StreamQueue:
        try:
            return self._streams[stream].queue
        except KeyError:
            raise ConfigError(f"no stream {stream}") from None

    @property
    def streams(self) -> list[StreamQueue]:
        return [self._streams[k].queue for k in sorted(self._streams)]

    def push(self, stream: int, message: Message, now: float, *, dst: int | None = None) -> int:
        """Queue ``message`` on ``stream``; returns its entry id. An unencodable message raises
        :class:`EncodeError` (nothing is queued). ``dst`` addresses it to one node (0: every
        node, a broadcast) in a network of several nodes; ``None`` (the default) sends it to the
        ``LinkConfig.dst`` of the link it goes out on. A packet carries messages for one
        destination (docs/channel.md, "A network of several nodes")."""
        if dst is not None and not 0 <= dst <= 15:
            raise ConfigError(f"destination {dst} is not a node id 0..15")
        q = self.stream(stream)
        size = encoded_size(message)  # raises EncodeError for a bad message
        entry = self._new_entry(q, message, size, now)
        entry.dst = dst
        for st in self._links.values():
            st.idle_until = -math.inf  # new data: the next opportunity is worth a look
        dropped = q.push(entry)
        if dropped is not None:
            self._forget(dropped)
            self._events.append(Dropped(now, stream, q.overflow_reason))
        return entry.id

    def _new_entry(self, q: StreamQueue, message: Message, size: int, now: float) -> Entry:
        self._entry_ids += 1
        return Entry(self._entry_ids, q.id, message, size, now)

    def flush(self, stream: int, now: float) -> int:
        """Empty ``stream`` (counted as ``flush`` drops); returns how many messages left."""
        return self._remove(stream, lambda m: True, "flush", now)

    def withdraw(self, stream: int, match: Callable[[Message], bool], now: float, *,
                 dst: int | None = None) -> int:
        """Take off ``stream`` every entry whose message ``match`` accepts, queued or sent and
        awaiting its ack (a later ack for it then clears nothing). Counted as ``superseded``
        drops; returns how many were withdrawn. With ``dst``, only entries pushed for that
        node."""
        return self._remove(stream, match, "superseded", now, dst)

    def _remove(self, stream: int, match: Callable[[Message], bool], reason: str, now: float,
                dst: int | None = None) -> int:
        q = self.stream(stream)
        # a match that raises changes nothing
        flags = [(dst is None or e.dst == dst) and bool(match(e.message)) for e in q.entries]
        gone = [e for e, f in zip(q.entries, flags, strict=True) if f]
        q.entries[:] = [e for e, f in zip(q.entries, flags, strict=True) if not f]
        for e in gone:
            self._forget(e)
        if gone:
            q.count_drop(reason, len(gone))
            self._events.append(Dropped(now, stream, reason, len(gone)))
        return len(gone)

    def _all_entries(self) -> Iterable[Entry]:
        for s in self._streams.values():
            yield from s.queue.entries

    def _find(self, sid: int, eid: int) -> Entry | None:
        s = self._streams.get(sid)
        if s is None:
            return None
        for e in s.queue.entries:
            if e.id == eid:
                return e
        return None

    def _forget(self, e: Entry) -> None:
        for link, seq in list(e.pending):
            st = self._links.get(link)
            if st is not None and seq in st.sent:
                st.sent[seq] = [r for r in st.sent[seq] if r[1] != e.id]
        e.pending.clear()

    def queue_status(self, now: float) -> QueueStatus:
        """Per-stream state (drop counters restart at each status)."""
        lines = []
        for q in self.streams:
            oldest = max((now - e.pushed for e in q.entries), default=0.0)
            lines.append(StreamStatus(
                q.id, q.config.enabled, q.config.tier, q.config.priority, min(len(q), 63),
                min(q.queued_bytes(), 65472), int(min(oldest, 4080)), min(q.drops, 15)))
            q.drops = 0
        return QueueStatus(to_stamp(now), tuple(lines))

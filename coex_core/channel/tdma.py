"""Links and TDMA time of a channel manager: link state, slots, opportunities, schedule switches, watchdog, expiry.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math
from typing import Any

from ..errors import ConfigError
from .events import (
    Dropped,
    LinkChanged,
    ScheduleSwitched,
)
from .links import (
    QUEUE_STATUS_STREAM,
    LinkConfig,
    _Link,
)
from .queue import Entry
from .schedule import Schedule, SlotWindow
from .streams import StreamsMixin

__all__ = ["LinksMixin"]


class LinksMixin(StreamsMixin):
    # ============================================================================= links
    def link(self, link: int) -> LinkConfig:
        return self._link(link).cfg

    def _link(self, link: int) -> _Link:
        try:
            return self._links[link]
        except KeyError:
            raise ConfigError(f"no link {link}") from None

    @property
    def links(self) -> list[int]:
        return sorted(self._links)

    def link_state(self, link: int) -> dict[str, Any]:
        st = self._link(link)
        return {"link": link, "enabled": st.enabled, "muted": st.muted,
                "schedule": st.current.version,
                "pending": None if st.pending is None else st.pending.schedule.version,
                "packets": st.packets, "frames_tx": st.frames_tx, "frames_rx": st.frames_rx,
                "last_heard": st.last_heard, "spare": st.spare}

    def schedule(self, link: int) -> Schedule:
        """The schedule link ``link`` runs now."""
        return self._link(link).current

    def _fleet(self, st: _Link) -> bool:
        """Whether ``st`` is a network of several nodes: its safe schedule gives slots to more
        than two nodes (this one counted). Schedule changes then need every node's agreement."""
        return len({s.owner for s in st.safe.slots if s.owner} | {self.node_id}) > 2

    def pending_schedule(self, link: int) -> Schedule | None:
        p = self._link(link).pending
        return None if p is None else p.schedule

    def set_link_enabled(self, link: int, enabled: bool, now: float) -> int:
        """Enable/disable a link. Disabling returns its unacked messages to their queues at
        once (they become sendable on the other links). Returns how many were returned."""
        st = self._link(link)
        returned = 0
        if not enabled and st.enabled:
            returned = self._release_link(link)
        st.enabled = enabled
        self._events.append(LinkChanged(now, link, st.enabled, st.muted, returned))
        return returned

    def set_mute(self, link: int, muted: bool, now: float) -> None:
        """Software mute: the link keeps receiving but never transmits."""
        st = self._link(link)
        st.muted = muted
        self._events.append(LinkChanged(now, link, st.enabled, st.muted, 0))

    def _release_link(self, link: int) -> int:
        st = self._links[link]
        ids = {eid for refs in st.sent.values() for _, eid in refs}
        st.sent.clear()
        n = 0
        for e in self._all_entries():
            keys = [k for k in e.pending if k[0] == link]
            for k in keys:
                del e.pending[k]
            if keys:
                self._recompute_ready(e)
            if keys and e.id in ids and not e.pending:
                n += 1
        return n

    def _recompute_ready(self, e: Entry) -> None:
        e.ready_at = max((t + self._links[lk].ack_timeout for (lk, _), t in e.pending.items()
                          if lk in self._links), default=-math.inf)

    # ============================================================================== time
    def _window(self, st: _Link, now: float) -> SlotWindow:
        return st.current.window(now)

    def can_transmit(self, link: int, now: float) -> bool:
        """Whether a packet may start on ``link`` at ``now``."""
        st = self._link(link)
        if not st.enabled or st.muted:
            return False
        if now < st.busy_until + st.cfg.gap - 1e-9 or now < st.idle_until - 1e-9:
            return False
        w = self._window(st, now)
        return w.slot.owner == self.node_id and now + st.cfg.packet_time + w.slot.guard <= w.end + 1e-9

    def next_opportunity(self, link: int, now: float) -> float | None:
        """The earliest time >= ``now`` at which ``link`` may start a packet (current schedule)."""
        st = self._link(link)
        if not st.enabled or st.muted:
            return None
        t = max(now, st.busy_until + st.cfg.gap, st.idle_until)
        for _ in range(2 * len(st.current.slots) + 2):
            w = st.current.next_window(t, self.node_id)
            if w is None:
                return None
            start = max(t, w.start)
            if start + st.cfg.packet_time + w.slot.guard <= w.end + 1e-9:
                return start
            t = w.end + 1e-6
        return None

    def next_event(self, now: float) -> float | None:
        """When :meth:`poll` next has something to do (an opportunity, a schedule activation,
        a watchdog deadline); ``None`` if nothing is foreseen."""
        times: list[float] = []
        for link, st in self._links.items():
            t = self.next_opportunity(link, now)
            if t is not None:
                times.append(t)
            if st.pending is not None:
                times.append(max(now, self._activation(st)))
            wd = self._watchdog_deadline(st)
            if wd is not None:
                times.append(max(now, wd))
        return min(times) if times else None

    def _watchdog_deadline(self, st: _Link) -> float | None:
        if st.current.version == st.safe.version and st.current.slots == st.safe.slots:
            return None
        ref = max(x for x in (st.last_heard, st.switched_at, -math.inf) if x is not None)
        if ref == -math.inf:
            return None
        # fall back at the first cycle boundary after N silent cycles, so that both ends (each
        # counting from the last frame it heard) switch on a boundary
        late = ref + st.cfg.watchdog_cycles * st.current.cycle
        return st.current.cycle_start(st.current.cycle_at(late) + 1)

    def _activation(self, st: _Link) -> float:
        """When ``st``'s pending schedule is due: its epoch; in a network of several nodes, one
        not committed is kept ``watchdog_cycles`` cycles past it (it is taken when a peer is
        heard on it), then dropped."""
        p = st.pending
        assert p is not None
        if not p.fleet or p.committed:
            return p.schedule.epoch
        return p.schedule.epoch + st.cfg.watchdog_cycles * p.schedule.cycle

    def _tick(self, now: float) -> None:
        """Schedule activations, watchdog, expiry, queue status."""
        for link, st in self._links.items():
            if st.switched_at is None:
                st.switched_at = now
            if st.pending is not None and now >= self._activation(st) - 1e-9:
                if not st.pending.fleet or st.pending.committed:
                    self._switch(link, st.pending.schedule, now, "activation")
                else:  # never committed (a node did not agree), never heard in use: dropped
                    st.pending = None
                    self.stats["schedules_not_agreed"] = self.stats.get("schedules_not_agreed", 0) + 1
            wd = self._watchdog_deadline(st)
            if wd is not None and now >= wd:
                self._fallback(link, now, "watchdog")
        self._expire(now)
        if self.queue_status_interval is not None and QUEUE_STATUS_STREAM in self._streams and (
            self._last_qs is None or now - self._last_qs >= self.queue_status_interval
        ):
            self._last_qs = now
            self.push(QUEUE_STATUS_STREAM, self.queue_status(now), now)

    def _switch(self, link: int, schedule: Schedule, now: float, reason: str) -> None:
        st = self._links[link]
        st.current = schedule
        st.pending = None
        st.switched_at = now
        self._events.append(ScheduleSwitched(now, link, schedule.version, schedule.cycle_at(now), reason))

    def _fallback(self, link: int, now: float, reason: str) -> None:
        st = self._links[link]
        st.proposed.clear()
        self._switch(link, st.safe, now, reason)

    def _expire(self, now: float) -> None:
        for s in self._streams.values():
            q = s.queue
            ttl = q.config.ttl
            if ttl <= 0:
                continue
            old = [e for e in q.entries if now - e.pushed > ttl]
            for e in old:
                self._forget(e)
                q.drop(e, "ttl")
            if old:
                self._events.append(Dropped(now, q.id, "ttl", len(old)))

"""Commands of a channel manager: applying them (vehicle) and sending and tracking them (topside).

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

from typing import Any

from ..errors import ConfigError
from ..messages import (
    AckStatus,
    CommandAck,
    LinkControl,
    Message,
    QueueConfig,
    ScheduleUpdate,
    SpareConfig,
)
from ..tracker import Event, Tracked, answer_event
from .events import (
    CommandApplied,
    CommandResult,
    Dropped,
)
from .links import (
    CONTROL_STREAM,
    _PendingSchedule,
)
from .packing import PackingMixin
from .schedule import Schedule, resolve_cycle

__all__ = ["CommandsMixin"]


class CommandsMixin(PackingMixin):
    # ============================================================== commands (vehicle side)
    def apply(self, command: Message, now: float) -> CommandAck:
        """Apply a topside command (QueueConfig, ScheduleUpdate, LinkControl, SpareConfig) and return the
        CommandAck to send; never raises for a well-formed message."""
        status, reason = AckStatus.REJECTED, "not a channel command"
        if isinstance(command, QueueConfig):
            status, reason = self._apply_queue_config(command, now)
        elif isinstance(command, ScheduleUpdate):
            status, reason = self._apply_schedule(command, now)
        elif isinstance(command, LinkControl):
            status, reason = self._apply_link_control(command, now)
        elif isinstance(command, SpareConfig):
            status, reason = self._apply_spare(command)
        cid = int(getattr(command, "command_id", 0))
        self._events.append(CommandApplied(now, command, status, reason))
        return CommandAck(cid, status)

    def _apply_queue_config(self, c: QueueConfig, now: float) -> tuple[AckStatus, str]:
        s = self._streams.get(c.stream)
        if s is None:
            return AckStatus.UNKNOWN_TARGET, f"no stream {c.stream}"
        changes: dict[str, Any] = {}
        if c.enabled is not None:
            changes["enabled"] = c.enabled
        if c.priority is not None:
            changes["priority"] = c.priority
        if c.ttl is not None:
            changes["ttl"] = float(c.ttl)
        if c.max_depth is not None:
            changes["max_depth"] = c.max_depth
        if c.newest_first is not None:
            changes["newest_first"] = c.newest_first
        try:
            cfg = s.queue.config.updated(**changes)
        except ConfigError as exc:
            return AckStatus.REJECTED, str(exc)
        s.queue.config = cfg
        for e in s.queue.trim():
            self._forget(e)
            self._events.append(Dropped(now, c.stream, "overflow"))
        if c.flush:
            self.flush(c.stream, now)
        return AckStatus.ACCEPTED, ""

    def _apply_schedule(self, c: ScheduleUpdate, now: float) -> tuple[AckStatus, str]:
        st = self._links.get(c.link)
        if st is None:
            return AckStatus.UNKNOWN_TARGET, f"no link {c.link}"
        if st.pending is not None and st.pending.command_id == c.command_id \
                and st.pending.schedule.version == c.version:
            return AckStatus.ACCEPTED, "duplicate"
        try:
            new = Schedule.from_message(c)
        except ConfigError as exc:
            return AckStatus.REJECTED, str(exc)
        if not new.owns_any(self.node_id, st.cfg.packet_time):
            return AckStatus.REJECTED, "no slot of this node fits a packet"
        cur = st.current.cycle_at(now)
        n = resolve_cycle(c.activate_cycle, cur)
        if n <= cur:
            if new.slots == st.current.slots and new.version == st.current.version:
                return AckStatus.ACCEPTED, "already active"
            return AckStatus.REJECTED, f"activation cycle {n} is not after the current cycle {cur}"
        st.pending = _PendingSchedule(new.starting_at(n, st.current.cycle_start(n)), c.command_id)
        return AckStatus.ACCEPTED, ""

    def _apply_spare(self, c: SpareConfig) -> tuple[AckStatus, str]:
        if not 0 <= c.percent <= 100:
            return AckStatus.REJECTED, f"spare share {c.percent} % outside 0..100"
        share = c.percent / 100.0
        if c.stream is not None:
            if c.link is not None:
                return AckStatus.REJECTED, "a spare share is set per link or per stream, not both"
            s = self._streams.get(c.stream)
            if s is None:
                return AckStatus.UNKNOWN_TARGET, f"no stream {c.stream}"
            s.queue.config = s.queue.config.updated(spare=share)
            return AckStatus.ACCEPTED, ""
        if c.link is not None and c.link not in self._links:
            return AckStatus.UNKNOWN_TARGET, f"no link {c.link}"
        self.set_spare(share, c.link)
        return AckStatus.ACCEPTED, ""

    def set_spare(self, share: float, link: int | None = None) -> None:
        """Set the share of each packet spare traffic may fill on ``link`` (every link when
        ``None``): 0 switches the spare tier and redundant copies off, 1 lets them fill every
        idle byte. (A stream's own share is ``StreamConfig.spare``.)"""
        if not 0.0 <= share <= 1.0:
            raise ConfigError(f"spare share {share} outside 0..1")
        for lk in ([link] if link is not None else list(self._links)):
            self._link(lk).spare = float(share)

    def _apply_link_control(self, c: LinkControl, now: float) -> tuple[AckStatus, str]:
        st = self._links.get(c.link)
        if st is None:
            return AckStatus.UNKNOWN_TARGET, f"no link {c.link}"
        if not c.enabled or c.mute:
            others = [x for k, x in self._links.items() if k != c.link and x.enabled and not x.muted]
            if not others:
                return AckStatus.REJECTED, "would leave the node without a transmitting link"
        if c.enabled != st.enabled:
            self.set_link_enabled(c.link, c.enabled, now)
        if c.mute != st.muted:
            self.set_mute(c.link, c.mute, now)
        return AckStatus.ACCEPTED, ""

    # ============================================================== commands (topside side)
    def next_command_id(self) -> int:
        self._command_id = (self._command_id + 1) % 256
        return self._command_id

    def send_command(self, command: Message, now: float) -> int:
        """Queue a command (on the control stream, acked) and remember it until its
        CommandAck arrives. Returns its command id."""
        cid = int(getattr(command, "command_id", 0))
        tracked = self._commands[cid] = Tracked(command)
        tracked.apply(Event.SEND, now)
        self.push(CONTROL_STREAM, command, now)
        return cid

    def propose_schedule(self, link: int, schedule: Schedule, now: float,
                         activate_cycle: int | None = None, lead_cycles: int = 2) -> ScheduleUpdate:
        """Topside: announce ``schedule`` for ``link`` from cycle ``activate_cycle`` (default: the
        current cycle + ``lead_cycles``). Both ends switch at that cycle boundary once the vehicle
        has acked; if the ack is late, topside switches when it first sees the new version."""
        st = self._link(link)
        cur = st.current.cycle_at(now)
        n = cur + lead_cycles if activate_cycle is None else activate_cycle
        if n <= cur:
            raise ConfigError(f"activation cycle {n} is not after the current cycle {cur}")
        cid = self.next_command_id()
        msg = schedule.to_message(cid, link, n)
        self.send_command(msg, now)
        st.proposed[cid] = _PendingSchedule(schedule.starting_at(n, st.current.cycle_start(n)), cid)
        return msg

    def on_command_ack(self, ack: CommandAck, now: float) -> CommandResult:
        """Topside: the vehicle's answer to one of our commands, through the core tracker's
        states (:mod:`coex_core.tracker`): a PENDING answer keeps the command, whose final
        answer follows; a final one ends it."""
        tracked = self._commands.get(ack.command_id)
        command = None
        if tracked is not None:
            command = tracked.message
            tracked.apply(answer_event(ack.status.name), now, answer=ack.status.name)
            if not tracked.open:
                del self._commands[ack.command_id]
        for link, st in self._links.items():
            prop = st.proposed.pop(ack.command_id, None)
            if prop is not None and ack.status == AckStatus.ACCEPTED:
                if now >= prop.schedule.epoch:
                    self._switch(link, prop.schedule, now, "activation")
                else:
                    st.pending = prop
        if isinstance(command, LinkControl) and ack.status == AckStatus.ACCEPTED:
            target = self._links.get(command.link)
            if target is not None and target.enabled != command.enabled:
                self.set_link_enabled(command.link, command.enabled, now)
        result = CommandResult(now, ack.command_id, ack.status, command)
        self._events.append(result)
        return result

"""Commands of a channel manager: applying them (vehicle) and sending and tracking them (topside).

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

from collections.abc import Iterable
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
from ..messages import command_id as command_id_of
from ..tracker import Event, State, Tracked, answer_event
from .events import (
    CommandApplied,
    CommandResult,
    CommandUnanswered,
    Dropped,
)
from .links import (
    CONTROL_STREAM,
    _PendingSchedule,
)
from .packing import PackingMixin
from .schedule import Schedule, resolve_cycle

__all__ = ["ANSWER_CYCLES", "CommandsMixin"]

#: TDMA cycles (of the node's longest) after its last send within which a command should be
#: answered: past them it shows as "no answer" (:class:`CommandUnanswered`); an answer that comes
#: after all still counts
ANSWER_CYCLES = 3.0


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
        cid = command_id_of(command) or 0
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
        sched = new.starting_at(n, st.current.cycle_start(n))
        if st.pending is not None and st.pending.schedule == sched:
            # the same schedule again under a new command id: in a network of several nodes,
            # the proposer's commit (every node agreed); it takes effect at its activation
            st.pending.committed = True
            st.pending.command_id = c.command_id
            return AckStatus.ACCEPTED, "committed"
        st.pending = _PendingSchedule(sched, c.command_id, fleet=self._fleet(st))
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

    def send_command(self, command: Message, now: float, *, dst: int | None = None) -> int:
        """Queue a command (on the control stream, acked) and remember it until its
        CommandAck arrives. Returns its command id. ``dst``: the node it is for (0: every
        node; ``None``: the link's ``dst``); a CommandAck from another node does not answer it."""
        cid = command_id_of(command) or 0
        tracked = self._commands[cid] = Tracked(command)
        tracked.apply(Event.SEND, now)
        self._command_dst[cid] = dst
        self.push(CONTROL_STREAM, command, now, dst=dst)
        return cid

    def answers(self, command_id: int, src: int) -> bool:
        """Whether a CommandAck from node ``src`` can answer our command ``command_id``: the
        command was addressed to ``src``, to every node, or to the link's destination."""
        dst = self._command_dst.get(command_id)
        return dst is None or dst in (0, src)

    def propose_schedule(self, link: int, schedule: Schedule, now: float,
                         activate_cycle: int | None = None, lead_cycles: int | None = None,
                         peers: Iterable[int] | None = None) -> ScheduleUpdate:
        """Topside: announce ``schedule`` for ``link`` from cycle ``activate_cycle`` (default: the
        current cycle + ``lead_cycles``: 2, or 4 in a network of several nodes). Both ends switch
        at that cycle boundary once the vehicle has acked; if the ack is late, topside switches
        when it first sees the new version.

        In a network of several nodes (the link's safe schedule gives slots to more than two
        nodes, or ``peers`` is given) the update is broadcast and must be agreed by every
        peer (default: every node the safe, current or new schedule gives a slot) before it
        takes effect: when all have accepted, the proposer announces it again under a new
        command id (the commit) and every node switches at the activation; a peer silent for
        ``watchdog_cycles`` cycles is not waited for. Without every ACCEPTED before the
        activation (a rejection, acks lost) nothing changes (docs/channel.md)."""
        st = self._link(link)
        fleet = peers is not None or self._fleet(st)
        lead = (4 if fleet else 2) if lead_cycles is None else lead_cycles
        cur = st.current.cycle_at(now)
        n = cur + lead if activate_cycle is None else activate_cycle
        if n <= cur:
            raise ConfigError(f"activation cycle {n} is not after the current cycle {cur}")
        if fleet:
            members = set(peers) if peers is not None else {
                s.owner for sch in (st.safe, st.current, schedule) for s in sch.slots}
            awaiting = {p for p in members if p not in (0, self.node_id)}
            for p in awaiting:
                if not 1 <= p <= 15:
                    raise ConfigError(f"peer {p} is not a node id 1..15")
        cid = self.next_command_id()
        msg = schedule.to_message(cid, link, n)
        self.send_command(msg, now, dst=0 if fleet else None)
        sched = schedule.starting_at(n, st.current.cycle_start(n))
        st.proposed[cid] = _PendingSchedule(sched, cid, awaiting if fleet else set(), fleet)
        if fleet:
            self._settle_proposals(link, now)
        return msg

    def _tick(self, now: float) -> None:
        for link, st in self._links.items():
            if st.proposed:
                self._settle_proposals(link, now)
        self._expire_commands(now)
        super()._tick(now)

    def _expire_commands(self, now: float) -> None:
        """Commands sent to one node and unanswered for :data:`ANSWER_CYCLES` cycles: "no
        answer" (kept, so that an answer that comes after all still lands)."""
        if not self._commands:
            return
        wait = ANSWER_CYCLES * max((st.current.cycle for st in self._links.values()), default=0.0)
        for cid, tracked in self._commands.items():
            if (tracked.state is State.SENT and tracked.sent_at is not None and now - tracked.sent_at >= wait
                    and self._command_dst.get(cid) != 0):
                tracked.apply(Event.GIVE_UP, now)
                self.stats["unanswered"] = self.stats.get("unanswered", 0) + 1
                self._events.append(CommandUnanswered(now, cid, tracked.message, self._command_dst.get(cid)))

    def _settle_proposals(self, link: int, now: float) -> None:
        """The proposer's proposals to a network of several nodes: a peer silent for
        ``watchdog_cycles`` cycles is no longer awaited; once none is, the proposal is committed
        (announced again, and pending here); one not agreed before its activation is dropped."""
        st = self._links[link]
        silent_after = st.cfg.watchdog_cycles * st.current.cycle
        for cid, prop in list(st.proposed.items()):
            if not prop.fleet:
                continue
            if now >= prop.schedule.epoch - 1e-9:
                del st.proposed[cid]
                self.stats["schedules_not_agreed"] = self.stats.get("schedules_not_agreed", 0) + 1
                continue
            for p in list(prop.awaiting):
                heard = self._peer_heard.get((link, p))
                if heard is None or now - heard > silent_after:
                    prop.awaiting.discard(p)
            if prop.awaiting:
                continue
            del st.proposed[cid]
            commit = self.next_command_id()
            msg = prop.schedule.to_message(commit, link, prop.schedule.first_cycle)
            self.send_command(msg, now, dst=0)
            st.proposed.pop(commit, None)
            st.pending = _PendingSchedule(prop.schedule, commit, set(), True, True)

    def on_command_ack(self, ack: CommandAck, now: float, src: int | None = None) -> CommandResult | None:
        """Topside: the vehicle's answer to one of our commands, through the core tracker's
        states (:mod:`coex_core.tracker`; a PENDING answer keeps the command, whose final answer
        follows). ``src``: the node that answered; an answer to a
        command addressed to another node is ignored (``None``). A command to every node
        (``dst`` 0) stays known for every node's answer."""
        if src is not None and not self.answers(ack.command_id, src):
            self.stats["foreign_answers"] = self.stats.get("foreign_answers", 0) + 1
            return None
        # through the core tracker's states (coex_core.tracker): a PENDING answer keeps the
        # command, a final one ends it; a command to every node stays for every node's answer
        tracked = self._commands.get(ack.command_id)
        command = None
        if tracked is not None:
            command = tracked.message
            if self._command_dst.get(ack.command_id) != 0:
                tracked.apply(answer_event(ack.status.name), now, answer=ack.status.name)
                if not tracked.open:
                    del self._commands[ack.command_id]
                    self._command_dst.pop(ack.command_id, None)
        for link, st in self._links.items():
            fprop = st.proposed.get(ack.command_id)
            if fprop is not None and fprop.fleet:
                if ack.status == AckStatus.ACCEPTED:
                    if src is not None:
                        fprop.awaiting.discard(src)
                elif ack.status != AckStatus.PENDING:  # a node refused it: nothing changes
                    del st.proposed[ack.command_id]
                    self.stats["schedules_not_agreed"] = self.stats.get("schedules_not_agreed", 0) + 1
                self._settle_proposals(link, now)
                continue
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
        result = CommandResult(now, ack.command_id, ack.status, command, src)
        self._events.append(result)
        return result

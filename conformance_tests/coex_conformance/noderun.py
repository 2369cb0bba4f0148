"""The plugin under test in two real nodes beside every other plugin (:mod:`.companions`),
over a lossy simulated acoustic link with the NUI TDMA schedule.

Each modality gets its own stream on the vehicle and its receiver on topside. Every message a
receiver is handed and every request a sender is handed is checked against the modality's own
declaration (``Modality.handles``): anything else is a misrouting.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from coex import (
    AcousticChannel,
    ChannelManager,
    LinkConfig,
    Message,
    Modality,
    ModalityReceiver,
    ModalitySender,
    Node,
    Received,
    Schedule,
    SimNetwork,
    SimulatedClock,
    StreamConfig,
)
from coex.messages import CommandAck
from coex.wire import encoded_size

from .companions import Companion, companions

VEHICLE, TOPSIDE = 2, 1
#: simulated seconds between convergence checks
CHECK_EVERY = 60.0


@dataclass
class Part:
    name: str
    modality: type[Modality]
    sender: ModalitySender
    receiver: ModalityReceiver
    converged: Callable[[ModalitySender, ModalityReceiver], bool]
    converged_at: float | None = None
    misrouted: list[str] = field(default_factory=list)
    #: (time, bytes) of every fill / spare answer of the sender
    sent: list[tuple[float, int]] = field(default_factory=list)


class NodeRun:
    """Build with the plugin under test's fixtures; :meth:`run_until_converged`, then
    :meth:`run` on to watch the senders."""

    def __init__(self, modality: Modality, sender_config: Any, receiver_config: Any,
                 sample_inputs: Any, converged: Callable[[ModalitySender, ModalityReceiver], bool],
                 start_requests: Callable[[ModalityReceiver, float], None] | None, loss: float,
                 seed: int = 5, others: Sequence[Companion] = ()) -> None:
        under_test = Companion(modality.name, lambda: modality, lambda: list(sample_inputs), converged,
                               lambda: sender_config, lambda: receiver_config, start_requests)
        self.under_test = modality.name
        # a companion the plugin under test is (or derives from) is replaced by it
        chosen = [under_test] + [c for c in (*others, *companions())
                                 if c.name != modality.name and not isinstance(modality, type(c.modality()))]
        names = [c.name for c in chosen]
        chosen = [c for i, c in enumerate(chosen) if c.name not in names[:i]]  # each plugin once
        schedule = Schedule.simple([TOPSIDE, VEHICLE, VEHICLE, TOPSIDE, VEHICLE, VEHICLE], 20.0, 2.0)
        self.vehicle = Node(ChannelManager(VEHICLE, [LinkConfig(0, schedule, dst=TOPSIDE)]))
        self.topside = Node(ChannelManager(TOPSIDE, [LinkConfig(0, schedule, dst=VEHICLE)]))
        self.parts: list[Part] = []
        inputs: list[tuple[float, int, Any]] = []
        for i, c in enumerate(chosen):
            mod = c.modality()
            cls = type(mod)
            part = Part(c.name, cls, mod.sender(c.sender_config()), mod.receiver(c.receiver_config()), c.converged)
            self._watch(part)
            self.vehicle.add_sender(cls, part.sender, StreamConfig(10 + i, c.name))
            self.topside.add_receiver(cls, part.receiver)
            self.parts.append(part)
            inputs += [(float(t), i, data) for t, data in c.sample_inputs()]
        for t, i, data in sorted(inputs, key=lambda x: (x[0], x[1])):
            self.parts[i].sender.ingest(data, t)
        start = max((t for t, _, _ in inputs), default=0.0) + 1.0
        for c, part in zip(chosen, self.parts, strict=True):
            if c.start_requests is not None:
                c.start_requests(part.receiver, start)
        self.net = SimNetwork({0: AcousticChannel(loss=loss, seed=seed)}, SimulatedClock(start))
        self.net.add_node(self.vehicle, (0.0, 0.0, 100.0))
        self.net.add_node(self.topside, (200.0, 0.0, 0.0))
        self.unrouted: list[str] = []

    @staticmethod
    def _watch(part: Part) -> None:
        """Record misrouted messages and the bytes the sender gives (instance attributes wrap
        the methods; the node calls them as usual)."""
        receiver, sender, cls = part.receiver, part.sender, part.modality
        receive, handle = receiver.receive, sender.handle
        fill, spare = sender.fill, sender.spare

        def checked_receive(m: Message, now: float) -> Any:
            # a CommandAck goes to the receiver whose request it answers
            if not isinstance(m, CommandAck) and not cls.handles(m):
                part.misrouted.append(f"receiver of {part.name!r} was handed {m!r:.120}")
            return receive(m, now)

        def checked_handle(m: Message, now: float) -> Any:
            if not cls.handles(m):
                part.misrouted.append(f"sender of {part.name!r} was handed {m!r:.120}")
            return handle(m, now)

        def counted(pull: Callable[[int, float], list[Message]]) -> Callable[[int, float], list[Message]]:
            def wrapped(max_bytes: int, now: float) -> list[Message]:
                out = pull(max_bytes, now)
                n = sum(encoded_size(m) for m in out)
                if n:
                    part.sent.append((now, n))
                return out
            return wrapped

        receiver.receive = checked_receive  # type: ignore[method-assign,assignment]
        sender.handle = checked_handle  # type: ignore[method-assign,assignment]
        sender.fill = counted(fill)  # type: ignore[method-assign,assignment]
        sender.spare = counted(spare)  # type: ignore[method-assign,assignment]

    @property
    def now(self) -> float:
        return self.net.now

    def run(self, seconds: float) -> None:
        end = self.net.now + seconds
        while self.net.now < end:
            self.net.run(min(self.net.now + CHECK_EVERY, end))
            self._collect()

    def _collect(self) -> None:
        for part in self.parts:
            if part.converged_at is None and part.converged(part.sender, part.receiver):
                part.converged_at = self.net.now
        owned = [p.modality for p in self.parts]
        for node in (self.vehicle, self.topside):
            for ev in node.events():
                if isinstance(ev, Received) and any(cls.handles(ev.message) for cls in owned):
                    self.unrouted.append(f"node {node.node_id} left {ev.message!r:.120} unrouted")

    def run_until_converged(self, limit: float) -> None:
        """Run until every part has converged, at most ``limit`` simulated seconds."""
        end = self.net.now + limit
        while self.net.now < end and any(p.converged_at is None for p in self.parts):
            self.run(CHECK_EVERY)

    def part(self, name: str) -> Part:
        return next(p for p in self.parts if p.name == name)

"""TDMA slots and versioned schedules derived from a shared epoch (no messages to keep time)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

from ..errors import ConfigError
from ..messages import ScheduleUpdate, Slot
from ..state import persistent

__all__ = ["CYCLE_MODULUS", "Schedule", "SlotWindow", "TdmaSlot", "resolve_cycle"]

#: ``ScheduleUpdate.activate_cycle`` carries the cycle number modulo 2^16.
CYCLE_MODULUS = 1 << 16


@persistent("channel.TdmaSlot")
@dataclass(frozen=True)
class TdmaSlot:
    """One slot: ``owner`` transmits in it; nothing may start later than ``guard`` seconds before
    its end; only streams of priority >= ``min_priority`` (and, if ``tags`` is not empty, carrying
    one of the tags) may use it. Tier-0 streams (status, control) ignore both filters."""

    owner: int
    duration: float
    guard: float = 0.0
    min_priority: int = 0
    tags: frozenset[str] = field(default_factory=frozenset)

    def __post_init__(self) -> None:
        if not (self.duration > 0 and math.isfinite(self.duration)):
            raise ConfigError(f"slot duration must be positive, got {self.duration}")
        if not 0 <= self.guard < self.duration:
            raise ConfigError(f"slot guard {self.guard} must be in [0, duration {self.duration})")
        if not 0 <= self.owner <= 15:
            raise ConfigError(f"slot owner {self.owner} is not a node id 0..15")

    def to_dict(self) -> dict[str, Any]:
        return {"owner": self.owner, "duration": self.duration, "guard": self.guard,
                "min_priority": self.min_priority, "tags": sorted(self.tags)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TdmaSlot:
        return cls(int(d["owner"]), float(d["duration"]), float(d.get("guard", 0.0)),
                   int(d.get("min_priority", 0)), frozenset(d.get("tags", ())))


@dataclass(frozen=True)
class SlotWindow:
    """Where a time falls in a schedule: slot ``index`` of cycle ``cycle``, ``[start, end)``."""

    cycle: int
    index: int
    slot: TdmaSlot
    start: float
    end: float


@persistent("channel.Schedule")
@dataclass(frozen=True)
class Schedule:
    """A TDMA cycle: ``slots`` in order, repeating from ``epoch``, which is the start of cycle
    number ``first_cycle``. Every node computes the same slot for the same time."""

    slots: tuple[TdmaSlot, ...]
    version: int = 0
    epoch: float = 0.0
    first_cycle: int = 0

    def __post_init__(self) -> None:
        if not self.slots:
            raise ConfigError("a schedule needs at least one slot")
        if not 0 <= self.version <= 15:
            raise ConfigError(f"schedule version {self.version} outside 0..15")

    @cached_property
    def cycle(self) -> float:
        """Cycle length in seconds."""
        return float(sum(s.duration for s in self.slots))

    def cycle_at(self, t: float) -> int:
        return self.first_cycle + math.floor((t - self.epoch) / self.cycle + 1e-9)

    def cycle_start(self, n: int) -> float:
        return self.epoch + (n - self.first_cycle) * self.cycle

    def window(self, t: float) -> SlotWindow:
        """The slot that contains time ``t``."""
        n = self.cycle_at(t)
        start = self.cycle_start(n)
        for i, s in enumerate(self.slots):
            end = start + s.duration
            if t < end - 1e-9 or i == len(self.slots) - 1:
                return SlotWindow(n, i, s, start, end)
            start = end
        raise AssertionError("unreachable")  # pragma: no cover

    def next_window(self, t: float, owner: int) -> SlotWindow | None:
        """The first slot owned by ``owner`` whose interval contains ``t`` or starts after it."""
        w = self.window(t)
        for _ in range(len(self.slots) + 1):
            if w.slot.owner == owner:
                return w
            w = self.window(w.end + 1e-6)
        return None

    def owns_any(self, owner: int, packet_seconds: float) -> bool:
        """Whether ``owner`` has a slot long enough for one packet before its guard."""
        return any(s.owner == owner and s.duration - s.guard >= packet_seconds for s in self.slots)

    def starting_at(self, cycle: int, epoch: float, version: int | None = None) -> Schedule:
        """The same slots, with cycle ``cycle`` starting at ``epoch``."""
        return Schedule(self.slots, self.version if version is None else version, epoch, cycle)

    # -------------------------------------------------------------------- wire forms
    def to_message(self, command_id: int, link: int, activate_cycle: int) -> ScheduleUpdate:
        return ScheduleUpdate(
            command_id % 256, link, self.version, activate_cycle % CYCLE_MODULUS,
            tuple(Slot(s.owner, s.duration, s.guard, s.min_priority) for s in self.slots),
        )

    @classmethod
    def from_message(cls, msg: ScheduleUpdate) -> Schedule:
        return cls(tuple(TdmaSlot(s.owner, float(s.duration), float(s.guard), s.min_priority)
                         for s in msg.slots), msg.version)

    def to_dict(self) -> dict[str, Any]:
        return {"version": self.version, "epoch": self.epoch, "first_cycle": self.first_cycle,
                "slots": [s.to_dict() for s in self.slots]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Schedule:
        return cls(tuple(TdmaSlot.from_dict(s) for s in d["slots"]), int(d.get("version", 0)),
                   float(d.get("epoch", 0.0)), int(d.get("first_cycle", 0)))

    @classmethod
    def simple(cls, owners: list[int], duration: float, guard: float = 0.0, *, version: int = 0,
               epoch: float = 0.0) -> Schedule:
        """Equal slots, one per entry of ``owners``."""
        return cls(tuple(TdmaSlot(o, duration, guard) for o in owners), version, epoch)


def resolve_cycle(wire_cycle: int, current: int) -> int:
    """The absolute cycle number with ``wire_cycle`` = n mod 2^16 nearest after ``current``
    (within half the modulus); a result <= ``current`` means the announced cycle has passed."""
    base = current - (current % CYCLE_MODULUS)
    best = min((base + d + wire_cycle for d in (-CYCLE_MODULUS, 0, CYCLE_MODULUS)),
               key=lambda n: abs(n - current))
    return best

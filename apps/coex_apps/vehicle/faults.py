"""The bits of ``VehicleStatus.faults`` (``spec/wire-format.md``: fault flags, vehicle specific)
that ``coex vehicle`` sets, and what the console says when one comes or goes
(``docs/deploy.md``, "Faults shown topside"). Bits 0 and 1 are CoEx's; an integrator's own
faults may use the others."""

from __future__ import annotations

__all__ = ["FAULT_PEER_SILENT", "FAULT_STORE", "FAULT_WORDS", "fault_changes"]

#: the vehicle's store cannot write (a full disk, a read-only or damaged file): what it takes
#: now is not kept across a restart (images wait, survey reports are held)
FAULT_STORE = 0x01
#: the vehicle hears nothing from topside (``coex_runtime.peers.SILENT_CYCLES`` TDMA cycles)
FAULT_PEER_SILENT = 0x02

#: bit -> (said when it comes, said when it goes)
FAULT_WORDS: dict[int, tuple[str, str]] = {
    FAULT_STORE: ("vehicle: its store cannot write (disk full, read-only or damaged): images and survey "
                  "reports wait, what else it takes is not kept across a restart",
                  "vehicle: its store writes again"),
    FAULT_PEER_SILENT: ("vehicle: it hears nothing from topside (check topside's modem: src, dest, rate, TDMA)",
                        "vehicle: it hears topside again"),
}


def fault_changes(before: int, now: int) -> list[tuple[str, bool]]:
    """``(sentence, came)`` for each of CoEx's bits that changed from ``before`` to ``now``."""
    return [(FAULT_WORDS[bit][0 if now & bit else 1], bool(now & bit))
            for bit in sorted(FAULT_WORDS) if (before ^ now) & bit]

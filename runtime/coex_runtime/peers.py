"""Hearing nothing from the peer: a running node that has heard no frame from its peer on a link
for :data:`SILENT_CYCLES` cycles of that link's TDMA says so, once, and once again when it hears
it again. A link that carries nothing is otherwise silent on both sides (a modem's ``dest`` set
to the wrong node, a ``src`` the peer does not expect, a peer that is down, slots too short to
send in): the vehicle daemon logs it and sets a fault bit of its status, topside logs it and
shows it in the console (``docs/deploy.md``, "Hearing nothing from the peer").

Sans-I/O: :class:`PeerWatch` reads the channel manager's own record of when it last heard each
peer (``ChannelManager.last_heard``) and the clock it is given."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from coex_core.channel.manager import ChannelManager

__all__ = ["SILENT_CYCLES", "PeerSilence", "PeerWatch"]

#: TDMA cycles of a link without a frame from the peer before a node says it hears nothing (the
#: NUI cycle of 6 x 20 s: 10 minutes). A working link carries something every cycle: the
#: vehicle's queue report, topside's frame acknowledgements.
SILENT_CYCLES = 5


@dataclass(frozen=True)
class PeerSilence:
    """A change: ``peer`` went silent on ``link`` (``silent``), or was heard again (not
    ``silent``); ``seconds``: how long nothing had been heard; ``cycles``: as TDMA cycles."""

    link: int
    peer: int
    silent: bool
    seconds: float
    cycles: float

    def text(self, name: str = "") -> str:
        """One sentence for a log (``name``: what the peer is called, e.g. "topside")."""
        who = f"{name} (node {self.peer})" if name else f"node {self.peer}"
        took = _duration(self.seconds)
        if self.silent:
            return (f"link {self.link}: nothing heard from {who} for {self.cycles:.0f} TDMA cycles ({took}): "
                    "check both modems (src, dest, rate), the TDMA and that the other side runs")
        return f"link {self.link}: {who} heard again after {took} of silence"


def _duration(seconds: float) -> str:
    s = max(0.0, float(seconds))
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


class PeerWatch:
    """Watches when ``peers`` were last heard on every enabled link of ``manager`` (see the
    module docstring). :meth:`check` returns the changes since the last call."""

    def __init__(self, manager: ChannelManager, peers: Iterable[int], *, cycles: float = SILENT_CYCLES) -> None:
        self.manager = manager
        self.peers = tuple(peers)
        self.cycles = float(cycles)
        #: (link, peer) -> since when nothing has been heard, while the peer is silent
        self.silent: dict[tuple[int, int], float] = {}
        self._start: float | None = None

    def check(self, now: float) -> list[PeerSilence]:
        if self._start is None:
            self._start = now  # a peer heard before a restart counts from the restart
        out: list[PeerSilence] = []
        for link in self.manager.links:
            if not self.manager.link_state(link)["enabled"]:
                continue
            cycle = self.manager.schedule(link).cycle
            for peer in self.peers:
                heard = self.manager.last_heard(link, peer)
                since = max(self._start, heard if heard is not None else self._start)
                key = (link, peer)
                if key in self.silent:
                    if heard is not None and heard > self.silent[key]:
                        began = self.silent.pop(key)
                        out.append(PeerSilence(link, peer, False, heard - began, (heard - began) / cycle))
                elif now - since >= self.cycles * cycle:
                    self.silent[key] = since
                    out.append(PeerSilence(link, peer, True, now - since, (now - since) / cycle))
        return out

    def any_silent(self) -> bool:
        return bool(self.silent)

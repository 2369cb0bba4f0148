"""Priorities that follow the link: the throughput a channel manager measures, and whether its
policy finds the link low (``docs/channel.md``).

* **Throughput.** Each link's *capacity* is what this node's slots can carry: in every slot it
  owns, as many full packets as fit before the slot's guard (the rule of ``can_transmit``),
  each ``frames x frame_bytes``, per second of the cycle. Its *throughput* is that capacity less
  the measured frame loss (:meth:`~coex_core.channel.delivery.DeliveryMixin.frame_loss`, from the
  peer's frame acks): the bytes per second this node's frames deliver when it has work. The
  node's throughput is the sum over its enabled, unmuted links.
* **Low.** The link is *low* once the node's throughput falls below ``low_throughput``
  (48 B/s by default) and stays low until it is back above ``normal_throughput`` (64 B/s):
  a Micromodem at rate 1 (32 B/s of the NUI cycle's vehicle slots) is always low, rate 5 at
  60 % loss (164 B/s) never. Before any loss is measured the capacity counts as delivered.
* **Telling the senders.** Before each packet it builds, the manager gives every sender the
  measure (:meth:`~coex_core.modality.ModalitySender.throughput`): each sender decides what it
  sends first while the link is low (the bathymetry sender keeps its finest level out of the
  background and sends it as spare work, beside the neighbourhoods of detections and the
  answers to requests; the imagery sender sends a requested image's bytes at most twice before
  an ack and the most interesting previews first).

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

import math
from typing import Any

from .acks import AcksMixin

__all__ = ["LOW_THROUGHPUT", "NORMAL_THROUGHPUT", "PolicyMixin"]

#: below this throughput (bytes per second delivered, every link together) the link is low
LOW_THROUGHPUT = 48.0
#: a low link is normal again above this (hysteresis: the loss estimate moves frame by frame)
NORMAL_THROUGHPUT = 64.0


def policy_fields() -> dict[str, Any]:
    """The policy's state of a new manager, by attribute (also what a ``channel.ChannelManager``
    saved before the policy existed is upgraded with)."""
    return {"low_throughput": LOW_THROUGHPUT, "normal_throughput": NORMAL_THROUGHPUT, "_low": False}


class PolicyMixin(AcksMixin):
    low_throughput: float
    normal_throughput: float
    #: whether the policy finds the link low now
    _low: bool

    def _policy_state(self) -> None:
        """Create the policy's state (``__init__``)."""
        for k, v in policy_fields().items():
            setattr(self, k, v)

    def capacity(self, link: int, node: int | None = None) -> float:
        """Bytes per second this node's slots (or ``node``'s) can carry on ``link`` (its current
        schedule): the full packets that fit in each slot it owns before the slot's guard, per
        cycle."""
        st = self._link(link)
        cfg, sched = st.cfg, st.current
        per = cfg.packet_time + cfg.gap
        owner = self.node_id if node is None else node
        packets = 0
        for s in sched.slots:
            if s.owner != owner:
                continue
            room = s.duration - s.guard - cfg.packet_time
            if room >= -1e-9 and per > 0:
                packets += math.floor(room / per + 1e-9) + 1
        return packets * cfg.n_frames * cfg.fbytes / sched.cycle

    def throughput(self, link: int | None = None) -> float:
        """Bytes per second this node's frames deliver: ``link``'s capacity less its measured
        frame loss, or (``None``) the sum over the enabled, unmuted links."""
        if link is not None:
            loss = self.frame_loss(link)
            return self.capacity(link) * (1.0 - (loss or 0.0))
        return sum(self.throughput(k) for k, st in self._links.items() if st.enabled and not st.muted)

    def peer_throughput(self, peer: int, link: int | None = None) -> float:
        """Bytes per second ``peer``'s frames deliver here: its slots' capacity on ``link`` less
        the loss of its frames measured here (gaps in their sequence numbers), or (``None``) the
        sum over the enabled links. What topside can tell of the vehicle's link."""
        if link is not None:
            seen = self._rx_outcomes.get(link)
            loss = 1.0 - sum(seen) / len(seen) if seen else 0.0
            return self.capacity(link, peer) * (1.0 - loss)
        return sum(self.peer_throughput(peer, k) for k, st in self._links.items() if st.enabled)

    def link_low(self) -> bool:
        """Whether the policy finds the link low (as of the last packet built)."""
        return self._low

    def _follow_link(self, now: float) -> None:
        """Update the policy's state from the measured throughput and tell every sender."""
        bps = self.throughput()
        if self._low and bps >= self.normal_throughput:
            self._low = False
        elif not self._low and bps < self.low_throughput:
            self._low = True
        for sid, s in self._streams.items():
            if s.sender is None:
                continue
            try:  # declared on ModalitySender (default: nothing)
                s.sender.throughput(bps, self._low, now)
            except Exception as exc:  # a sender's hook never stops the channel
                self._sender_failed(now, sid, f"throughput() failed: {type(exc).__name__}: {exc}")

    def link_state(self, link: int) -> dict[str, Any]:
        """:meth:`DeliveryMixin.link_state`, with the link's ``capacity`` and ``throughput``
        (bytes per second) and whether the policy finds the node's links ``low``."""
        out = super().link_state(link)
        out["capacity"] = round(self.capacity(link), 1)
        out["throughput"] = round(self.throughput(link), 1)
        out["low"] = self._low
        return out

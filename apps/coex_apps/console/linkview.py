"""The console's links and queues: packets, frames and throughput per link, both ends' modems,
the TDMA schedules, and the vehicle's queue report.

A part of :class:`~coex_apps.console.state.ConsoleState` (its API is the state's).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

from coex import messages as m
from coex import unwrap
from coex.wire import encoded_size

from .model import ConsoleModel
from .words import _num

__all__ = ["LinkView"]


class LinkView(ConsoleModel):
    """The link and queues part of :class:`~coex_apps.console.state.ConsoleState`."""

    def set_schedule(self, link: int, schedule: Any) -> None:
        """Record the TDMA schedule a link runs (for the timeline)."""
        d = schedule.to_dict() if hasattr(schedule, "to_dict") else dict(schedule)
        slots = [dict(s) for s in d.get("slots", [])]
        self.schedules[int(link)] = {
            "link": int(link), "version": int(d.get("version", 0)),
            "active_version": int(d.get("version", 0)),
            "epoch": float(d.get("epoch", 0.0)), "first_cycle": int(d.get("first_cycle", 0)),
            "cycle": float(sum(float(s["duration"]) for s in slots)),
            "slots": [{"owner": int(s["owner"]), "duration": float(s["duration"]),
                       "guard": float(s.get("guard", 0.0)),
                       "min_priority": int(s.get("min_priority", 0))} for s in slots],
            "proposed": None,
        }
        self._link(int(link))
        self._touch("link")

    def _link(self, link: int) -> dict[str, Any]:
        lk = self.links.get(link)
        if lk is None:
            lk = self.links[link] = {"link": link, "enabled": True, "muted": False,
                                     "packets": 0, "frames": 0, "bad_frames": 0, "snr": None,
                                     "doppler": None, "last": None, "history": deque(maxlen=240)}
        return lk

    def _count_rx(self, msg: m.Message, now: float, link: int | None) -> None:
        """Throughput: the bytes of the messages received, per TDMA cycle of the link (60 s
        without a schedule). Not a change of its own: the bins go out with the link section's
        next change (the modem's report of the packet, topside's frame counters)."""
        try:
            size = encoded_size(msg)
        except Exception:  # a message the codec cannot build (a test double): not counted
            return
        if link is None:
            link = min(self.links, default=0)
        lk = self._link(int(link))
        sch = self.schedules.get(int(link))
        cycle = float(sch["cycle"]) if sch and sch.get("cycle", 0) > 0 else 60.0
        epoch = float(sch["epoch"]) if sch else 0.0
        start = epoch + math.floor((now - epoch) / cycle) * cycle
        bins = lk.get("_rx")
        if not isinstance(bins, deque):
            bins = lk["_rx"] = deque(maxlen=240)
        if bins and abs(bins[-1][0] - start) < 1e-6:
            bins[-1][1] += size
        else:
            bins.append([start, size, cycle])
        lk["rx_bytes"] = int(lk.get("rx_bytes", 0)) + size

    def _on_link_status(self, s: m.LinkStatus, now: float) -> None:
        lk = self._link(s.link)
        t = unwrap(s.stamp, now)
        lk["packets"] += 1
        lk["frames"] += s.frames
        lk["bad_frames"] += s.bad_frames
        lk["snr"], lk["doppler"], lk["last"] = s.snr, s.doppler, t
        lk["history"].append((t, s.snr, s.frames, s.bad_frames))
        self._touch("link")

    def _on_link_health(self, h: m.LinkHealth, now: float) -> None:
        """The vehicle's report of one of its modems' outages (gone and back)."""
        from coex_transports.recovery import describe_seconds

        lk = self._link(h.link)
        t = unwrap(h.stamp, now)
        prev = lk.get("vehicle_modem")
        if prev is not None and prev["t"] > t:
            return  # an older report arriving late
        lk["vehicle_modem"] = {"t": _num(t, 1), "up": h.up, "outages": h.outages, "down_total": h.down_total,
                               "last_down": h.last_down}
        if h.up:
            text = (f"vehicle modem {h.link} was down {describe_seconds(h.last_down)} (outage {h.outages}; "
                    f"{describe_seconds(h.down_total)} down in all)")
        else:
            text = f"vehicle modem {h.link} is down (outage {h.outages}, reported over another link)"
        self._log(now, text, "warn")
        self._touch("link")

    def set_own_modem(self, link: int, up: bool, outages: int, down_total: float, last_down: float,
                      last_error: str, now: float) -> None:
        """Topside's own modem on ``link``: up or being reopened, its outages so far."""
        from coex_transports.recovery import describe_seconds

        lk = self._link(link)
        new = {"up": up, "outages": outages, "down_total": _num(down_total, 0), "last_down": _num(last_down, 0),
               "last_error": last_error if not up else ""}
        old = lk.get("topside_modem")
        if old is not None and (old["up"], old["outages"]) == (up, outages):
            if not up:  # the outage grows: shown, not logged
                lk["topside_modem"] = new
            return
        lk["topside_modem"] = new
        if outages and (old is not None or not up):
            self._log(now, f"topside modem {link}: " + (
                f"back after {describe_seconds(last_down)} (outage {outages})" if up else
                f"{last_error}; reopening it"), "warn")
        self._touch("link")

    def _on_queue_status(self, q: m.QueueStatus, now: float) -> None:
        self.queue_stamp = unwrap(q.stamp, now)
        for st in q.streams:
            row = self.streams.setdefault(st.stream, {"stream": st.stream, "drops_total": 0})
            row.update(enabled=st.enabled, tier=st.tier, priority=st.priority, depth=st.depth,
                       queued_bytes=st.queued_bytes, oldest_age=st.oldest_age, drops=st.drops)
            row["drops_total"] += st.drops
        self._touch("queues")

    def _snap_link(self) -> dict[str, Any]:
        links = []
        for lk in sorted(self.links.values(), key=lambda x: x["link"]):
            d = {k: v for k, v in lk.items() if k != "history" and not k.startswith("_")}
            d["history"] = [[_num(t, 1), snr, f, b] for t, snr, f, b in lk["history"]]
            # bytes received per cycle: [cycle start, bytes, cycle length] (the open cycle last)
            d["throughput"] = [[_num(t, 1), int(n), _num(c, 1)]
                               for t, n, c in lk.get("_rx") or ()]
            d["age"] = _num(self.now - lk["last"], 1) if lk["last"] is not None else None
            links.append(d)
        schedules = [{k: v for k, v in self.schedules[link].items() if not k.startswith("_")}
                     for link in sorted(self.schedules)]
        return {"links": links, "schedules": schedules,
                "node_id": self.node_id, "vehicle_id": self.vehicle_id,
                "bad_frames": self.bad_frames}

    def _snap_queues(self) -> dict[str, Any]:
        rows = []
        for sid, row in sorted(self.streams.items()):
            d = dict(row)
            d["name"] = self.stream_names.get(sid, f"stream {sid}")
            rows.append(d)
        return {"t": self.queue_stamp,
                "age": _num(self.now - self.queue_stamp, 1) if self.queue_stamp else None,
                "streams": rows}

"""The console's words: durations, times of day, gaps, regions, survey commands and what the
vehicle's answer to a command means. Pure functions of their arguments (the routing table of
the installed modalities is made once, by the core's :mod:`coex_core.routing`)."""

from __future__ import annotations

import math
from typing import Any

from coex import messages as m
from coex_core.routing import Routes, declared_ids

__all__ = ["_num", "ack_reason", "gap_words", "hms", "region_words", "survey_summary"]


def _num(x: float | None, nd: int = 3) -> float | None:
    """A number as the page shows it: rounded to ``nd`` places, None when not finite."""
    if x is None:
        return None
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


def region_words(state: Any, r: Any) -> str:
    """A region of subgrids in metres: ``32 x 24 m at (24, 32) m``."""
    span = state.subgrid_metres(int(r.level))
    return (f"{r.w * span:g} x {r.h * span:g} m at ({r.x0 * span:g}, {r.y0 * span:g}) m")


def gap_words(empty: int, block_m: float, subgrid_cells: int, cells: int) -> str:
    """The gaps of a level in words: empty squares inside its extent, and the cells missing
    inside the subgrids held (between sonar swaths, beyond the beams: the map's stripes)."""
    parts = []
    if empty:
        parts.append(f"{empty} empty {block_m:g} m square{'s' if empty != 1 else ''}")
    inner = subgrid_cells - cells
    if inner > 0 and subgrid_cells:
        parts.append(f"{100.0 * inner / subgrid_cells:.0f} % of cells between swaths")
    return ", ".join(parts) or "none"


def _span(seconds: float) -> str:
    """A duration in words: "40 s", "9 min 40 s", "2 h 5 min"."""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min" + (f" {s % 60} s" if s % 60 else "")
    return f"{s // 3600} h" + (f" {s % 3600 // 60} min" if s % 3600 // 60 else "")


def _counted(base: str, count: int, n: int, span: float) -> str:
    """A log entry's text for ``n`` events of one kind over ``span`` seconds: ``{n}`` in
    ``base`` is the total ``count``; otherwise the number of times is added."""
    if "{n}" in base:
        text = base.replace("{n}", str(count))
        return text if n <= 1 else f"{text} in {_span(span)}"
    return base if n <= 1 else f"{base} ({n} times in {_span(span)})"


def hms(t: float | None) -> str:
    """``hh:mm:ss`` of the day (UTC) of an absolute time, as the page shows it."""
    if t is None or not math.isfinite(float(t)):
        return "-"
    s = math.floor(float(t)) % 86400
    return f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


def ack_reason(msg: m.Message, status: str, was_pending: bool = False) -> str:
    """What the vehicle's answer ``status`` (an :class:`~coex_core.messages.AckStatus` name)
    to ``msg`` means, in words. A ``CommandAck`` carries no reason: this is the cause the
    vehicle's code gives for that answer to that kind of command."""
    if status == "ACCEPTED":
        return ""
    if status == "UNAUTHENTICATED":
        return "not authenticated: the vehicle and topside command keys differ"
    if status == "PENDING":
        return "no image of that time yet: the request stands on the vehicle until one is taken"
    if isinstance(msg, m.QueueConfig):
        if status == "UNKNOWN_TARGET":
            return f"the vehicle has no stream {msg.stream}"
        return "the vehicle refused the setting (outside its limits)"
    if isinstance(msg, m.LinkControl | m.SpareConfig | m.ScheduleUpdate):
        link = msg.link
        if status == "UNKNOWN_TARGET":
            return f"the vehicle has no link {link}" if link is not None else \
                f"the vehicle has no stream {msg.stream if isinstance(msg, m.SpareConfig) else '?'}"
        if isinstance(msg, m.LinkControl):
            return "it would leave the vehicle without a transmitting link"
        if isinstance(msg, m.ScheduleUpdate):
            return ("its activation cycle had passed when it arrived, or no slot of the "
                    "vehicle fits a packet")
        return "the vehicle refused the share"
    if isinstance(msg, m.ImageByTimeRequest):
        if was_pending:
            return "no image of that time was taken before the request expired"
        d = {m.TimeDirection.BEFORE: "before", m.TimeDirection.AFTER: "after"}.get(
            msg.direction, "near")
        return f"the vehicle holds no image {d} that time"
    if isinstance(msg, m.ImageGoal):
        return f"the vehicle no longer holds image {msg.image_id}, or the goal is beyond it"
    if isinstance(msg, m.ImageRegionRequest):
        return (f"the vehicle no longer holds image {msg.image_id}, or it was coded without "
                "precincts (ask for more of the whole image), or the region is outside it")
    if isinstance(msg, m.TimeSeriesRequest):
        return f"the vehicle has no channel {msg.channel}, or the window is not valid"
    if status == "UNKNOWN_TARGET":
        return "the vehicle does not know what it names"
    return "refused by the vehicle"


_ROUTES: Routes | None = None


def _modality_of(msg: m.Message) -> str | None:
    """The installed modality whose receiver takes ``msg``: the core's routing table
    (:class:`coex_core.routing.Routes`, by wire type id, as a node routes) of the modalities in
    the registry, made once. A modality that cannot be loaded, or whose ids another one claimed
    first, is left out (a node would refuse it)."""
    global _ROUTES
    if _ROUTES is None:
        from coex import available, load_modality

        routes = Routes("messages")
        for info in available(check=False):
            if info.group != "coex.modalities":
                continue
            try:
                cls = load_modality(info.name)
                routes.claim(info.name, cls, declared_ids(cls, "messages"), info.name)
            except Exception:
                continue
        _ROUTES = routes
    owner = _ROUTES.owner(msg)
    return None if owner is None else str(owner)


def survey_summary(cmd: m.SurveyCommand) -> str:
    """A survey command in words (the commands list and the event log)."""
    def n(v: float | None) -> str:
        return "?" if v is None else f"{v:g}"

    kind = m.SurveyKind(cmd.kind)
    at = f"({cmd.x:.0f}, {cmd.y:.0f})"
    if kind == m.SurveyKind.GOTO:
        what = f"go to {at}"
    elif kind == m.SurveyKind.LINE:
        what = f"line from {at}, heading {n(cmd.heading)}°, {n(cmd.length)} m"
    elif kind == m.SurveyKind.LAWNMOWER:
        what = (f"lawnmower {n(cmd.length)} x {n(cmd.width)} m at {at}, heading {n(cmd.heading)}°, "
                f"rows {n(cmd.spacing)} m apart")
    else:
        what = f"{len(cmd.points) + 1} waypoints from {at}"
    if cmd.altitude is not None:
        what += f", altitude {n(cmd.altitude)} m"
    if cmd.depth is not None:
        what += f", depth {n(cmd.depth)} m"
    if cmd.speed is not None:
        what += f", {n(cmd.speed)} m/s"
    return f"survey {cmd.survey_id}: {what}" + (" (after the others)" if cmd.append else "")

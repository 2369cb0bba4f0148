"""Survey commands as paths, and the vehicle's checks on them. Sans-I/O, no clock.

:func:`plan_of` turns a :class:`~coex_core.messages.SurveyCommand` into a :class:`SurveyPlan`
(waypoints in local metres, with the altitude or depth and speed to fly them), and
:class:`Geofence` checks a plan against what the vehicle allows: a polygon (or a circle round the
origin) every waypoint and every leg must stay inside, a minimum altitude, a maximum depth, a
maximum speed and a maximum path length. A failed check names the rule, the waypoint and the
number (:class:`Refusal`), which the vehicle reports topside in a ``SurveyStatus``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from coex import ConfigError, SurveyPlan, SurveyReport, persistent
from coex.messages import (
    SURVEY_DETAIL_MAX,
    SurveyCommand,
    SurveyKind,
    SurveyReason,
)

__all__ = ["Geofence", "Refusal", "SurveyPlan", "SurveyReport", "cut_detail", "describe", "plan_of"]

#: most lawnmower rows a command may expand to (a 10 km wide box at 0.5 m is refused as INVALID)
MAX_ROWS = 200


@dataclass(frozen=True)
class Refusal(Exception):
    """A plan the vehicle will not fly: the reason, the first offending waypoint, a number."""

    reason: SurveyReason
    index: int | None = None
    value: float | None = None
    text: str = ""

    def __str__(self) -> str:
        return self.text or describe(self.reason, self.index, self.value)


def _unit(heading: float) -> tuple[float, float]:
    h = math.radians(heading)
    return math.sin(h), math.cos(h)  # east, north


def plan_of(cmd: SurveyCommand) -> SurveyPlan:
    """The path a command asks for. :class:`Refusal` (INVALID) when it cannot be flown as given."""
    x, y = float(cmd.x), float(cmd.y)
    kind = SurveyKind(cmd.kind)
    shape: dict[str, Any] = {}
    if kind == SurveyKind.GOTO:
        pts = [(x, y)]
    elif kind == SurveyKind.LINE:
        if not cmd.length or cmd.heading is None:
            raise Refusal(SurveyReason.INVALID, text="a line needs a heading and a length above 0")
        ex, ey = _unit(cmd.heading)
        pts = [(x, y), (x + cmd.length * ex, y + cmd.length * ey)]
        shape = dict(heading=cmd.heading, length=cmd.length)
    elif kind == SurveyKind.LAWNMOWER:
        if not (cmd.length and cmd.spacing) or cmd.width is None or cmd.heading is None:
            raise Refusal(SurveyReason.INVALID, text="a lawnmower needs a heading, a length and a "
                                                     "spacing above 0, and a width")
        rows = math.floor(cmd.width / cmd.spacing + 1e-9) + 1
        if rows > MAX_ROWS:
            raise Refusal(SurveyReason.INVALID, value=float(rows),
                          text=f"a lawnmower of {rows} rows (at most {MAX_ROWS})")
        ex, ey = _unit(cmd.heading)
        px, py = -ey, ex  # port (left of the heading)
        across = (rows - 1) * cmd.spacing
        pts = []
        for r in range(rows):
            off = across / 2 - r * cmd.spacing  # first row on the port side
            cx, cy = x + off * px, y + off * py
            a = (cx - cmd.length / 2 * ex, cy - cmd.length / 2 * ey)
            b = (cx + cmd.length / 2 * ex, cy + cmd.length / 2 * ey)
            pts += [a, b] if r % 2 == 0 else [b, a]
        shape = dict(heading=cmd.heading, length=cmd.length, width=cmd.width, spacing=cmd.spacing,
                     centre=(x, y))
    else:
        pts = [(x, y)] + [(float(p.x), float(p.y)) for p in cmd.points]
    if cmd.speed is not None and cmd.speed <= 0:
        raise Refusal(SurveyReason.INVALID, text="a speed of 0")
    return SurveyPlan(int(cmd.survey_id), kind, tuple((round(a, 2), round(b, 2)) for a, b in pts),
                      cmd.altitude, cmd.depth, cmd.speed, **shape)


@persistent("survey.Geofence")
@dataclass(frozen=True)
class Geofence:
    """What the vehicle allows. ``polygon``: vertices (metres east/north of the origin), every
    waypoint and leg must stay inside (None: no polygon); ``radius``: the same for a circle round
    the origin; ``min_altitude``: the lowest altitude a survey may ask for; ``max_depth``: the
    deepest; ``max_speed``; ``max_length``: the longest path (metres); ``require_height``: a
    survey must say its altitude or depth."""

    polygon: tuple[tuple[float, float], ...] | None = None
    radius: float | None = None
    min_altitude: float | None = None
    max_depth: float | None = None
    max_speed: float | None = None
    max_length: float | None = None
    require_height: bool = False
    extra: Mapping[str, Any] = field(default_factory=dict)

    KEYS = ("polygon", "radius", "min_altitude", "max_depth", "max_speed", "max_length", "require_height")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None, where: str = "geofence") -> Geofence:
        """From a configuration table; :class:`ConfigError` names the key at fault."""
        cfg = dict(cfg or {})
        unknown = sorted(set(cfg) - set(cls.KEYS))
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(cls.KEYS)})")
        poly = cfg.get("polygon")
        if poly is not None:
            try:
                poly = tuple((float(p[0]), float(p[1])) for p in poly)
                if any(len(p) != 2 for p in cfg["polygon"]):
                    raise ValueError
            except (TypeError, ValueError, IndexError):
                raise ConfigError(f"{where}.polygon: a list of [x, y] pairs (metres east, north of the "
                                  "origin)") from None
            if len(poly) < 3:
                raise ConfigError(f"{where}.polygon: at least 3 vertices, got {len(poly)}")
        nums: dict[str, float | None] = {}
        for k in ("radius", "min_altitude", "max_depth", "max_speed", "max_length"):
            v = cfg.get(k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)
                                  or not math.isfinite(v) or v < 0):
                raise ConfigError(f"{where}.{k}: a number >= 0, got {v!r}")
            nums[k] = None if v is None else float(v)
        req = cfg.get("require_height", False)
        if not isinstance(req, bool):
            raise ConfigError(f"{where}.require_height: true or false, got {req!r}")
        return cls(poly, require_height=req, **nums)  # type: ignore[arg-type]

    # ---------------------------------------------------------------------------- checks
    def check(self, plan: SurveyPlan) -> None:
        """Raise :class:`Refusal` for the first rule ``plan`` breaks."""
        if self.require_height and plan.altitude is None and plan.depth is None:
            raise Refusal(SurveyReason.INVALID, text="this vehicle needs an altitude or a depth")
        if self.min_altitude is not None and plan.altitude is not None and plan.altitude < self.min_altitude:
            raise Refusal(SurveyReason.ALTITUDE_LIMIT, value=self.min_altitude)
        if self.max_depth is not None and plan.depth is not None and plan.depth > self.max_depth:
            raise Refusal(SurveyReason.DEPTH_LIMIT, value=self.max_depth)
        if self.max_speed is not None and plan.speed is not None and plan.speed > self.max_speed:
            raise Refusal(SurveyReason.SPEED_LIMIT, value=self.max_speed)
        w = np.asarray(plan.waypoints, float).reshape(-1, 2)
        if self.radius is not None:
            r = np.hypot(w[:, 0], w[:, 1])
            bad = np.flatnonzero(r > self.radius)
            if bad.size:  # a circle is convex: the legs stay inside when the points do
                i = int(bad[0])
                raise Refusal(SurveyReason.OUTSIDE_GEOFENCE, i, round(float(r[i] - self.radius), 1))
        if self.polygon is not None:
            poly = np.asarray(self.polygon, float)
            inside = _inside(w, poly)
            if not inside.all():
                i = int(np.flatnonzero(~inside)[0])
                raise Refusal(SurveyReason.OUTSIDE_GEOFENCE, i,
                              round(float(_distance_to_edges(w[i], poly)), 1))
            leg = _first_crossing(w, poly)
            if leg is not None:  # both ends inside, the leg leaves (a concave fence)
                raise Refusal(SurveyReason.OUTSIDE_GEOFENCE, leg + 1, 0.0,
                              text=f"the leg to waypoint {leg + 1} leaves the geofence")
        if self.max_length is not None and plan.path_length > self.max_length:
            raise Refusal(SurveyReason.TOO_LONG, value=self.max_length)


def _inside(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule, vectorised over points and edges; points on an edge count as inside."""
    x, y = points[:, :1], points[:, 1:2]
    a, b = poly, np.roll(poly, -1, axis=0)
    ax, ay, bx, by = a[:, 0], a[:, 1], b[:, 0], b[:, 1]
    crosses = (ay > y) != (by > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = ax + (y - ay) * (bx - ax) / (by - ay)
    odd = (crosses & (x < xc)).sum(axis=1) % 2 == 1
    return odd | (_edge_distances(points, poly) < 1e-6)


def _edge_distances(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance of each point to the polygon's boundary (points x edges, vectorised)."""
    a, b = poly[None, :, :], np.roll(poly, -1, axis=0)[None, :, :]
    ab = b - a
    p = points[:, None, :]
    t = np.clip(((p - a) * ab).sum(2) / np.maximum((ab * ab).sum(2), 1e-12), 0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return np.hypot(d[..., 0], d[..., 1]).min(axis=1) if len(points) else np.zeros(0)


def _distance_to_edges(p: np.ndarray, poly: np.ndarray) -> float:
    return float(_edge_distances(np.asarray(p, float).reshape(1, 2), poly)[0])


def _first_crossing(w: np.ndarray, poly: np.ndarray) -> int | None:
    """The first leg (index of its start) that properly crosses an edge of the polygon."""
    if len(w) < 2:
        return None
    p, r = w[:-1, None, :], (w[1:] - w[:-1])[:, None, :]
    q, s = poly[None, :, :], (np.roll(poly, -1, axis=0) - poly)[None, :, :]

    def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    den = cross(r, s)
    qp = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross(qp, s) / den
        u = cross(qp, r) / den
    eps = 1e-9
    hit = (np.abs(den) > eps) & (t > eps) & (t < 1 - eps) & (u > eps) & (u < 1 - eps)
    legs = np.flatnonzero(hit.any(axis=1))
    return int(legs[0]) if legs.size else None


_REASONS = {
    SurveyReason.NONE: "",
    SurveyReason.OUTSIDE_GEOFENCE: "outside the geofence",
    SurveyReason.ALTITUDE_LIMIT: "below the vehicle's minimum altitude",
    SurveyReason.DEPTH_LIMIT: "deeper than the vehicle's maximum depth",
    SurveyReason.TOO_LONG: "longer than the vehicle's longest survey",
    SurveyReason.INVALID: "cannot be flown as given",
    SurveyReason.AUTONOMY_REFUSED: "the vehicle's autonomy refused it",
    SurveyReason.SUPERSEDED: "replaced by a newer survey",
    SurveyReason.NO_AUTONOMY: "the vehicle has no autonomy that takes surveys",
    SurveyReason.AUTONOMY_STOPPED: "the vehicle's autonomy stopped it",
    SurveyReason.SPEED_LIMIT: "faster than the vehicle's maximum speed",
    SurveyReason.AUTONOMY_NO_ANSWER: "no answer from the vehicle's autonomy",
    SurveyReason.MANUAL_OVERRIDE: "taken over on the vehicle (manual override)",
    SurveyReason.AUTONOMY_RESTARTED: "the vehicle's autonomy restarted and dropped it",
    SurveyReason.ALL_STOP: "the vehicle's autonomy stopped all motion",
    SurveyReason.AUTONOMY_SILENT: "autopilot silent",
}


def describe(reason: SurveyReason | int, index: int | None = None, value: float | None = None,
             detail: str | None = None) -> str:
    """A reason in words, as the console shows it: "waypoint 3 is 212.5 m outside the
    geofence", "below the vehicle's minimum altitude (3.0 m)", "the vehicle's autonomy refused
    it (code 15: MAV_MISSION_DENIED)", "no answer from the vehicle's autonomy (after 6 tries)"."""
    text = _describe(SurveyReason(reason), index, value)
    if detail:
        text += f": {detail}"
    return text


def _describe(reason: SurveyReason, index: int | None, value: float | None) -> str:
    if reason == SurveyReason.OUTSIDE_GEOFENCE:
        where = f"waypoint {index}" if index is not None else "a waypoint"
        if value:
            return f"{where} is {value:g} m outside the geofence"
        return f"{where} (or the leg to it) is outside the geofence"
    text = _REASONS.get(reason, reason.name.lower())
    if value is not None and reason in (SurveyReason.ALTITUDE_LIMIT, SurveyReason.DEPTH_LIMIT,
                                        SurveyReason.TOO_LONG):
        text += f" ({value:g} m)"
    elif value is not None and reason == SurveyReason.SPEED_LIMIT:
        text += f" ({value:g} m/s)"
    elif value is not None and reason in (SurveyReason.AUTONOMY_REFUSED, SurveyReason.AUTONOMY_STOPPED):
        text += f" (code {value:g})"
    elif value is not None and reason == SurveyReason.AUTONOMY_NO_ANSWER:
        text += f" (after {value:g} tries)"
    elif value is not None and reason == SurveyReason.AUTONOMY_SILENT:
        text += f" for {value:g} s"
    return text


def cut_detail(text: str | None) -> str | None:
    """``text`` as ``SurveyStatus.detail`` carries it: one line, at most SURVEY_DETAIL_MAX bytes of
    UTF-8 (cut at a character), None when empty."""
    if not text:
        return None
    line = " ".join(str(text).split())
    data = line.encode("utf-8")[:SURVEY_DETAIL_MAX]
    out = data.decode("utf-8", errors="ignore").rstrip()
    return out or None


def waypoints_array(plan: SurveyPlan) -> np.ndarray:
    return np.asarray(plan.waypoints, float).reshape(-1, 2)


def as_points(seq: Sequence[Sequence[float]]) -> tuple[tuple[float, float], ...]:
    return tuple((float(a), float(b)) for a, b in seq)

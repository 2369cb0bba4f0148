"""Operator actions as wire-format commands: :class:`ConsoleActions` (``POST /api/action`` runs
:meth:`ConsoleActions.dispatch`; docs/console.md has the table of actions, their arguments and
their refusals). Each action checks its input (:class:`~coex_core.errors.RequestRejected` with
the reason, nothing sent), builds :mod:`coex_core.messages` commands, records them in the
:class:`~.state.ConsoleState` and hands each one to ``send`` (the topside node's send path)."""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, cast

import numpy as np

from coex import CoexError, RequestRejected, to_stamp
from coex import messages as m
from coex_plugins.bathymetry import BathymetryReceiver
from coex_plugins.imagery import ImageryReceiver

from .state import ConsoleState
from .words import hms, survey_summary

__all__ = ["ACTIONS", "CallSink", "CommandSink", "ConsoleActions", "as_sink"]


class CommandSink(abc.ABC):
    """Where the console's commands go (the ``send`` of :class:`ConsoleActions` and
    :class:`~.hub.ConsoleHub`): ``sink(msg)`` sends or queues one command message.

    :class:`~.node.NodeCommands` is the one for a topside node. A plain callable given as
    ``send`` is wrapped in a :class:`CallSink`, which has the defaults below."""

    @abc.abstractmethod
    def __call__(self, msg: m.Message) -> m.Message | None:
        """Send (or queue) ``msg``; return the message actually sent when it differs (a
        schedule numbered by the node), else ``msg`` or None."""

    def next_command_id(self) -> int | None:
        """The command id of the next command the console builds, when the sink numbers
        commands (a node: one id space with its channel manager). Default: None, the console
        numbers its own (from ``first_command_id``, modulo 256)."""
        return None

    def flush(self) -> int:
        """Send what :meth:`__call__` queued; the thread driving the node calls it (through
        :meth:`ConsoleHub.pump <coex_apps.console.hub.ConsoleHub.pump>`) and it returns how many
        went. Default: nothing is queued, 0."""
        return 0


class CallSink(CommandSink):
    """A plain callable as a :class:`CommandSink` (``fn(msg)``; its answer is the message sent
    when it is one), with the defaults: the console numbers its commands, nothing is queued."""

    def __init__(self, fn: Callable[[m.Message], Any]) -> None:
        self.fn = fn

    def __call__(self, msg: m.Message) -> m.Message | None:
        out = self.fn(msg)
        return out if isinstance(out, m.Message) else None


def as_sink(send: CommandSink | Callable[[m.Message], Any]) -> CommandSink:
    """``send`` as a :class:`CommandSink` (a plain callable wrapped in a :class:`CallSink`)."""
    return send if isinstance(send, CommandSink) else CallSink(send)


class ConsoleActions:
    """Operator actions as wire-format commands.

    Each method builds :mod:`coex_core.messages` commands, records them in ``state`` (so the page
    shows what was requested) and hands each one to ``send``. Invalid input raises
    :class:`~coex_core.errors.RequestRejected` and sends nothing. ``clock`` gives ``now``
    (the runner's clock; the actions never read one themselves)."""

    def __init__(self, state: ConsoleState, send: CommandSink | Callable[[m.Message], Any],
                 clock: Callable[[], float], *, first_command_id: int = 0,
                 map_receiver: BathymetryReceiver | None = None) -> None:
        self.state = state
        #: A bathymetry receiver (``request_area``): when set, map regions are asked through it
        #: (it knows what topside holds, numbers the requests and retries them).
        self.map_receiver = map_receiver
        self.send = as_sink(send)
        self.clock = clock
        self._next_id = first_command_id % 256

    def _cid(self) -> int:
        given = self.send.next_command_id()
        if given is not None:
            return int(given) % 256
        cid = self._next_id
        self._next_id = (cid + 1) % 256
        return cid

    def _emit(self, msgs: Sequence[m.Message], summaries: Sequence[str]) -> list[m.Message]:
        now = self.clock()
        out: list[m.Message] = []
        for msg, text in zip(msgs, summaries):
            sent = self.send(msg)
            actual = sent if isinstance(sent, m.Message) else msg
            self.state.record_command(actual, now, text)
            out.append(actual)
        return out

    # -------------------------------------------------------------------------- map
    def request_region(self, level: int, x_min: float, y_min: float, x_max: float,
                       y_max: float, *, fill_gaps: bool = False) -> list[Any]:
        """Request the map at ``level`` over the rectangle ``[x_min, x_max] x [y_min, y_max]``
        (metres) through the node's bathymetry receiver (:attr:`map_receiver`), which cuts it
        into requests listing what topside holds (or, with ``fill_gaps``, a bitmap of it), so
        the vehicle sends only what is newer or missing, numbers them and retries them until
        the vehicle has nothing newer. Returns the receiver's regions."""
        level = int(level)
        if not 0 <= level <= 15:
            raise RequestRejected(f"level {level} outside 0..15")
        vals = [float(v) for v in (x_min, y_min, x_max, y_max)]
        if not all(math.isfinite(v) for v in vals):
            raise RequestRejected("region corners must be finite numbers")
        x_min, x_max = sorted(vals[0::2])
        y_min, y_max = sorted(vals[1::2])
        rx = self.map_receiver
        if rx is None:
            raise RequestRejected("map requests need a topside node with a bathymetry receiver")
        # the receiver checks the level, the size and the wire's index range
        regions = list(rx.request_area(level, x_min, y_min, x_max, y_max, fill_gaps=bool(fill_gaps)))
        self.state.record_regions(regions, self.clock(), f"map level {level}"
                                  + (" (gaps)" if fill_gaps else ""))
        return regions

    # ---------------------------------------------------------------------- surveys
    def survey(self, kind: str, x: float | None = None, y: float | None = None, *, heading: float | None = None,
               length: float | None = None, width: float | None = None,
               spacing: float | None = None, altitude: float | None = None,
               depth: float | None = None, speed: float | None = None, append: bool = False,
               points: Sequence[Sequence[float]] = ()) -> m.SurveyCommand:
        """Ask the vehicle to survey (``kind`` ``goto``, ``line``, ``lawnmower`` or
        ``waypoints``; ``x``, ``y`` metres east/north of the origin; a lawnmower is centred on
        them with its rows along ``heading``; waypoints fly ``x``, ``y`` then ``points``, or
        with no ``x``, ``y`` all of ``points``) through the node's survey receiver, which sends the
        ``SurveyCommand``, re-sends it until answered and follows the survey's state. Returns
        the command (sent at the node's next poll)."""
        rx = self.state.survey_receiver
        if rx is None or self.state.own_receivers:
            raise RequestRejected("survey requests need a topside node with the survey receiver "
                                  "(coex topside runs it unless --modalities leaves out survey)")
        nums: dict[str, float | None] = {}
        given: tuple[tuple[str, Any], ...] = (  # numbers, or what the page sent for them
            ("x", x), ("y", y), ("heading", heading), ("length", length), ("width", width),
            ("spacing", spacing), ("altitude", altitude), ("depth", depth), ("speed", speed))
        for name, v in given:
            if v is None or v == "":
                nums[name] = None
                continue
            f = float(v)
            if not math.isfinite(f):
                raise RequestRejected(f"survey {name} must be a finite number, not {v!r}")
            nums[name] = f
        if nums["altitude"] is not None and nums["depth"] is not None:
            raise RequestRejected("give an altitude or a depth, not both")
        if isinstance(points, str | bytes) or not isinstance(points, Sequence):
            raise RequestRejected("survey points are a list of [x, y] pairs (metres)")
        try:
            pts = [(float(p[0]), float(p[1])) for p in points or ()]
        except (TypeError, ValueError, IndexError, KeyError):
            raise RequestRejected("survey points are [x, y] pairs (metres)") from None
        if not all(math.isfinite(a) and math.isfinite(b) for a, b in pts):
            raise RequestRejected("survey points must be finite numbers")
        if nums["x"] is None and nums["y"] is None and pts and str(kind).lower() == "waypoints":
            (nums["x"], nums["y"]), pts = pts[0], pts[1:]  # the waypoint form: every point in points
        if nums["x"] is None or nums["y"] is None:
            raise RequestRejected("a survey needs x and y (metres east and north of the origin; for "
                                  "waypoints, or the first of at least one [x, y] in points)")
        now = self.clock()
        nav = self.state.navigation
        if nav is not None and nav.apply:
            # drawn on the corrected map: sent in the vehicle's own frame (issue 56), each point
            # moved by the correction topside estimates now
            vid = self.state.vehicle_id
            nums["x"], nums["y"] = nav.to_vehicle(vid, nums["x"], nums["y"], now)
            pts = [nav.to_vehicle(vid, a, b, now) for a, b in pts]
        # the receiver checks the kind, the fields the kind needs and their wire ranges
        cmd: m.SurveyCommand = rx.request(str(kind), nums["x"], nums["y"], now, heading=nums["heading"],
                         length=nums["length"], width=nums["width"], spacing=nums["spacing"],
                         altitude=nums["altitude"], depth=nums["depth"], speed=nums["speed"],
                         append=bool(append), points=pts)
        self.state.record_command(cmd, now, survey_summary(cmd))
        self.state.refresh_surveys()
        return cmd

    # ----------------------------------------------------------------------- images
    def set_image_goal(self, image_id: int, kind: str, value: int = 0) -> m.ImageGoal:
        """Transfer an image up to a goal: ``skip``, ``fraction`` (value in %), ``layer``, ``full``."""
        try:
            gk = m.GoalKind[str(kind).upper()]
        except KeyError:
            raise RequestRejected(f"unknown goal kind {kind!r}") from None
        value = int(value)
        if gk == m.GoalKind.FRACTION and not 1 <= value <= 100:
            raise RequestRejected("a fraction goal is 1..100 (%)")
        if gk == m.GoalKind.LAYER and not 0 <= value <= 255:
            raise RequestRejected("a layer goal is 0..255")
        if gk in (m.GoalKind.SKIP, m.GoalKind.FULL):
            value = 0
        msg = m.ImageGoal(self._cid(), int(image_id), gk, value)
        text = f"image {image_id} goal {gk.name.lower()}" + (f" {value}" if value else "")
        self._emit([msg], [text])
        return msg

    def image_by_time(self, t: float, direction: str = "nearest") -> m.ImageByTimeRequest:
        """Ask for the image nearest time ``t`` (absolute seconds), or the one before/after it."""
        try:
            d = {"nearest": m.TimeDirection.NEAREST, "previous": m.TimeDirection.BEFORE,
                 "before": m.TimeDirection.BEFORE, "next": m.TimeDirection.AFTER,
                 "after": m.TimeDirection.AFTER}[str(direction).lower()]
        except KeyError:
            raise RequestRejected(f"unknown direction {direction!r}") from None
        if not math.isfinite(float(t)):
            raise RequestRejected("time must be finite")
        msg = m.ImageByTimeRequest(self._cid(), to_stamp(float(t)), d)
        what = {m.TimeDirection.BEFORE: "previous image before",
                m.TimeDirection.AFTER: "next image after"}.get(d, "image nearest")
        self._emit([msg], [f"{what} {hms(float(t))}"])
        return msg

    def image_region(self, image_id: int, x0: float, y0: float, x1: float, y1: float,
                     kind: str = "quality", value: float = 30) -> m.ImageRegionRequest:
        """Bring the rectangle ``[x0, x1) x [y0, y1)`` (pixels of the image as announced) of an
        image to a goal: ``quality`` (``value`` in dB PSNR inside the region, 10..60; 0.1 dB on
        the wire), ``layer`` (quality layers, 1..the image's) or ``bytes`` (a budget of body
        bytes, 1..65535). The vehicle sends the packets of the JPEG 2000 precincts covering it.
        Through the node's imagery receiver when the console has one (it retries the request
        and lists the region with the layers complete inside it), else as a command."""
        iid = int(image_id)
        img = self.state.images.get(iid)
        info = img.decoded_meta if img is not None else {}
        w, h = info.get("width"), info.get("height")
        if img is None or not w or not h:
            raise RequestRejected(f"image {iid} is not announced yet: its size is unknown")
        from coex_plugins.imagery.goals import region_fields

        try:
            (bx0, by0, bx1, by1), goal, code = region_fields(
                (x0, y0, x1, y1), kind, value, int(w), int(h), int(info.get("layers") or 255),
                1 if info.get("precincts") is None else int(info["precincts"]))  # unknown: let the vehicle say
        except CoexError as exc:
            raise RequestRejected(f"image {iid}: {exc}") from None
        v = float(value)
        words = {m.RegionGoal.QUALITY: f"to {v:g} dB", m.RegionGoal.BYTES: f"within {code} bytes",
                 m.RegionGoal.LAYER: f"to {code} layer{'s' if code != 1 else ''}"}[goal]
        text = f"image {iid} region {bx0}..{bx1} x {by0}..{by1} {words}"
        rx = None if self.state.own_receivers else self.state.receivers.get("imagery")
        if isinstance(rx, ImageryReceiver) and iid in rx.images:
            # the node's receiver numbers it, retries it until answered and follows it
            now = self.clock()
            try:
                msg = rx.request_region(iid, (bx0, by0, bx1, by1), goal.name.lower(),
                                        v if goal == m.RegionGoal.QUALITY else code, now=now)
            except CoexError as exc:
                raise RequestRejected(str(exc)) from None
            self.state.record_command(msg, now, text)
            return cast(m.ImageRegionRequest, msg)
        msg = m.ImageRegionRequest(self._cid(), iid, bx0, by0, bx1, by1, goal, code)
        self._emit([msg], [text])
        return msg

    # ------------------------------------------------------------------ time series
    def refine_series(self, channel: int, start: float, end: float,
                      max_error: float | None = None) -> m.TimeSeriesRequest:
        """Refine a channel over ``[start, end]`` (absolute seconds) down to ``max_error``
        (default: a quarter of the worst bound held in the window)."""
        start, end = sorted((float(start), float(end)))
        if not (math.isfinite(start) and math.isfinite(end)):
            raise RequestRejected("window must be finite")
        s = self.state.series.get(int(channel))
        if s is None:
            raise RequestRejected(f"unknown channel {channel}")
        if max_error is None:
            t, b = s.get("times"), s.get("bounds")
            if t is None or b is None:
                raise RequestRejected("no data in that window to refine; give max_error")
            sel = (t >= start) & (t <= end) & np.isfinite(b)
            if not sel.any():
                raise RequestRejected("no data in that window to refine; give max_error")
            max_error = float(b[sel].max()) / 4
            if s.get("resolution"):
                max_error = max(max_error, float(s["resolution"]) / 2)
        if not (math.isfinite(max_error) and max_error > 0):
            raise RequestRejected("max_error must be positive")
        msg = m.TimeSeriesRequest(self._cid(), int(channel), to_stamp(start), to_stamp(end),
                                  float(np.float32(max_error)))
        name = s.get("name", f"channel {channel}")
        self._emit([msg], [f"refine {name} {hms(start)} to {hms(end)} to ±{max_error:.3g}"])
        return msg

    # ------------------------------------------------------------------------ queues
    def queue_config(self, stream: int, *, flush: bool = False, enabled: bool | None = None,
                     priority: int | None = None, ttl: int | None = None,
                     max_depth: int | None = None,
                     newest_first: bool | None = None) -> m.QueueConfig:
        """Change one stream's settings (``None`` leaves a setting unchanged) or flush it."""
        stream = int(stream)
        if not 0 <= stream <= 31:
            raise RequestRejected(f"stream {stream} outside 0..31")
        if priority is not None and not 0 <= int(priority) <= 127:
            raise RequestRejected("priority is 0..127")
        if ttl is not None and not 0 <= int(ttl) <= 16383:
            raise RequestRejected("ttl is 0..16383 s")
        if max_depth is not None and not 0 <= int(max_depth) <= 1023:
            raise RequestRejected("max_depth is 0..1023")
        msg = m.QueueConfig(self._cid(), stream, bool(flush), enabled,
                            None if priority is None else int(priority),
                            None if ttl is None else int(ttl),
                            None if max_depth is None else int(max_depth), newest_first)
        parts = [f"stream {stream}:"]
        if flush:
            parts.append("flush")
        if enabled is not None:
            parts.append("enable" if enabled else "disable")
        if priority is not None:
            parts.append(f"priority {priority}")
        for k, v in (("ttl", ttl), ("max depth", max_depth), ("newest first", newest_first)):
            if v is not None:
                parts.append(f"{k} {v}")
        self._emit([msg], [" ".join(parts)])
        return msg

    # -------------------------------------------------------------------------- link
    def link_control(self, link: int, enabled: bool, mute: bool = False) -> m.LinkControl:
        """Enable or disable one modem link (or mute it)."""
        link = int(link)
        if not 0 <= link <= 7:
            raise RequestRejected(f"link {link} outside 0..7")
        msg = m.LinkControl(self._cid(), link, bool(enabled), bool(mute))
        self._emit([msg], [f"link {link} {'enable' if enabled else 'disable'}"
                           + (" mute" if mute else "")])
        return msg

    def spare_config(self, percent: int, link: int | None = None,
                     stream: int | None = None) -> m.SpareConfig:
        """Cap spare traffic (re-sends, refinements, redundant copies) at ``percent`` of each
        packet, 0 = off: on ``link``, on every link (both None), or for ``stream``'s spare work.
        Acoustic transmissions cost the vehicle energy: this is the operator's lever."""
        pct = int(percent)
        if not 0 <= pct <= 100:
            raise RequestRejected("spare share is 0..100 %")
        if link is not None and stream is not None:
            raise RequestRejected("set a spare share per link or per stream, not both")
        if link is not None and not 0 <= int(link) <= 7:
            raise RequestRejected(f"link {link} outside 0..7")
        if stream is not None and not 0 <= int(stream) <= 31:
            raise RequestRejected(f"stream {stream} outside 0..31")
        msg = m.SpareConfig(self._cid(), None if link is None else int(link),
                            None if stream is None else int(stream), pct)
        target = (f"stream {stream}" if stream is not None else
                  f"link {link}" if link is not None else "every link")
        self._emit([msg], [f"spare traffic on {target}: {'off' if pct == 0 else f'at most {pct} % of each packet'}"])
        return msg

    def propose_schedule(self, link: int, slots: Sequence[Mapping[str, Any]],
                         activate_cycle: int | None = None,
                         version: int | None = None) -> m.ScheduleUpdate:
        """Propose a new TDMA schedule for ``link``: ``slots`` of ``owner``, ``duration``,
        ``guard``, ``min_priority``; active from ``activate_cycle`` (default: two cycles after
        the current one) with ``version`` (default: the running one plus 1, mod 16)."""
        link = int(link)
        if not 0 <= link <= 7:
            raise RequestRejected(f"link {link} outside 0..7")
        if not 1 <= len(slots) <= 32:
            raise RequestRejected("a schedule has 1..32 slots")
        out = []
        for s in slots:
            try:
                owner, dur = int(s["owner"]), float(s["duration"])
                guard, minp = float(s.get("guard", 0.0)), int(s.get("min_priority", 0))
            except (KeyError, TypeError, ValueError) as exc:
                raise RequestRejected(f"bad slot {s!r}: {exc}") from None
            if not (0 <= owner <= 15 and 0.1 <= dur <= 600 and 0 <= guard <= 25.5
                    and guard < dur and 0 <= minp <= 127):
                raise RequestRejected(f"slot {s!r} out of range")
            out.append(m.Slot(owner, round(dur, 1), round(guard, 1), minp))
        cur = self.state.schedules.get(link)
        now = self.clock()
        if version is None:
            version = ((cur["active_version"] if cur else 0) + 1) % 16
        if activate_cycle is None:
            if cur and cur["cycle"] > 0:
                activate_cycle = (cur["first_cycle"]
                                  + int((now - cur["epoch"]) // cur["cycle"]) + 2)
            else:
                activate_cycle = 0
        msg = m.ScheduleUpdate(self._cid(), link, int(version) % 16, int(activate_cycle) % 65536,
                               tuple(out))
        self._emit([msg], [f"schedule v{msg.version} for link {link} "
                           f"({len(out)} slots, cycle {msg.activate_cycle})"])
        return msg

    # ------------------------------------------------------------------- dispatcher
    def dispatch(self, action: str, args: Mapping[str, Any], operator: str = "") -> list[m.Message]:
        """Run an action named by the page (``request_region``, ``set_image_goal``,
        ``image_by_time``, ``image_region``, ``refine_series``, ``queue_config``, ``link_control``,
        ``spare_config``, ``propose_schedule``, ``survey``) with keyword ``args``; returns the
        messages sent."""
        fn = getattr(self, action) if action in ACTIONS else None
        if fn is None:
            raise RequestRejected(f"unknown action {action!r} (one of {', '.join(sorted(ACTIONS))})")
        _check_arguments(action, fn, args)
        self.state.actor = str(operator)  # recorded with every command this action sends
        try:
            result = fn(**dict(args))  # type: ignore[operator]
        except TypeError as exc:  # a value of the wrong kind (a list for a number ...)
            raise RequestRejected(f"bad value for {action}: {exc}") from None
        except (ValueError, OverflowError) as exc:
            raise RequestRejected(f"bad value for {action}: {exc}") from None
        finally:
            self.state.actor = ""
        return list(result) if isinstance(result, list) else [result]


#: the actions of ``POST /api/action`` (:meth:`ConsoleActions.dispatch`; docs/console.md)
ACTIONS = ("request_region", "survey", "set_image_goal", "image_by_time", "image_region", "refine_series",
           "queue_config", "link_control", "spare_config", "propose_schedule")


def _check_arguments(action: str, fn: Callable[..., Any], args: Mapping[str, Any]) -> None:
    """:class:`RequestRejected` naming an argument ``fn`` does not take or one it needs."""
    import inspect

    params = inspect.signature(fn).parameters
    takes = ", ".join(params)
    for name in args:
        if name not in params:
            raise RequestRejected(f"{action} has no argument {name!r} (it takes {takes})")
    missing = [n for n, p in params.items() if p.default is inspect.Parameter.empty and n not in args]
    if missing:
        raise RequestRejected(f"{action} needs {', '.join(missing)} (it takes {takes})")

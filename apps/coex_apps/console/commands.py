"""The console's commands: what the operator (or the node) sent and what became of it.

A part of :class:`~coex_apps.console.state.ConsoleState` (its API is the state's). Each
command's state is the core tracker's (:mod:`coex_core.tracker`: one table of states and
transitions); the list the page shows is a view of it: ``status`` is the vehicle's answer
(``accepted``, ``rejected``, ``unknown_target``, ``unauthenticated``, ``pending``) or the
tracker's state (``sent``, ``queued``, ``no answer``, ``aborted``).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from typing import Any, cast

from coex import messages as m
from coex import unwrap
from coex.tracker import TRANSITIONS, Event, State, Tracked, answer_event
from coex_plugins.survey import SurveyProduct

from .images import ImagesView
from .mapview import MapView
from .model import OPEN_COMMAND_STATES
from .records import _Command, _RoiRequest
from .surveys import SurveysView
from .words import _num, ack_reason, hms, region_words

__all__ = ["OPEN_COMMAND_STATES", "CommandsView"]

class CommandsView(MapView, SurveysView, ImagesView):
    """The commands part of :class:`~coex_apps.console.state.ConsoleState`: a map, surveys and
    images view too, since the list shows what became of a map region, a survey and an image."""

    def record_command(self, msg: m.Message, now: float, summary: str = "") -> None:
        """Remember a command the operator sent (shown as pending until answered)."""
        self._advance(now)
        cid = msg.request_id if isinstance(msg, m.MapRoiRequest) else m.command_id(msg)
        if cid is None:
            return
        kind = type(msg).__name__
        key = self._new_command_key()
        self.commands[key] = _Command(int(cid), kind, summary or kind, now, msg, by=self.actor)
        self.command_order.append(key)
        self._prune_commands()
        if isinstance(msg, m.ImageGoal):
            self._image(msg.image_id).goal = (msg.kind.name, msg.value)
            self._touch("images")
        elif isinstance(msg, m.ImageRegionRequest):
            self._touch("images")
        elif isinstance(msg, m.ImageByTimeRequest):
            self.image_queries.append({"command_id": msg.command_id, "stamp": msg.stamp,
                                       "direction": msg.direction.name, "sent": _num(now, 1)})
            self._touch("images")
        elif isinstance(msg, m.TimeSeriesRequest):
            self.series_requests.append({"command_id": msg.command_id, "channel": msg.channel,
                                         "start": unwrap(msg.start, now),
                                         "end": unwrap(msg.end, now),
                                         "max_error": msg.max_error, "sent": _num(now, 1)})
            self._touch("series")
        elif isinstance(msg, m.ScheduleUpdate):
            sch = self.schedules.get(msg.link)
            if sch is not None:
                sch["proposed"] = {"version": msg.version, "activate_cycle": msg.activate_cycle,
                                   "command_id": msg.command_id, "status": "sent",
                                   "slots": [{"owner": s.owner, "duration": s.duration,
                                              "guard": s.guard, "min_priority": s.min_priority}
                                             for s in msg.slots]}
                self._touch("link")
        self._touch("commands")
        self._log(now, f"{self.actor + ' ' if self.actor else ''}sent {summary or kind}")

    def _new_command_key(self) -> int:
        """A key no other command of this console has (command ids wrap at 256 and are reused:
        a command is never looked up by its id alone)."""
        return max(self.commands, default=0) + 1

    def _prune_commands(self) -> None:
        """Forget commands that fell out of the list (``command_order`` keeps the newest 64)."""
        keep = set(self.command_order)
        for key in [k for k in self.commands if k not in keep]:
            del self.commands[key]

    def _find_command(self, command_id: int, message: m.Message | None = None) -> int | None:
        """The key of the newest command with ``command_id`` (and, when given, that message)."""
        for key in reversed(self.command_order):
            c = self.commands.get(key)
            if c is None or c.roi_key is not None or c.command_id != command_id:
                continue
            if message is None or c.message == message:
                return key
        return None

    def replace_command(self, built: m.Message, sent: m.Message, now: float) -> None:
        """The node sent ``sent`` for the command recorded as ``built`` (another command id)."""
        built_id = m.command_id(built)
        key = self._find_command(-1 if built_id is None else built_id, built)
        if key is None:
            return
        old = self.commands[key]
        old.message, old.command_id = sent, m.command_id(sent) or 0
        if isinstance(sent, m.ScheduleUpdate):
            sch = self.schedules.get(sent.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["command_id"] = sent.command_id
                sch["proposed"]["activate_cycle"] = sent.activate_cycle
        self._touch("commands", "link")

    def record_regions(self, regions: Sequence[Any], now: float, summary: str) -> None:
        """Remember map regions a bathymetry receiver will request (and retry) for us."""
        self._advance(now)
        for r in regions:
            if id(r) in self._region_ids:
                continue
            self._region_ids.add(id(r))
            self._region_count += 1
            key = -self._region_count
            self.roi[key] = _RoiRequest(r.level, r.x0, r.y0, r.w, r.h, now, r)
            text = f"{summary}: {region_words(self, r)}"
            ckey = self._new_command_key()
            self.commands[ckey] = _Command(-1, "MapRoiRequest", text, now,
                                           m.MapRoiRequest(0, r.level, r.x0, r.y0, r.w, r.h,
                                                           True, (), 0),
                                           track=Tracked(None), roi_key=key, by=self.actor)
            self.command_order.append(ckey)
            self._prune_commands()
            self._log(now, f"{self.actor + ' ' if self.actor else ''}requested {text}")
        self._touch("map", "commands")

    def _command_result(self, command_id: int, status: Any, now: float,
                        command: m.Message | None = None) -> None:
        """The vehicle's answer to a command. The node gives the command it answers the first
        time (``command``); a repeated answer (the vehicle answers every re-send) comes without
        it and changes nothing, nor does an answer to a command already answered: ids wrap at
        256, so an old answer must never land on a newer command that reuses the id."""
        name = status.name if isinstance(status, enum.Enum) else str(status)
        new = name.lower()
        key = self._find_command(command_id, command)
        if key is None and command is None:
            last = self._foreign_acks.get(command_id)
            if last is None or last[0] != name or now - last[1] > 600:
                self._log(now, f"vehicle answered command {command_id}: {new} "
                               "(not sent from this console)")
            self._foreign_acks[command_id] = (name, now)
            return
        if key is None:
            # a command the topside node sent for someone else (a script, a receiver)
            key = self._new_command_key()
            self.commands[key] = _Command(command_id, type(command).__name__,
                                          f"{type(command).__name__} (by the node)", now,
                                          cast(m.Message, command))
            self.command_order.append(key)
            self._prune_commands()
        cmd = self.commands[key]
        event = answer_event(name)
        if TRANSITIONS[cmd.track.state].get(event) in (None, cmd.track.state):
            # the same answer again (a re-send answered), or an answer to a command already
            # answered for good (a late or repeated one): nothing new
            return
        was_pending = cmd.track.state is State.PENDING
        cmd.track.apply(event, now, answer=name)
        cmd.reason = ack_reason(cmd.message, name, was_pending)
        if isinstance(cmd.message, m.ScheduleUpdate):
            sch = self.schedules.get(cmd.message.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["status"] = new
            self._touch("link")
        if isinstance(cmd.message, m.ImageByTimeRequest | m.ImageGoal | m.ImageRegionRequest):
            self._touch("images")
        self._touch("commands")
        if isinstance(cmd.message, m.SurveyCommand):
            return  # the survey receiver's product says it, with the reason (_survey_product)
        self._log(now, f"{cmd.summary}: {new}" + (f" ({cmd.reason})" if cmd.reason else ""),
                  "info" if name in ("ACCEPTED", "PENDING") else "warn")

    def _command_unanswered(self, command_id: int, now: float, command: m.Message | None = None) -> None:
        """The node's word that a command went unanswered for its answer time: "no answer" (an
        answer that comes after all still lands: :func:`_command_result`)."""
        key = self._find_command(command_id, command)
        if key is None:
            return
        cmd = self.commands[key]
        if cmd.track.apply(Event.GIVE_UP, now) is None:
            return
        self._touch("commands")
        if isinstance(cmd.message, m.ScheduleUpdate):
            sch = self.schedules.get(cmd.message.link)
            if sch is not None and sch.get("proposed"):
                sch["proposed"]["status"] = State.NO_ANSWER.value
            self._touch("link")
        self._log(now, f"{cmd.summary}: no answer from the vehicle yet (sent {now - (cmd.track.sent_at or now):.0f} s "
                       "ago; the link keeps sending it, and a late answer still counts)", "warn")

    def _on_command_ack(self, a: m.CommandAck, now: float) -> None:
        self._command_result(a.command_id, a.status, now)

    def _snap_commands(self) -> list[dict[str, Any]]:
        out = []
        surveys: dict[int, SurveyProduct] | None = None
        for key in reversed(self.command_order):
            c = self.commands[key]
            status, reason = c.status, c.reason
            if c.roi_key is not None and c.roi_key in self.roi:
                roi = self._snap_roi(self.roi[c.roi_key])
                status, reason = roi["state"], roi["text"]
            elif isinstance(c.message, m.SurveyCommand):  # the survey's own state
                if surveys is None:
                    surveys = self._survey_metas()
                survey = surveys.get(int(c.message.survey_id))
                if survey is not None:
                    status = str(survey.state or status)
                    if status in ("rejected", "aborted", "given up") and survey.text:
                        reason = str(survey.text)
            answer, img = "", None
            if isinstance(c.message, m.ImageByTimeRequest) and status == "accepted":
                img = self.by_time_answer(c.message, c.sent)
                answer = (f"answered by image #{img.image_id} taken {hms(img.t)}"
                          if img is not None else "answered: the image is on its way")
            out.append({"command_id": c.command_id, "kind": c.kind, "summary": c.summary,
                        "answer": answer, "image_id": None if img is None else img.image_id,
                        "sent": _num(c.sent, 1), "status": status,
                        "answered": _num(c.answered, 1), "by": c.by,
                        "reason": reason})
        return out

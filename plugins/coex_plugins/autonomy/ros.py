"""The ``ros`` autonomy output: each accepted survey is published on ROS 1 for the vehicle's own
planner, whose answers on a progress topic become survey reports.

What it publishes (both latched: a planner that starts later still gets the newest survey):

* ``path_topic`` (``/coex/survey/path``): a ``nav_msgs/Path`` in ``frame`` (``coex_local``: x
  east, y north of ``node.origin``, z up, metres), one ``PoseStamped`` per waypoint in order. A
  pose's z is ``-depth`` when the survey gives a depth, else 0; its orientation faces the next
  leg; its stamp is when it is reached at the survey's speed from the path's stamp (all the
  path's stamp without a speed).
* ``plan_topic`` (``/coex/survey/plan``, ``""`` for none): a ``std_msgs/String`` holding JSON,
  published just before the path: ``survey_id``, ``kind`` (goto, line, lawnmower, waypoints),
  ``waypoints`` (their count), ``altitude`` and ``depth`` (metres, null = keep the present one),
  ``speed`` (m/s, null = the vehicle's own), ``frame`` and ``stamp`` (the path's, seconds).

What it reads: ``progress_topic`` (``/coex/survey/progress``), a ``std_msgs/String`` per answer,
``[SURVEY_ID] WORD [MORE]`` (case ignored; without the id, the newest survey):

* ``started K`` (or ``started``: K = 0) -> STARTED, heading for waypoint K (0-based);
* ``completed`` -> COMPLETED;
* ``refused WHY`` (or ``rejected WHY``) -> REJECTED, AUTONOMY_REFUSED, detail WHY;
* ``aborted WHY`` -> ABORTED, AUTONOMY_STOPPED, detail WHY; ``aborted manual WHY`` ->
  MANUAL_OVERRIDE, ``aborted all_stop WHY`` -> ALL_STOP, ``aborted restarted WHY`` ->
  AUTONOMY_RESTARTED.

An answer about a survey this output handed over earlier, or about the survey after it ended, is
reported as it is (the daemon's survey lifecycle records it as a late answer and, for a
``started``, takes the survey back again); an answer naming a survey it never handed over, a
repeated ``started K`` and anything else are logged (once) and dropped. No answer within
``answer_timeout`` seconds of the submit -> REJECTED, AUTONOMY_NO_ANSWER (``detail``: the
seconds waited, and whether a planner was subscribed to the path at all). Reports are stamped
with the daemon's ``now``.

**The ended form.** When a survey ends (:meth:`RosAutonomy.end`) and it is the one latched, both
topics are replaced, still latched: ``path_topic`` by an empty ``nav_msgs/Path`` (no poses; a
planner flies nothing, and stops flying what it flies) and ``plan_topic`` by ``{"survey_id": 7,
"ended": true, "waypoints": 0, ...}``. A planner that starts or respawns later gets that, never
the ended survey.

**Liveness** (:meth:`RosAutonomy.heard`): the planner is alive while its publisher of the
progress topic is connected to CoEx (ROS 1 connections are peer to peer: a roscore restart does
not break them; a planner that dies closes it) or it answers; the daemon aborts a survey it
flies when neither holds for ``silence`` seconds.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from collections import deque
from collections.abc import Mapping
from typing import Any

from coex import Autonomy
from coex.messages import SurveyKind, SurveyReason, SurveyState
from coex.options import number

from ..options import LogOnce, Problems
from ..survey.plan import SurveyReport

__all__ = ["RosAutonomy", "ended_json", "parse_progress", "plan_json"]

log = logging.getLogger(__name__)

#: the word after ``aborted`` -> the reason it reports
ABORT_WORDS = {"manual": SurveyReason.MANUAL_OVERRIDE, "all_stop": SurveyReason.ALL_STOP,
               "restarted": SurveyReason.AUTONOMY_RESTARTED}


def parse_progress(text: str) -> tuple[int | None, SurveyState, SurveyReason, int | None, str | None]:
    """``(survey_id or None, state, reason, index, detail)`` of a progress answer (module
    docstring); ValueError when it is not one."""
    words = str(text).strip().split(None, 1)
    sid: int | None = None
    if words and words[0].isdigit():
        sid = int(words[0])
        words = words[1].split(None, 1) if len(words) > 1 else []
    if not words:
        raise ValueError(f"no state in {text!r}")
    word, rest = words[0].lower(), (words[1].strip() if len(words) > 1 else "")
    if word == "started":
        head = rest.split(None, 1)
        if head and not head[0].isdigit():
            raise ValueError(f"'started' takes a waypoint index, not {head[0]!r}")
        return sid, SurveyState.STARTED, SurveyReason.NONE, int(head[0]) if head else 0, None
    if word == "completed":
        return sid, SurveyState.COMPLETED, SurveyReason.NONE, None, None
    if word in ("refused", "rejected"):
        return sid, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, None, rest or None
    if word == "aborted":
        head = rest.split(None, 1)
        reason = ABORT_WORDS.get(head[0].lower()) if head else None
        if reason is not None:
            return sid, SurveyState.ABORTED, reason, None, (head[1].strip() if len(head) > 1 else None)
        return sid, SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED, None, rest or None
    raise ValueError(f"unknown state {words[0]!r} (started K, completed, refused WHY, aborted WHY)")


def plan_json(plan: Any, stamp: float, frame: str) -> str:
    """The JSON of ``plan_topic`` (module docstring)."""
    return json.dumps({
        "survey_id": int(plan.survey_id), "kind": SurveyKind(plan.kind).name.lower(),
        "waypoints": len(plan.waypoints), "altitude": plan.altitude, "depth": plan.depth,
        "speed": plan.speed, "frame": frame, "stamp": round(float(stamp), 6), "ended": False,
    })


def ended_json(survey_id: int, stamp: float, frame: str) -> str:
    """The JSON of ``plan_topic`` once survey ``survey_id`` ended (its ended form)."""
    return json.dumps({
        "survey_id": int(survey_id), "kind": None, "waypoints": 0, "altitude": None, "depth": None,
        "speed": None, "frame": frame, "stamp": round(float(stamp), 6), "ended": True,
    })


class RosAutonomy(Autonomy):
    """Surveys as ``nav_msgs/Path`` for a ROS planner, its answers as reports (module docstring)."""

    name = "ros"
    options = {
        "master": ("", "the ROS master URI; empty: $ROS_MASTER_URI, else http://localhost:11311"),
        "node": ("coex_vehicle", "the name of CoEx's ROS node (one per process)"),
        "path_topic": ("/coex/survey/path", "where the survey goes: nav_msgs/Path (latched)"),
        "plan_topic": ("/coex/survey/plan", "the survey's id, kind, altitude, depth and speed: "
                                            "std_msgs/String JSON (latched; '' = none)"),
        "progress_topic": ("/coex/survey/progress", "the planner's answers: std_msgs/String "
                                                    "'[ID] started K | completed | refused WHY | aborted WHY'"),
        "frame": ("coex_local", "frame_id of the path: the local grid (x east, y north, z up)"),
        "answer_timeout": number(10.0, "seconds without any answer after a submit before it is reported "
                                       "REJECTED / AUTONOMY_NO_ANSWER (0: wait forever)", unit="s", lo=0),
        "position_fix_topic": ("/coex/position_fix", "where topside's position fixes go: "
                                                     "geometry_msgs/PoseWithCovarianceStamped (robot_localization's "
                                                     "pose input); '' = refuse them"),
        "silence": number(10.0, "seconds without the planner (its progress publisher connected, or an answer) "
                                "while a survey flies before it is aborted AUTONOMY_SILENT (0: not watched)",
                          unit="s", lo=0),
    }

    @classmethod
    def check(cls, options: Mapping[str, Any]) -> Problems:
        p = Problems()
        for key in ("master", "node", "path_topic", "plan_topic", "progress_topic", "frame", "position_fix_topic"):
            v = options.get(key, "x")
            if not isinstance(v, str) or (key in ("node", "path_topic", "progress_topic") and not v.strip()):
                p.said(key, f"autonomy 'ros': option {key!r} must be a "
                            f"{'non-empty ' if key in ('node', 'path_topic', 'progress_topic') else ''}"
                            f"string, not {v!r}")
        master = options.get("master", "")
        if isinstance(master, str) and master and not master.startswith(("http://", "https://")):
            p.said("master", f"autonomy 'ros': option 'master' must be an http:// URI, not {master!r}")
        return p

    def __init__(self, options: Mapping[str, Any], context: Any) -> None:
        super().__init__(options, context)
        self.node: Any = None
        self._path: Any = None
        self._plan_pub: Any = None
        self._fix_pub: Any = None
        self._sub: Any = None
        self._answers: deque[str] = deque(maxlen=1000)
        self._lock = threading.Lock()
        self.plan: Any = None
        self._since = 0.0
        self._answered = True
        self._done = True
        self._index: int | None = None
        #: the survey whose path is latched now (None: none, or its ended form)
        self.latched: int | None = None
        #: surveys handed over before the one flown now (their answers are late answers)
        self._handed: deque[int] = deque(maxlen=64)
        self._heard: float | None = None
        self._out: list[SurveyReport] = []
        self._problem = LogOnce(log)
        self.stats = {"published": 0, "received": 0, "ignored": 0, "ended": 0}

    def open(self) -> None:
        if self.node is not None:
            return
        from coex.ros import RosNode

        c = self.config
        node = RosNode.get(c["master"], c["node"])
        self._path = node.publisher(c["path_topic"], "nav_msgs/Path", latch=True)
        if c["plan_topic"]:
            self._plan_pub = node.publisher(c["plan_topic"], "std_msgs/String", latch=True)
        if c["position_fix_topic"]:
            self._fix_pub = node.publisher(c["position_fix_topic"], "geometry_msgs/PoseWithCovarianceStamped")
        self._sub = node.subscribe(c["progress_topic"], self._on_answer, queue=100)
        self.node = node

    def _on_answer(self, msgtype: str, data: bytes) -> None:  # in a rospy thread
        if msgtype not in ("std_msgs/String", "std_msgs/msg/String"):
            self._problem(f"type:{msgtype}", "ros: %s carries %s, not std_msgs/String: dropped",
                          self.config["progress_topic"], msgtype)
            return
        try:
            text = str(self.node.deserialize("std_msgs/String", data).data)
        except ValueError as exc:
            self._problem("bad", "ros: an answer that does not decode: %s", exc)
            return
        with self._lock:
            self._answers.append(text)

    def close(self) -> None:
        if self.node is not None:
            for pub in (self._path, self._plan_pub, self._fix_pub):
                if pub is not None:
                    pub.close()
            if self._sub is not None:
                self.node.unsubscribe(self._sub)
            self.node = None

    def aid(self, fix: Any, now: float) -> bool:
        """A position fix published on ``position_fix_topic`` as a
        ``geometry_msgs/PoseWithCovarianceStamped`` in ``frame``."""
        if not self.config["position_fix_topic"]:
            return False
        if self.node is None:
            self.open()
        from coex.ros import msgs

        self._fix_pub.publish(msgs.position_fix(fix, self.node.message_class, self.config["frame"]))
        return True

    def submit(self, plan: Any, now: float) -> None:
        if self.node is None:
            self.open()
        from coex.ros import msgs

        c = self.config
        z = -float(plan.depth) if plan.depth is not None else 0.0
        path = msgs.path(plan.waypoints, self.node.message_class, now, c["frame"], z=z, speed=plan.speed)
        self._drain(now)  # answers about an older survey are that one's (before publishing: a quick
        # planner's first answer to this one must not be taken for the older one's)
        if self.plan is not None:
            self._handed.append(int(self.plan.survey_id))
        self.plan, self._since, self._answered, self._done, self._index = plan, float(now), False, False, None
        if self._plan_pub is not None:
            text = self.node.message("std_msgs/String", data=plan_json(plan, now, c["frame"]))
            self._plan_pub.publish(text)
        sent = self._path.publish(path)
        self.latched = int(plan.survey_id)
        self.stats["published"] += 1
        log.info("ros: survey %s (%d waypoints) %s %s", plan.survey_id, len(plan.waypoints),
                 "published on" if sent else "waits for the ROS master to publish on", c["path_topic"])

    def _report(self, out: list[Any], state: SurveyState, now: float, reason: SurveyReason = SurveyReason.NONE,
                index: int | None = None, value: float | None = None, detail: str | None = None) -> None:
        out.append(SurveyReport(int(self.plan.survey_id), state, float(now), reason, index, value, detail))
        self._answered = True
        if state != SurveyState.STARTED:
            self._done = True

    def resume(self, plan: Any, now: float) -> bool:
        """The planner may still fly the Path: its progress answers are followed again."""
        if self.node is None:
            self.open()
        self.plan, self._since, self._answered, self._done, self._index = plan, float(now), True, False, None
        return True

    def end(self, survey_id: int, now: float) -> None:
        """The survey ended: stop following it and, when its path is the one latched (or none is,
        after a restart), latch the ended form instead (module docstring)."""
        if self.node is None:
            self.open()
        sid = int(survey_id)
        if self.plan is not None and int(self.plan.survey_id) == sid:
            self._done = True
        if sid not in self._handed and (self.plan is None or int(self.plan.survey_id) != sid):
            self._handed.append(sid)  # after a restart: its late answers are still its own
        if self.latched not in (None, sid):
            return  # a newer survey is latched: a planner that starts later gets that one
        c = self.config
        if self._plan_pub is not None:
            self._plan_pub.publish(self.node.message("std_msgs/String", data=ended_json(sid, now, c["frame"])))
        from coex.ros import msgs

        self._path.publish(msgs.path([], self.node.message_class, now, c["frame"]))
        self.latched = None
        self.stats["ended"] += 1
        log.info("ros: survey %s ended: %s holds the ended form (an empty path)", sid, c["path_topic"])

    def heard(self, now: float) -> float | None:
        """Now while a planner's publisher of the progress topic is connected to CoEx, else when
        one last was or last answered (-inf: never since this output opened; None: not opened).
        Only that side is read: a subscriber that dies (the planner's to the path) is noticed
        by rospy only when the next message is sent, a publisher that dies at once (its
        connection's end of stream)."""
        if self.node is None:
            return None
        if self._sub is not None and self._sub.connections() > 0:
            self._heard = float(now)
        return -math.inf if self._heard is None else self._heard

    def silent_detail(self) -> str:
        return f"no planner on {self.config['progress_topic']}"

    def poll(self, now: float) -> list[Any]:
        if self.node is None:
            return []
        self._drain(now)
        out, self._out = self._out, []
        timeout = float(self.config["answer_timeout"])
        if self.plan is not None and not self._answered and not self._done and timeout > 0 \
                and now - self._since >= timeout:
            listeners = self._path.connections() if self._path is not None else 0
            waited = now - self._since
            why = (f"no answer on {self.config['progress_topic']}" if listeners else
                   f"no planner subscribed to {self.config['path_topic']}")
            log.warning("ros: survey %s: %s within %g s", self.plan.survey_id, why, timeout)
            # the seconds first: a long topic name is what the 48 bytes of detail cut
            self._report(out, SurveyState.REJECTED, now, SurveyReason.AUTONOMY_NO_ANSWER,
                         detail=f"{round(waited, 1):g} s, {why}")
        return out

    def _drain(self, now: float) -> None:
        """The planner's answers received since the last call, into the reports of the next poll."""
        with self._lock:
            answers = list(self._answers)
            self._answers.clear()
        out = self._out
        for text in answers:
            self.stats["received"] += 1
            try:
                sid, state, reason, index, detail = parse_progress(text)
            except ValueError as exc:
                self.stats["ignored"] += 1
                self._problem(f"parse:{text[:40]}", "ros: answer %r not understood: %s", text, exc)
                continue
            self._heard = float(now)
            current = None if self.plan is None else int(self.plan.survey_id)
            about = current if sid is None else sid
            if about is None or (about != current and about not in self._handed):
                self.stats["ignored"] += 1
                self._problem(f"other:{about}", "ros: answer %r dropped (survey %s was not handed over by "
                              "this output; survey %s is flown now)", text, about, current)
                continue
            if about != current or self._done:  # a late answer: the daemon's lifecycle records it
                out.append(SurveyReport(int(about), state, float(now), reason, index, None, detail))
                continue
            if state == SurveyState.STARTED:
                n = len(self.plan.waypoints)
                if index is None or not 0 <= index < n or index == self._index:
                    self.stats["ignored"] += 1
                    if index is None or not 0 <= index < n:
                        self._problem(f"index:{index}", "ros: waypoint %s of a %d-waypoint survey ignored", index, n)
                    continue
                self._index = index
            elif state == SurveyState.COMPLETED and self._index is None:
                self._report(out, SurveyState.STARTED, now, index=0)  # it did set off
            self._report(out, state, now, reason, index, None, detail)

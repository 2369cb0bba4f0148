"""The ``survey`` modality: survey commands from topside to the vehicle, and their states back.

Topside, :class:`SurveyReceiver` sends a :class:`~coex_core.messages.SurveyCommand` (go to a
point, fly a line, a lawnmower or waypoints; :meth:`SurveyReceiver.request`) and follows it:
the vehicle's CommandAck, then :class:`~coex_core.messages.SurveyStatus` reports (accepted,
rejected with a reason, started, completed, aborted). Subsea, :class:`SurveySender` checks each
command against the vehicle's geofence and limits (:class:`~.plan.Geofence`), keeps the queue of
accepted surveys, gives the one to fly now to the vehicle's autonomy (:meth:`SurveySender.active_plan`;
the daemon hands it to a ``coex.autonomy`` output) and reports every change of state topside, re-sent
until acknowledged. What the autonomy says happened comes back through :meth:`SurveySender.ingest`
(:class:`~.plan.SurveyReport`), so a node store journals it like any sensor input.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from coex import (
    CoexError,
    EncodeError,
    Modality,
    ModalityReceiver,
    ModalitySender,
    PositionAid,
    Product,
    RequestRejected,
    RequestTracker,
    merged_config,
    persistent,
    to_stamp,
    unwrap,
)
from coex.messages import (
    AckStatus,
    CommandAck,
    Message,
    PositionFix,
    PositionSource,
    SurveyCommand,
    SurveyKind,
    SurveyPoint,
    SurveyReason,
    SurveyState,
    SurveyStatus,
)
from coex.wire import encode, encoded_size

from .plan import Geofence, Refusal, SurveyPlan, SurveyReport, cut_detail, describe, plan_of

__all__ = ["PositionAid", "SurveyModality", "SurveyPlan", "SurveyReceiver", "SurveyReport", "SurveySender"]

SENDER_DEFAULTS: dict[str, Any] = {
    #: the vehicle's limits (:class:`~.plan.Geofence` keys); empty: no geofence
    "geofence": {},
    #: whether the vehicle has an autonomy that takes surveys (False: every survey is rejected
    #: with NO_AUTONOMY)
    "autonomy": True,
    #: seconds before an unacknowledged status is sent again
    "rto": 120.0,
    #: surveys remembered (finished ones beyond this are forgotten, oldest first)
    "keep": 64,
    #: whether the vehicle's navigation takes position fixes from topside (``PositionFix``, issue
    #: 56): accepted and handed to the autonomy output's ``aid`` (False: rejected)
    "aiding": False,
}
RECEIVER_DEFAULTS: dict[str, Any] = {
    #: seconds between re-sends of an unanswered survey command
    "retry": 300.0,
    #: sends of a survey command before it is given up
    "max_tries": 6,
}
class InvalidReport(CoexError, ValueError):
    """What was given to :meth:`SurveySender.ingest` is not a survey report."""


FINAL = (SurveyState.REJECTED, SurveyState.COMPLETED, SurveyState.ABORTED)


#: late answers kept per survey (the newest)
LATE_MAX = 8


def _upgrade_tx_survey(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    # version 1 had no detail, versions 1 and 2 kept no late answers
    return {"detail": None, "late": [], **fields}


@persistent("survey.TxSurvey", version=3, upgrade=_upgrade_tx_survey)
class _Survey:
    """One survey on the vehicle: its plan (None when refused), its newest state, and the
    autonomy's answers that came after it ended (``late``: ``(time, state, index, reason,
    detail)``, the newest :data:`LATE_MAX`; kept, never sent: an ended survey's state is final)."""

    __slots__ = ("acked", "command", "detail", "index", "late", "plan", "reason", "sent_at", "state",
                 "survey_id", "time", "value")

    def __init__(self, survey_id: int, command: SurveyCommand | None, plan: SurveyPlan | None,
                 state: SurveyState, time: float, reason: SurveyReason = SurveyReason.NONE,
                 index: int | None = None, value: float | None = None, detail: str | None = None) -> None:
        self.survey_id, self.command, self.plan = survey_id, command, plan
        self.state, self.time, self.reason, self.index, self.value = state, time, reason, index, value
        self.detail = cut_detail(detail)
        self.sent_at: float | None = None
        self.acked = False
        self.late: list[tuple[float, str, int | None, str, str | None]] = []

    def status(self) -> SurveyStatus:
        index = None if self.index is None else max(0, min(int(self.index), 255))
        value = None if self.value is None else round(max(0.0, min(float(self.value), 10000.0)), 1)
        return SurveyStatus(self.survey_id, self.state, self.reason, to_stamp(self.time), index, value,
                            self.detail)

    def set(self, state: SurveyState, time: float, reason: SurveyReason = SurveyReason.NONE,
            index: int | None = None, value: float | None = None, detail: str | None = None) -> None:
        self.state, self.time, self.reason, self.index, self.value = state, time, reason, index, value
        self.detail = cut_detail(detail)
        self.sent_at, self.acked = None, False


def _upgrade_sender(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    return {"aiding": False, "aids": [], "_fixes_seen": [], **fields}  # version 1 took no position fixes


@persistent("survey.Sender", version=2, upgrade=_upgrade_sender)
class SurveySender(ModalitySender):
    """The vehicle side (see the module docstring)."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, SENDER_DEFAULTS, "survey sender")
        self.geofence = Geofence.from_config(cfg["geofence"], "survey sender geofence")
        self.autonomy = bool(cfg["autonomy"])
        self.rto = float(cfg["rto"])
        self.keep = int(cfg["keep"])
        self.aiding = bool(cfg["aiding"])
        #: position fixes accepted and not yet taken by the autonomy (:meth:`take_aids`)
        self.aids: list[PositionAid] = []
        #: the newest fixes taken (stamp, x, y, sigma): a repeat is answered, not handed on twice
        self._fixes_seen: list[tuple[int, float, float, float]] = []
        self.surveys: dict[int, _Survey] = {}
        #: accepted surveys not yet finished, in the order they are to be flown (the first is active)
        self.queue: list[int] = []
        #: increases whenever the survey to fly now changes (:meth:`active_plan`)
        self.plan_version = 0

    # ------------------------------------------------------------------ the autonomy's side
    def active_plan(self) -> SurveyPlan | None:
        """The survey the vehicle should fly now (None: none)."""
        return self.surveys[self.queue[0]].plan if self.queue else None

    def ingest(self, data: Any, now: float) -> None:
        """Take what the vehicle's autonomy reports (:class:`SurveyReport`, or a sequence of
        them): the survey's new state goes topside. A report on a survey that was already
        finished (a late "completed" of a superseded plan, a planner's "started" after it was
        given up) changes nothing and is kept in the survey's record (:meth:`late`); one on a
        survey this sender never saw (the vehicle's own mission) is reported as it is."""
        reports = [data] if isinstance(data, SurveyReport) else list(data) if isinstance(data, list | tuple) else None
        if reports is None or not all(isinstance(r, SurveyReport) for r in reports):
            raise InvalidReport(f"the survey sender takes SurveyReports, not {type(data).__name__}")
        for r in reports:
            state = SurveyState(r.state)
            if state == SurveyState.ACCEPTED:
                raise InvalidReport("an autonomy reports STARTED, COMPLETED, ABORTED or REJECTED, not ACCEPTED")
        for r in reports:
            self._report(r)

    def _report(self, r: SurveyReport) -> None:
        s = self.surveys.get(r.survey_id)
        if s is None:
            s = self.surveys[r.survey_id] = _Survey(r.survey_id, None, None, r.state, r.time)
        elif s.state in FINAL:
            entry = (float(r.time), SurveyState(r.state).name, r.index, SurveyReason(r.reason).name,
                     cut_detail(r.detail))
            if not s.late or s.late[-1][1:] != entry[1:]:  # the same answer repeated: kept once
                s.late.append(entry)
                del s.late[:-LATE_MAX]
            return
        if s.state == r.state == SurveyState.STARTED and s.index == r.index:
            return
        s.set(SurveyState(r.state), r.time, SurveyReason(r.reason), r.index, r.value, r.detail)
        if s.state in FINAL and r.survey_id in self.queue:
            first = self.queue[0] == r.survey_id
            self.queue.remove(r.survey_id)
            if first:
                self.plan_version += 1
        self._forget()

    def state_of(self, survey_id: int) -> SurveyState | None:
        """The newest state of a survey this sender holds (None: not known, or forgotten)."""
        s = self.surveys.get(int(survey_id))
        return None if s is None else SurveyState(s.state)

    def late(self, survey_id: int) -> list[tuple[float, str, int | None, str, str | None]]:
        """The autonomy's answers about a survey that came after it ended: ``(time, state,
        index, reason, detail)``, oldest first (the newest :data:`LATE_MAX`)."""
        s = self.surveys.get(int(survey_id))
        return [] if s is None else list(s.late)

    # ------------------------------------------------------------------ topside's commands
    def take_aids(self) -> list[PositionAid]:
        """The position fixes accepted since the last call, oldest first (the daemon hands them
        to the autonomy output's ``aid``)."""
        out, self.aids = self.aids, []
        return out

    def _position_fix(self, message: PositionFix, now: float) -> list[Message]:
        cid = int(message.command_id)
        if not self.aiding:
            return [CommandAck(cid, AckStatus.REJECTED)]
        key = (int(message.stamp), float(message.x), float(message.y), float(message.sigma))
        if key not in self._fixes_seen:
            self._fixes_seen = [*self._fixes_seen[-31:], key]
            t = unwrap(message.stamp, now)
            newest = max((a.time for a in self.aids), default=-float("inf"))
            if t >= newest:
                self.aids.append(PositionAid(t, float(message.x), float(message.y), float(message.sigma),
                                             message.depth, PositionSource(message.source).name.lower()))
        return [CommandAck(cid, AckStatus.ACCEPTED)]

    def handle(self, message: Message, now: float) -> list[Message]:
        if isinstance(message, PositionFix):
            return self._position_fix(message, now)
        if not isinstance(message, SurveyCommand):
            raise RequestRejected(f"the survey sender takes SurveyCommand, not {type(message).__name__}")
        cid, sid = int(message.command_id), int(message.survey_id)
        old = self.surveys.get(sid)
        if old is not None and old.command is not None and _same(old.command, message):
            # the same survey again (its ack was lost and topside re-sent it): answer, change nothing
            ok = old.state != SurveyState.REJECTED
            old.sent_at = None if not old.acked else old.sent_at
            return [CommandAck(cid, AckStatus.ACCEPTED if ok else AckStatus.REJECTED)]
        try:
            if not self.autonomy:
                raise Refusal(SurveyReason.NO_AUTONOMY)
            plan = plan_of(message)
            self.geofence.check(plan)
        except Refusal as exc:
            if sid in self.queue:  # the id now names the refused command
                first = self.queue[0] == sid
                self.queue.remove(sid)
                self.plan_version += first
            self.surveys[sid] = _Survey(sid, message, None, SurveyState.REJECTED, now, exc.reason, exc.index,
                                        exc.value)
            self._forget()
            return [CommandAck(cid, AckStatus.REJECTED)]
        if not message.append:
            for other in self.queue:
                if other != sid:
                    self.surveys[other].set(SurveyState.ABORTED, now, SurveyReason.SUPERSEDED)
            self.queue = []
        if sid in self.queue:
            self.queue.remove(sid)
        self.surveys[sid] = _Survey(sid, message, plan, SurveyState.ACCEPTED, now)
        self.queue.append(sid)
        if self.queue[0] == sid:
            self.plan_version += 1
        self._forget()
        return [CommandAck(cid, AckStatus.ACCEPTED)]

    def _forget(self) -> None:
        if len(self.surveys) <= self.keep:
            return
        for sid in sorted(self.surveys, key=lambda k: self.surveys[k].time):
            if len(self.surveys) <= self.keep:
                break
            s = self.surveys[sid]
            if s.state in FINAL and s.acked:
                del self.surveys[sid]

    # ------------------------------------------------------------------ reports topside
    def _due(self, now: float) -> list[_Survey]:
        return [s for s in self.surveys.values()
                if not s.acked and (s.sent_at is None or not (s.sent_at <= now < s.sent_at + self.rto))]

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        for s in sorted(self._due(now), key=lambda s: s.time):
            m = s.status()
            size = encoded_size(m)
            if size > max_bytes:
                break
            out.append(m)
            max_bytes -= size
            s.sent_at = now
        return out

    def acked(self, message: Message, now: float) -> None:
        s = self.surveys.get(message.survey_id) if isinstance(message, SurveyStatus) else None
        if s is not None and s.status() == message:
            s.acked = True

    def lost(self, message: Message, now: float) -> None:
        s = self.surveys.get(message.survey_id) if isinstance(message, SurveyStatus) else None
        if s is not None and s.status() == message and not s.acked:
            s.sent_at = None

    def pending_bytes(self) -> int:
        return sum(9 for s in self.surveys.values() if not s.acked and s.sent_at is None)

    def ready_bytes(self, now: float) -> int:
        return 9 * len(self._due(now))


def _same(a: SurveyCommand, b: SurveyCommand) -> bool:
    """The same survey, whatever its command id."""
    from dataclasses import replace

    return replace(a, command_id=0) == replace(b, command_id=0)


# ================================================================================ topside
def _upgrade_rx_survey(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    # version 1 kept neither the newest vehicle time nor which history entries carry one
    return {"vtime": None, "stamped": [False] * len(fields.get("history", [])), **fields}


@persistent("survey.RxSurvey", version=2, upgrade=_upgrade_rx_survey)
class SurveyRecord:
    """What topside knows of one survey it asked for (or heard of)."""

    __slots__ = ("command", "command_id", "history", "index", "reason", "stamped", "state", "survey_id",
                 "text", "time", "value", "version", "vtime")

    def __init__(self, survey_id: int, command: SurveyCommand | None, now: float) -> None:
        self.survey_id = survey_id
        self.command = command
        self.command_id = None if command is None else int(command.command_id)
        #: "requested" (sent, no answer yet), "given up", or a SurveyState name in lower case
        self.state = "requested" if command is not None else "unknown"
        self.reason: str | None = None
        self.text = ""
        self.index: int | None = None
        self.value: float | None = None
        self.time = now
        #: (time, state, text), in the order things happened: topside's own events (sent, the
        #: vehicle's CommandAck heard) at topside's time as they come, the vehicle's reports at the
        #: vehicle's time, a late one put back among them by its stamp
        self.history: list[tuple[float, str, str]] = [(now, self.state, "")]
        #: for each history entry, whether its time is the vehicle's (a SurveyStatus stamp)
        self.stamped: list[bool] = [False]
        self.version = 1
        #: the vehicle's time of the newest SurveyStatus taken (None: none yet)
        self.vtime: float | None = None

    def set(self, state: str, time: float, text: str = "", reason: str | None = None, *,
            stamped: bool = False) -> None:
        self.state, self.time, self.text, self.reason = state, time, text, reason
        self.history.append((time, state, text))
        self.stamped.append(stamped)
        self.version += 1

    def restamp(self, state: str, time: float) -> None:
        """The vehicle's report of a state topside already noted at its own time (the
        CommandAck's "accepted"): the entry takes the vehicle's time, so the history's times
        are the vehicle's wherever the vehicle said when."""
        for i, (_t, st, text) in enumerate(self.history):
            if st == state and not self.stamped[i]:
                self.history[i] = (time, st, text)
                self.stamped[i] = True
                if self.state == state:
                    self.time = time
                self.version += 1
                return

    def note_late(self, time: float, state: str, text: str = "") -> None:
        """A vehicle report older than one already taken: into the history by its stamp (after
        the vehicle's reports up to that time), without changing the present state."""
        at = len(self.history)
        while at > 0 and not (self.stamped[at - 1] and self.history[at - 1][0] <= time):
            at -= 1
        if at == 0:  # older than every vehicle report: just before the first of them
            at = next((i for i, st in enumerate(self.stamped) if st), len(self.history))
        self.history.insert(at, (time, state, text))
        self.stamped.insert(at, True)
        self.version += 1


def _upgrade_receiver(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    return {"fixes": {}, **fields}  # version 1 sent no position fixes


@persistent("survey.Receiver", version=2, upgrade=_upgrade_receiver)
class SurveyReceiver(ModalityReceiver):
    """The topside side (see the module docstring)."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, RECEIVER_DEFAULTS, "survey receiver")
        self._requests: RequestTracker[Message] = RequestTracker(float(cfg["retry"]), int(cfg["max_tries"]))
        self.surveys: dict[int, SurveyRecord] = {}
        self._next_id = 0
        #: position fixes sent (command id -> ``[state, stamp, x, y, sigma]``; state "requested",
        #: "accepted", "rejected" or "given up")
        self.fixes: dict[int, list[Any]] = {}

    def request(self, kind: SurveyKind | str, x: float, y: float, now: float, *,
                heading: float | None = None, length: float | None = None, width: float | None = None,
                spacing: float | None = None, altitude: float | None = None, depth: float | None = None,
                speed: float | None = None, append: bool = False,
                points: Sequence[tuple[float, float]] = ()) -> SurveyCommand:
        """Ask the vehicle to survey (see :class:`~coex_core.messages.SurveyKind`); the command goes
        out at the next :meth:`poll` and again until answered. :class:`RequestRejected` when it
        cannot be sent as given (a field out of its range, a LINE without a heading ...)."""
        try:
            k = SurveyKind[kind.upper()] if isinstance(kind, str) else SurveyKind(kind)
        except (KeyError, ValueError):
            raise RequestRejected(f"unknown survey kind {kind!r} (goto, line, lawnmower, waypoints)") from None
        pts = tuple(SurveyPoint(round(float(a), 1), round(float(b), 1)) for a, b in points)
        sid = self._next_id

        def r(v: float | None, q: float) -> float | None:
            return None if v is None else round(round(float(v) / q) * q, 6)

        cmd = SurveyCommand(0, sid, k, round(float(x), 1), round(float(y), 1), r(heading, 0.1), r(length, 0.5),
                            r(width, 0.5), r(spacing, 0.5), r(altitude, 0.1), r(depth, 0.1), r(speed, 0.05),
                            bool(append), pts)
        try:
            encode(cmd)
        except EncodeError as exc:
            raise RequestRejected(f"this survey cannot be sent: {exc}") from None
        from dataclasses import replace

        cmd = replace(cmd, command_id=self.next_command_id())
        self._next_id = (sid + 1) % 1024
        self.surveys[sid] = SurveyRecord(sid, cmd, now)
        self._requests.add(cmd.command_id, cmd)
        return cmd

    def position_fix(self, x: float, y: float, now: float, *, stamp: float | None = None, sigma: float = 1.0,
                     depth: float | None = None, source: PositionSource | str = PositionSource.ESTIMATE
                     ) -> PositionFix:
        """Tell the vehicle where it truly was at ``stamp`` (default ``now``; local metres, 1-sigma
        ``sigma``): a :class:`~coex_core.messages.PositionFix` (spec type 15), sent at the next
        :meth:`poll` and again until the vehicle answers (accepted: its navigation takes aiding).
        :class:`RequestRejected` when it cannot be sent as given."""
        try:
            src = PositionSource[source.upper()] if isinstance(source, str) else PositionSource(source)
        except (KeyError, ValueError):
            raise RequestRejected(f"unknown position source {source!r} (usbl, estimate, other)") from None
        fix = PositionFix(0, src, to_stamp(now if stamp is None else stamp), round(float(x), 1), round(float(y), 1),
                          round(min(max(float(sigma), 0.0), 102.3), 1), None if depth is None else round(float(depth), 1))
        try:
            encode(fix)
        except EncodeError as exc:
            raise RequestRejected(f"this position fix cannot be sent: {exc}") from None
        from dataclasses import replace

        fix = replace(fix, command_id=self.next_command_id())
        self._requests.add(fix.command_id, fix)
        self.fixes[fix.command_id] = ["requested", now if stamp is None else stamp, fix.x, fix.y, fix.sigma]
        return fix

    def receive(self, message: Message, now: float) -> list[Product]:
        if isinstance(message, CommandAck) and message.command_id in self.fixes:
            state = self.fixes[message.command_id]
            if message.status != AckStatus.PENDING:
                self._requests.answered(message.command_id, now, message.status.name)
            if state[0] == "requested" and message.status in (AckStatus.ACCEPTED, AckStatus.REJECTED):
                state[0] = message.status.name.lower()
            return []
        if isinstance(message, CommandAck):
            rec = next((s for s in self.surveys.values() if s.command_id == message.command_id
                        and s.state == "requested"), None)
            if message.status != AckStatus.PENDING:
                self._requests.answered(message.command_id, now, message.status.name)
            if rec is None:
                return []
            if message.status == AckStatus.ACCEPTED:
                rec.set("accepted", now)
            elif message.status == AckStatus.REJECTED:
                rec.set("rejected", now, "refused by the vehicle (its reason follows)")
            elif message.status == AckStatus.UNAUTHENTICATED:
                rec.set("rejected", now, "not authenticated: the vehicle and topside command keys differ",
                        "UNAUTHENTICATED")
            else:
                return []
            return [self._product(rec)]
        if not isinstance(message, SurveyStatus):
            return []
        rec = self.surveys.get(message.survey_id)
        if rec is None:
            rec = self.surveys[message.survey_id] = SurveyRecord(message.survey_id, None, now)
        t = unwrap(message.stamp, now)
        state = SurveyState(message.state).name.lower()
        reason = SurveyReason(message.reason)
        text = describe(reason, message.index, message.value, message.detail) if reason != SurveyReason.NONE else ""
        if state == "started" and message.index is not None:
            text = f"heading for waypoint {message.index}"
        rec.restamp(state, t)
        same = (rec.state, rec.text, rec.index) == (state, text, message.index)
        if same or any(h == (t, state, text) for h in rec.history):
            return []  # a copy
        if (rec.vtime is not None and t < rec.vtime) or (
                rec.state in ("completed", "aborted", "rejected") and state in ("accepted", "started")):
            rec.note_late(t, state, text)  # an older state arriving late: history, not the present
            return [self._product(rec)]
        rec.vtime = t
        rec.index, rec.value = message.index, message.value
        rec.set(state, t, text, reason.name if reason != SurveyReason.NONE else None, stamped=True)
        if rec.command_id is not None:
            self._requests.answered(rec.command_id, now)
        return [self._product(rec)]

    def poll(self, now: float) -> list[Message]:
        out = self._requests.due(now)
        for cid, state in self.fixes.items():
            if state[0] == "requested" and cid not in self._requests:
                state[0] = "given up"
        for rec in self.surveys.values():
            if rec.state == "requested" and rec.command_id is not None and rec.command_id not in self._requests:
                rec.set("given up", now, "no answer from the vehicle")
        return out

    def pending_requests(self) -> list[Message]:
        return self._requests.pending()

    def _product(self, rec: SurveyRecord) -> Product:
        meta: dict[str, Any] = {"survey_id": rec.survey_id, "state": rec.state, "text": rec.text,
                                "reason": rec.reason, "index": rec.index, "time": rec.time,
                                "history": [list(h) for h in rec.history[-12:]]}
        if rec.command is not None:
            c = rec.command
            meta["kind"] = SurveyKind(c.kind).name.lower()
            try:
                meta["waypoints"] = [list(p) for p in plan_of(c).waypoints]
            except Refusal:
                meta["waypoints"] = [[c.x, c.y]]
            for k in ("heading", "length", "width", "spacing", "altitude", "depth", "speed", "append"):
                meta[k] = getattr(c, k)
        return Product("survey", str(rec.survey_id), rec.version, None, meta)

    def products(self) -> list[Product]:
        return [self._product(r) for r in self.surveys.values()]

    def view(self, product: Product) -> Mapping[str, Any] | None:
        m = product.meta
        return {"survey": m.get("survey_id"), "kind": m.get("kind", "?"), "state": m.get("state"),
                "why": m.get("text") or ""}

    def supersedes(self, old: Message, new: Message) -> bool:
        return False


class SurveyModality(Modality):
    """The ``survey`` modality plugin."""

    name: ClassVar[str] = "survey"
    version: ClassVar[str] = "1.0"
    messages: ClassVar[tuple[type[Message], ...]] = (SurveyStatus,)
    requests: ClassVar[tuple[type[Message], ...]] = (SurveyCommand, PositionFix)
    #: a finished survey sends nothing; one status per change of state
    keepalive_bytes_per_hour: ClassVar[int] = 0

    def sender(self, config: Mapping[str, Any] | None = None) -> SurveySender:
        return SurveySender(config)

    def receiver(self, config: Mapping[str, Any] | None = None) -> SurveyReceiver:
        return SurveyReceiver(config)

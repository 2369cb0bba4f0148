"""Survey commands: the plan a command asks for, the vehicle's geofence and limits, the queue of
accepted surveys, the autonomy's reports, and the whole exchange between two real nodes (signed
commands, acks, the reason for a rejection shown topside)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from coex_core.channel import ChannelManager, LinkConfig, Schedule, StreamConfig
from coex_core.errors import ConfigError, RequestRejected
from coex_core.messages import (
    AckStatus,
    CommandAck,
    SurveyCommand,
    SurveyKind,
    SurveyPoint,
    SurveyReason,
    SurveyState,
    SurveyStatus,
)
from coex_core.node import Node
from coex_core.state import dumps, loads
from coex_plugins.survey import InvalidReport, SurveyModality, SurveyReceiver, SurveySender
from coex_plugins.survey.plan import Geofence, Refusal, SurveyReport, describe, plan_of

KEY = b"k" * 32
FENCE = {"polygon": [[-100, -100], [100, -100], [100, 100], [-100, 100]], "min_altitude": 2.0,
         "max_depth": 300.0, "max_speed": 2.0, "max_length": 5000.0}


# ------------------------------------------------------------------------------ plans
def test_lawnmower_rows_are_spaced_and_start_on_the_port_side() -> None:
    p = plan_of(SurveyCommand(1, 1, SurveyKind.LAWNMOWER, 10.0, 20.0, 0.0, 60.0, 30.0, 10.0, 5.0))
    w = np.asarray(p.waypoints)
    assert len(w) == 8  # 4 rows of 2 points
    # heading north: rows run south to north, the first on the west (port) side
    assert w[0].tolist() == [-5.0, -10.0] and w[1].tolist() == [-5.0, 50.0]
    assert sorted(set(w[:, 0].tolist())) == [-5.0, 5.0, 15.0, 25.0]
    assert math.isclose(p.path_length, 4 * 60 + 3 * 10)
    assert p.altitude == 5.0 and p.centre == (10.0, 20.0)


def test_line_goto_and_waypoints() -> None:
    line = plan_of(SurveyCommand(1, 1, SurveyKind.LINE, 0.0, 0.0, 90.0, 40.0))
    assert np.allclose(line.waypoints, [(0, 0), (40, 0)])
    assert plan_of(SurveyCommand(1, 2, SurveyKind.GOTO, 3.0, 4.0)).waypoints == ((3.0, 4.0),)
    wp = plan_of(SurveyCommand(1, 3, SurveyKind.WAYPOINTS, 0.0, 0.0, points=(SurveyPoint(1, 2), SurveyPoint(3, 4))))
    assert wp.waypoints == ((0.0, 0.0), (1.0, 2.0), (3.0, 4.0))
    with pytest.raises(Refusal) as e:
        plan_of(SurveyCommand(1, 4, SurveyKind.LINE, 0.0, 0.0, 90.0, 0.0))
    assert e.value.reason == SurveyReason.INVALID


def test_geofence_names_the_rule_the_waypoint_and_the_number() -> None:
    g = Geofence.from_config(FENCE)
    g.check(plan_of(SurveyCommand(1, 1, SurveyKind.LINE, -90.0, 0.0, 90.0, 180.0, altitude=5.0)))
    with pytest.raises(Refusal) as e:
        g.check(plan_of(SurveyCommand(1, 1, SurveyKind.WAYPOINTS, 0.0, 0.0,
                                      points=(SurveyPoint(50, 0), SurveyPoint(150, 0)))))
    assert (e.value.reason, e.value.index, e.value.value) == (SurveyReason.OUTSIDE_GEOFENCE, 2, 50.0)
    assert str(e.value) == "waypoint 2 is 50 m outside the geofence"
    for cmd, reason in [(SurveyCommand(1, 1, SurveyKind.GOTO, 0, 0, altitude=1.0), SurveyReason.ALTITUDE_LIMIT),
                        (SurveyCommand(1, 1, SurveyKind.GOTO, 0, 0, depth=400.0), SurveyReason.DEPTH_LIMIT),
                        (SurveyCommand(1, 1, SurveyKind.GOTO, 0, 0, speed=3.0), SurveyReason.SPEED_LIMIT),
                        (SurveyCommand(1, 1, SurveyKind.LAWNMOWER, 0, 0, 0.0, 190.0, 190.0, 0.5),
                         SurveyReason.INVALID)]:  # 381 rows
        with pytest.raises(Refusal) as e:
            g.check(plan_of(cmd))
        assert e.value.reason == reason, cmd
    # a concave fence: both ends inside, the leg between them outside
    u = Geofence.from_config({"polygon": [[0, 0], [100, 0], [100, 100], [50, 10], [0, 100]]})
    with pytest.raises(Refusal) as e:
        u.check(plan_of(SurveyCommand(1, 1, SurveyKind.LINE, 10.0, 50.0, 90.0, 80.0)))
    assert e.value.index == 1 and "leaves the geofence" in str(e.value)
    # a circle round the origin
    c = Geofence.from_config({"radius": 50.0})
    with pytest.raises(Refusal) as e:
        c.check(plan_of(SurveyCommand(1, 1, SurveyKind.GOTO, 30.0, 50.0)))
    assert e.value.value == pytest.approx(8.3, abs=0.05)


@pytest.mark.parametrize("bad, key", [({"polygon": [[0, 0], [1, 1]]}, "polygon"),
                                      ({"radius": -1}, "radius"), ({"max_depht": 3}, "max_depht"),
                                      ({"polygon": [[0, "a"], [1, 1], [2, 2]]}, "polygon")])
def test_a_bad_geofence_names_the_key(bad: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        Geofence.from_config(bad)


# ------------------------------------------------------------------------------ sender
def _cmd(cid: int, sid: int, x: float = 0.0, *, append: bool = False, altitude: float | None = 5.0) -> SurveyCommand:
    return SurveyCommand(cid, sid, SurveyKind.LINE, x, 0.0, 90.0, 20.0, altitude=altitude, append=append)


def test_sender_queue_supersede_append_and_reports() -> None:
    s = SurveySender({"geofence": FENCE})
    assert s.handle(_cmd(1, 1), 0.0) == [CommandAck(1, AckStatus.ACCEPTED)]
    assert s.active_plan().survey_id == 1 and s.plan_version == 1
    s.handle(_cmd(2, 2, append=True), 1.0)
    assert s.active_plan().survey_id == 1 and s.queue == [1, 2]
    s.ingest(SurveyReport(1, SurveyState.STARTED, 2.0, index=0), 2.0)
    s.ingest(SurveyReport(1, SurveyState.COMPLETED, 3.0), 3.0)
    assert s.active_plan().survey_id == 2 and s.plan_version == 2
    s.handle(_cmd(3, 3, x=50.0), 4.0)  # replaces survey 2
    assert s.queue == [3] and s.surveys[2].state == SurveyState.ABORTED
    assert s.surveys[2].reason == SurveyReason.SUPERSEDED
    s.ingest(SurveyReport(2, SurveyState.COMPLETED, 5.0), 5.0)  # late: ignored
    assert s.surveys[2].state == SurveyState.ABORTED
    out = s.fill(240, 6.0)
    assert {(m.survey_id, m.state) for m in out} == {(1, SurveyState.COMPLETED), (2, SurveyState.ABORTED),
                                                    (3, SurveyState.ACCEPTED)}
    assert s.fill(240, 7.0) == []  # re-sent only after rto, or when lost
    s.lost(out[0], 8.0)
    assert s.fill(240, 8.0) == [out[0]]
    for m in out:
        s.acked(m, 9.0)
    assert s.fill(240, 500.0) == []
    with pytest.raises(InvalidReport):
        s.ingest("started", 10.0)


def test_sender_rejects_and_a_resent_command_is_not_applied_twice() -> None:
    s = SurveySender({"geofence": FENCE})
    assert s.handle(_cmd(5, 9, x=500.0), 0.0) == [CommandAck(5, AckStatus.REJECTED)]
    assert s.active_plan() is None
    [st] = s.fill(240, 1.0)
    assert (st.state, st.reason, st.index) == (SurveyState.REJECTED, SurveyReason.OUTSIDE_GEOFENCE, 0)
    s.handle(_cmd(6, 10), 2.0)
    s.ingest(SurveyReport(10, SurveyState.STARTED, 3.0, index=1), 3.0)
    version = s.plan_version
    assert s.handle(_cmd(7, 10), 4.0) == [CommandAck(7, AckStatus.ACCEPTED)]  # the same survey again
    assert s.surveys[10].state == SurveyState.STARTED and s.plan_version == version
    no = SurveySender({"autonomy": False})
    assert no.handle(_cmd(1, 1), 0.0) == [CommandAck(1, AckStatus.REJECTED)]
    assert no.surveys[1].reason == SurveyReason.NO_AUTONOMY


def test_sender_and_receiver_survive_a_restart() -> None:
    s = SurveySender({"geofence": FENCE})
    s.handle(_cmd(1, 1), 0.0)
    s.handle(_cmd(2, 2, append=True), 0.0)
    s2 = loads(dumps(s))
    assert s2.queue == [1, 2] and s2.active_plan() == s.active_plan() and s2.geofence == s.geofence
    r = SurveyReceiver()
    r.request("goto", 1.0, 2.0, 0.0)
    r2 = loads(dumps(r))
    assert r2.surveys[0].state == "requested" and r2.pending_requests() == r.pending_requests()


def test_receiver_refuses_what_cannot_be_sent() -> None:
    r = SurveyReceiver()
    with pytest.raises(RequestRejected, match="kind"):
        r.request("spiral", 0.0, 0.0, 0.0)
    with pytest.raises(RequestRejected, match="heading"):
        r.request("line", 0.0, 0.0, 0.0, length=10.0)  # no heading
    with pytest.raises(RequestRejected):
        r.request("goto", 1e6, 0.0, 0.0)
    assert not r.pending_requests()


def test_describe_reads_like_a_sentence() -> None:
    assert describe(SurveyReason.ALTITUDE_LIMIT, None, 3.0) == "below the vehicle's minimum altitude (3 m)"
    assert describe(SurveyReason.SUPERSEDED) == "replaced by a newer survey"


# ------------------------------------------------------------------------------ two nodes
def _nodes(key: bytes | None = KEY, fence: dict | None = None) -> tuple[Node, Node, SurveySender, SurveyReceiver]:
    sched = Schedule.simple([1, 2], 10.0, 1.0)
    vehicle = Node(ChannelManager(2, [LinkConfig(0, sched, rate=5, dst=1)], command_key=key))
    topside = Node(ChannelManager(1, [LinkConfig(0, sched, rate=5, dst=2)], command_key=key))
    tx, rx = SurveySender({"geofence": fence or FENCE}), SurveyReceiver()
    vehicle.add_sender(SurveyModality, tx, StreamConfig(7, "survey", priority=90))
    topside.add_receiver(SurveyModality, rx)
    return vehicle, topside, tx, rx


def _run(vehicle: Node, topside: Node, t0: float, t1: float, drop: set[int] | None = None) -> None:
    n = 0
    for t in np.arange(t0, t1, 1.0):
        for a, b in ((vehicle, topside), (topside, vehicle)):
            for tx in a.poll(float(t)):
                for f in tx.frames:
                    n += 1
                    if drop and n in drop:
                        continue
                    b.receive(0, f, float(t) + 0.5)


def test_two_nodes_accept_fly_and_complete_a_signed_survey() -> None:
    vehicle, topside, tx, rx = _nodes()
    cmd = rx.request("lawnmower", 0.0, 0.0, 0.0, heading=45.0, length=60.0, width=40.0, spacing=10.0, altitude=5.0)
    _run(vehicle, topside, 0.0, 60.0)
    assert tx.active_plan() is not None and tx.active_plan().survey_id == cmd.survey_id
    assert rx.surveys[cmd.survey_id].state == "accepted"
    tx.ingest(SurveyReport(cmd.survey_id, SurveyState.STARTED, 61.0, index=3), 61.0)
    _run(vehicle, topside, 61.0, 100.0)
    assert (rx.surveys[cmd.survey_id].state, rx.surveys[cmd.survey_id].index) == ("started", 3)
    tx.ingest(SurveyReport(cmd.survey_id, SurveyState.COMPLETED, 101.0), 101.0)
    _run(vehicle, topside, 101.0, 140.0)
    rec = rx.surveys[cmd.survey_id]
    assert rec.state == "completed"
    assert [h[1] for h in rec.history] == ["requested", "accepted", "started", "completed"]
    assert vehicle.stats["unauthenticated"] == 0


def test_a_survey_outside_the_geofence_is_rejected_with_its_reason_shown_topside() -> None:
    vehicle, topside, tx, rx = _nodes()
    cmd = rx.request("line", 50.0, 0.0, 0.0, heading=90.0, length=120.0, altitude=5.0)
    _run(vehicle, topside, 0.0, 60.0)
    rec = rx.surveys[cmd.survey_id]
    assert rec.state == "rejected" and rec.reason == "OUTSIDE_GEOFENCE"
    assert rec.text == "waypoint 1 is 70 m outside the geofence"
    assert tx.active_plan() is None
    [p] = [p for p in rx.products() if p.key == str(cmd.survey_id)]
    assert p.meta["state"] == "rejected" and "70 m outside" in p.meta["text"]


def test_an_unsigned_survey_is_refused_by_a_vehicle_with_a_key() -> None:
    vehicle, _, tx, _ = _nodes()
    _, topside, _, rx = _nodes(key=None)
    cmd = rx.request("goto", 1.0, 1.0, 0.0)
    _run(vehicle, topside, 0.0, 40.0)
    assert tx.active_plan() is None and vehicle.stats["unauthenticated"] >= 1
    assert rx.surveys[cmd.survey_id].state == "rejected"
    assert "not authenticated" in rx.surveys[cmd.survey_id].text


def test_lost_frames_delay_but_never_lose_the_states() -> None:
    vehicle, topside, tx, rx = _nodes()
    cmd = rx.request("goto", 10.0, 10.0, 0.0, altitude=5.0)
    _run(vehicle, topside, 0.0, 30.0, drop=set(range(1, 6)))  # the first frames both ways are lost
    _run(vehicle, topside, 30.0, 900.0)
    assert rx.surveys[cmd.survey_id].state == "accepted"
    assert isinstance(vehicle, Node) and tx.surveys[cmd.survey_id].acked
    assert not [m for m in tx.fill(240, 2000.0) if isinstance(m, SurveyStatus)]


# ------------------------------------------------------------------------------ autonomy outcomes
@pytest.mark.parametrize(("report", "state", "reason", "words"), [
    (SurveyReport(0, SurveyState.REJECTED, 61.0, SurveyReason.AUTONOMY_REFUSED, None, 14.0, "MAV_MISSION_DENIED"),
     "rejected", "AUTONOMY_REFUSED", "the vehicle's autonomy refused it (code 14): MAV_MISSION_DENIED"),
    (SurveyReport(0, SurveyState.REJECTED, 61.0, SurveyReason.AUTONOMY_REFUSED, None, None,
                  "Faulty update for behavior: coex_survey. Bad parameter(s): speed, capture_radius"),
     "rejected", "AUTONOMY_REFUSED", "refused it: Faulty update for behavior: coex_survey. Bad par"),
    (SurveyReport(0, SurveyState.REJECTED, 61.0, SurveyReason.AUTONOMY_NO_ANSWER, None, 6.0),
     "rejected", "AUTONOMY_NO_ANSWER", "no answer from the vehicle's autonomy (after 6 tries)"),
    (SurveyReport(0, SurveyState.ABORTED, 61.0, SurveyReason.MANUAL_OVERRIDE, None, None, "MOOS_MANUAL_OVERRIDE"),
     "aborted", "MANUAL_OVERRIDE", "taken over on the vehicle (manual override): MOOS_MANUAL_OVERRIDE"),
    (SurveyReport(0, SurveyState.ABORTED, 61.0, SurveyReason.AUTONOMY_RESTARTED),
     "aborted", "AUTONOMY_RESTARTED", "the vehicle's autonomy restarted and dropped it"),
    (SurveyReport(0, SurveyState.ABORTED, 61.0, SurveyReason.ALL_STOP, None, None, "MissingDecVars:depth"),
     "aborted", "ALL_STOP", "stopped all motion: MissingDecVars:depth"),
])
def test_each_autonomy_outcome_reaches_topside_in_its_own_words(report: SurveyReport, state: str, reason: str,
                                                                words: str) -> None:
    vehicle, topside, tx, rx = _nodes()
    cmd = rx.request("goto", 1.0, 1.0, 0.0)
    _run(vehicle, topside, 0.0, 60.0)
    assert rx.surveys[cmd.survey_id].state == "accepted"
    tx.ingest(report, 61.0)
    _run(vehicle, topside, 61.0, 100.0)
    rec = rx.surveys[cmd.survey_id]
    assert (rec.state, rec.reason) == (state, reason)
    assert words in rec.text
    assert tx.active_plan() is None  # whatever ended it, the vehicle no longer flies it


def test_a_long_detail_is_cut_to_what_the_wire_carries() -> None:
    s = SurveySender({"geofence": FENCE})
    s.handle(_cmd(1, 1), 0.0)
    s.ingest(SurveyReport(1, SurveyState.REJECTED, 1.0, SurveyReason.AUTONOMY_REFUSED, detail="é" * 40 + "\nx"), 1.0)
    [m] = s.fill(200, 2.0)
    assert isinstance(m, SurveyStatus) and m.detail is not None
    assert len(m.detail.encode()) <= 48 and m.detail == "é" * 24


def test_history_is_in_the_vehicles_time_order_whatever_order_it_arrives_in() -> None:
    r = SurveyReceiver()
    cmd = r.request("line", 0.0, 0.0, 0.0, heading=0.0, length=10.0)
    r.receive(CommandAck(cmd.command_id, AckStatus.ACCEPTED), 5.0)
    r.receive(SurveyStatus(cmd.survey_id, SurveyState.COMPLETED, SurveyReason.NONE, 300), 400.0)
    r.receive(SurveyStatus(cmd.survey_id, SurveyState.STARTED, SurveyReason.NONE, 100, 1), 410.0)
    rec = r.surveys[cmd.survey_id]
    assert rec.state == "completed"  # the late "started" is history, not the present
    assert [h[0] for h in rec.history] == sorted(h[0] for h in rec.history)
    assert [h[1] for h in rec.history] == ["requested", "accepted", "started", "completed"]


@pytest.mark.parametrize("version", [1, 2])
def test_an_older_saved_status_without_detail_or_late_answers_still_loads(version: int) -> None:
    s = SurveySender({"geofence": FENCE})
    s.handle(_cmd(1, 1), 0.0)
    data = dumps(s)
    n = int.from_bytes(data[10:14], "big")
    doc = data[14:14 + n].replace(b'"survey.TxSurvey":3', f'"survey.TxSurvey":{version}'.encode())
    for field in (b'"late":[]', b'"detail":null') if version == 1 else (b'"late":[]',):
        doc = doc.replace(b"," + field, b"").replace(field + b",", b"")
    assert b"late" not in doc and (b"detail" not in doc) == (version == 1)
    assert f'"survey.TxSurvey":{version}'.encode() in doc
    s2 = loads(data[:10] + len(doc).to_bytes(4, "big") + doc + data[14 + n:])
    assert s2.surveys[1].detail is None and s2.surveys[1].status().detail is None
    assert s2.late(1) == []
    s2.ingest(SurveyReport(1, SurveyState.COMPLETED, 5.0), 5.0)
    s2.ingest(SurveyReport(1, SurveyState.STARTED, 6.0, index=0), 6.0)  # late: recorded, not taken
    assert s2.state_of(1) == SurveyState.COMPLETED and s2.late(1) == [(6.0, "STARTED", 0, "NONE", None)]


def test_answers_after_a_survey_ended_are_kept_in_its_record_never_sent() -> None:
    s = SurveySender({"geofence": FENCE})
    s.handle(_cmd(1, 1), 0.0)
    s.ingest(SurveyReport(1, SurveyState.REJECTED, 10.0, SurveyReason.AUTONOMY_NO_ANSWER, detail="10 s"), 10.0)
    for t in (12.0, 13.0, 14.0):  # a planner repeating itself is kept once
        s.ingest(SurveyReport(1, SurveyState.STARTED, t, index=0), t)
    s.ingest(SurveyReport(1, SurveyState.COMPLETED, 20.0), 20.0)
    assert s.late(1) == [(12.0, "STARTED", 0, "NONE", None), (20.0, "COMPLETED", None, "NONE", None)]
    assert [m.state for m in s.fill(1000, 30.0)] == [SurveyState.REJECTED]  # the final state only
    for t in range(40):
        s.ingest(SurveyReport(1, SurveyState.STARTED, 100.0 + t, index=t % 3), 100.0 + t)
    assert len(s.late(1)) == 8 and s.late(1)[-1][0] == 139.0
    restored = loads(dumps(s))
    assert restored.late(1) == s.late(1) and restored.state_of(1) == SurveyState.REJECTED
    assert s.late(99) == [] and s.state_of(99) is None


def test_the_acks_accepted_takes_the_vehicles_time_when_its_report_comes() -> None:
    r = SurveyReceiver()
    cmd = r.request("goto", 0.0, 0.0, 100.0)
    r.receive(CommandAck(cmd.command_id, AckStatus.ACCEPTED), 130.7)  # heard topside at 130.7
    r.receive(SurveyStatus(cmd.survey_id, SurveyState.STARTED, SurveyReason.NONE, 125, 0), 140.0)
    r.receive(SurveyStatus(cmd.survey_id, SurveyState.ACCEPTED, SurveyReason.NONE, 120), 141.0)  # late
    rec = r.surveys[cmd.survey_id]
    assert [h[1] for h in rec.history] == ["requested", "accepted", "started"]
    assert [h[0] for h in rec.history] == [100.0, 120.0, 125.0]  # the vehicle's times, in order
    assert rec.state == "started"

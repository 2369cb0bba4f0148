"""The ``mavlink`` autonomy output against a MAVLink mission-protocol peer built from stock
pymavlink (coex_plugins.autonomy.mavpeer), over UDP on 127.0.0.1."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

pytest.importorskip("pymavlink")

from coex import InputContext
from coex_core.errors import ConfigError
from coex_core.messages import SurveyKind, SurveyReason, SurveyState
from coex_plugins.autonomy.mavlink import MavlinkAutonomy, mission_items
from coex_plugins.autonomy.mavpeer import MissionPeer
from coex_plugins.survey.plan import SurveyPlan, SurveyReport
from coex_transports.testing import free_port

CTX = InputContext(origin_lat=41.5, origin_lon=-70.7)
PTS = ((10.0, 0.0), (10.0, 10.0), (0.0, 10.0))
ROOT = Path(__file__).resolve().parents[1]


def _plan(sid: int = 7, pts: tuple[tuple[float, float], ...] = PTS, **kw: object) -> SurveyPlan:
    return SurveyPlan(sid, kw.pop("kind", SurveyKind.WAYPOINTS), pts, **kw)  # type: ignore[arg-type]


Until = Callable[[list[SurveyReport]], bool]


def _final(reports: list[SurveyReport]) -> bool:
    return any(r.state in (SurveyState.COMPLETED, SurveyState.REJECTED, SurveyState.ABORTED) for r in reports)


def run(out: MavlinkAutonomy, until: Until = _final, timeout: float = 5.0,
        peer: MissionPeer | None = None) -> list[SurveyReport]:
    """Poll (and step a hand-driven peer) in real time until ``until`` holds."""
    got: list[SurveyReport] = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if peer is not None:
            peer.step(time.monotonic())
        got += out.poll(time.monotonic())
        if until(got):
            return got
        time.sleep(0.002)
    raise AssertionError(f"timed out; reports so far: {got}")


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def make(port: int) -> Iterator[Callable[..., MavlinkAutonomy]]:
    made: list[MavlinkAutonomy] = []

    def build(**options: object) -> MavlinkAutonomy:
        # a peer thread on a loaded machine may answer late: unless a test is about them, the
        # resend timeouts are long enough that no answer is taken for a lost one (the exact
        # counts of items, acks and commands the tests assert hold)
        options = {"timeout": 3.0, "item_timeout": 1.0, **options}
        out = MavlinkAutonomy({"connection": f"udpout:127.0.0.1:{port}", **options}, CTX)
        out.open()
        made.append(out)
        return out

    yield build
    for out in made:
        out.close()


def _peer(port: int, **kw: object) -> MissionPeer:
    return MissionPeer(f"udpin:127.0.0.1:{port}", heartbeat=kw.pop("heartbeat", 0.2), **kw)  # type: ignore[arg-type]


# ------------------------------------------------------------------ the items (no sockets)
def test_items_carry_the_waypoints_lat_lon_and_depth_after_the_home_placeholder() -> None:
    items = mission_items(_plan(depth=20.0), CTX)
    assert [i.seq for i in items] == [0, 1, 2, 3] and [i.waypoint for i in items] == [None, 0, 1, 2]
    home = items[0]
    assert (home.command, home.frame, home.z) == (16, 0, 0.0)
    assert (home.x, home.y) == (415_000_000, -707_000_000)
    for item, (x, y) in zip(items[1:], PTS):
        lat, lon = CTX.geodetic(x, y)
        assert (item.x, item.y) == (round(lat * 1e7), round(lon * 1e7))
        assert (item.command, item.frame, item.z, item.param1, item.param2) == (16, 3, -20.0, 0.0, 2.0)
        assert math.isnan(item.param4)


def test_items_heights_frames_and_speed() -> None:
    alt = mission_items(_plan(altitude=5.0, speed=1.2), CTX, acceptance_radius=3.0, hold=4.0)
    speed = alt[1]
    assert (speed.seq, speed.command, speed.param1, speed.param2, speed.waypoint) == (1, 178, 1.0, 1.2, None)
    assert [(i.seq, i.frame, i.z, i.param1, i.param2) for i in alt[2:]] == [(s, 10, 5.0, 4.0, 3.0) for s in (2, 3, 4)]
    # an altitude with a non-terrain frame keeps the present depth; neither height: z = 0 too
    flat = mission_items(_plan(altitude=5.0), CTX, altitude_frame=3)
    assert {(i.frame, i.z) for i in flat[1:]} == {(3, 0.0)}
    assert {(i.frame, i.z) for i in mission_items(_plan(), CTX)[1:]} == {(3, 0.0)}
    # depth wins over altitude; without the placeholder waypoint k is seq k
    both = mission_items(_plan(altitude=5.0, depth=30.0, speed=1.0), CTX, home_placeholder=False, speed_item=False)
    assert [(i.seq, i.waypoint, i.frame, i.z) for i in both] == [(0, 0, 3, -30.0), (1, 1, 3, -30.0), (2, 2, 3, -30.0)]


@pytest.mark.parametrize(("options", "match"), [
    ({}, "needs option 'connection'"),
    ({"connection": ""}, "connection must be"),
    ({"connection": "udpout:h:1", "frame": 4}, "frame: one of 0, 3, 6, 10, 11, got 4"),
    ({"connection": "udpout:h:1", "start": "go"}, "start: one of 'mission_start', 'auto_mode', 'none', got 'go'"),
    ({"connection": "udpout:h:1", "timeout": 0}, "timeout: 0 is not above 0 s"),
    ({"connection": "udpout:h:1", "target_system": 300}, "target_system: 300 is outside 0..255"),
    ({"connection": "udpout:h:1", "home_placeholder": "yes"}, "home_placeholder: true or false"),
    ({"connection": "udpout:h:1", "manual_modes": [2, "x"]}, "manual_modes must be a list"),
    ({"connection": "udpout:h:1", "frme": 3}, "unknown option 'frme'"),
    ({"connection": "udpout:h:1", "silence": -1}, "silence: -1 is below 0 s"),
    ({"connection": "udpout:h:1", "clear": "no"}, "clear: true or false"),
])
def test_options_are_checked(options: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        MavlinkAutonomy(options, CTX)


def test_defaults() -> None:
    cfg = MavlinkAutonomy({"connection": "udpout:127.0.0.1:1"}, CTX).config
    assert (cfg["frame"], cfg["altitude_frame"], cfg["home_placeholder"], cfg["acceptance_radius"]) == (3, 10, True, 2.0)
    assert (cfg["timeout"], cfg["item_timeout"], cfg["retries"], cfg["start"], cfg["auto_mode"]) == (
        1.5, 0.25, 5, "mission_start", 3)
    assert (cfg["source_system"], cfg["source_component"], cfg["target_system"]) == (1, 191, None)


# ------------------------------------------------------------------ against the peer
def test_upload_accepted_started_then_completed(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, fly_interval=0.05) as peer:
        out = make()
        out.submit(_plan(depth=20.0), time.monotonic())
        got = run(out)
        assert [(r.survey_id, r.state, r.index) for r in got] == [
            (7, SurveyState.STARTED, 0), (7, SurveyState.STARTED, 1), (7, SurveyState.STARTED, 2),
            (7, SurveyState.COMPLETED, None)]
        assert peer.acks_sent == [0] and peer.counts == [4]
        assert [c[0] for c in peer.commands_received] == [300]  # MAV_CMD_MISSION_START
        assert [r[0] for r in peer.requests_sent] == ["MISSION_REQUEST_INT"] * 4
        items = peer.items
        assert [i["seq"] for i in items] == [0, 1, 2, 3] and {i["type"] for i in items} == {"MISSION_ITEM_INT"}
        for item, (x, y) in zip(items[1:], PTS):
            lat, lon = CTX.geodetic(x, y)
            assert item["x"] / 1e7 == pytest.approx(lat, abs=1e-7) and item["y"] / 1e7 == pytest.approx(lon, abs=1e-7)
            assert (item["frame"], item["command"], item["z"], item["autocontinue"], item["current"]) == (3, 16, -20.0, 1, 0)
        # MISSION_CURRENT keeps coming after the end; nothing more is reported
        time.sleep(0.3)
        assert out.poll(time.monotonic()) == []
        assert (out.target_system, out.target_component) == (1, 1) and out.stats["bad"] == 0


def test_peer_rejects_the_mission(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, result=4):  # MAV_MISSION_NO_SPACE
        out = make()
        out.submit(_plan(), time.monotonic())
        assert run(out) == [SurveyReport(7, SurveyState.REJECTED, pytest.approx(time.monotonic(), abs=5),  # type: ignore[arg-type]
                                         SurveyReason.AUTONOMY_REFUSED, None, 4.0, "MAV_MISSION_NO_SPACE")]


def test_a_denied_mission_is_reported_with_its_code_and_name(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, result=14):  # MAV_MISSION_DENIED (common.xml)
        out = make()
        out.submit(_plan(), time.monotonic())
        [r] = run(out)
        assert (r.state, r.reason, r.value, r.detail) == (SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, 14.0,
                                                          "MAV_MISSION_DENIED")


def test_result_and_mode_names_come_from_pymavlink_or_the_table(monkeypatch: pytest.MonkeyPatch) -> None:
    from coex_plugins.autonomy.mavlink import enum_name, mode_name

    assert enum_name("MAV_MISSION_RESULT", 14) == "MAV_MISSION_DENIED"
    assert enum_name("MAV_RESULT", 4) == "MAV_RESULT_FAILED"
    assert enum_name("MAV_RESULT", 99) == "MAV_RESULT 99"
    assert (mode_name(2), mode_name(9), mode_name(3, 2)) == ("ALT_HOLD", "SURFACE", "mode 3")  # 2: a quadrotor
    monkeypatch.setitem(sys.modules, "pymavlink.dialects.v20.ardupilotmega", None)  # not installed
    assert enum_name("MAV_MISSION_RESULT", 2) == "MAV_MISSION_UNSUPPORTED_FRAME"
    assert enum_name("MAV_RESULT", 6) == "MAV_RESULT_CANCELLED" and mode_name(19) == "MANUAL"


def test_peer_refuses_an_item_frame(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, frames=(0, 3)) as peer:  # no terrain frame
        out = make()
        out.submit(_plan(altitude=5.0), time.monotonic())
        last = run(out)[-1]
        assert (last.state, last.reason, last.value, last.detail) == (
            SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, 2.0, "MAV_MISSION_UNSUPPORTED_FRAME")
        assert peer.acks_sent == [2]  # MAV_MISSION_UNSUPPORTED_FRAME


def test_silent_peer_count_resent_then_no_answer(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    """Driven with a made-up clock: MISSION_COUNT again every 1.5 s, 5 times, then REJECTED
    AUTONOMY_NO_ANSWER after 6 tries (not AUTONOMY_REFUSED: nobody refused it)."""
    with _peer(port, silent=True) as peer:
        out = make(heartbeat=0, timeout=1.5)
        out.submit(_plan(), 100.0)
        assert out.poll(101.49) == []
        for k in range(1, 6):
            assert out.poll(100.0 + 1.5 * k) == []
        assert out.poll(108.9) == []
        [r] = out.poll(109.0)
        assert (r.survey_id, r.state, r.time, r.reason, r.value) == (
            7, SurveyState.REJECTED, 109.0, SurveyReason.AUTONOMY_NO_ANSWER, 6.0)
        assert r.detail is not None and r.detail.startswith("MISSION_COUNT unanswered")
        assert out.poll(200.0) == []
        deadline = time.monotonic() + 2
        while len(peer.counts) < 6 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert peer.counts == [4] * 6 and out.stats["resent"] == 5


def test_lost_item_is_resent_after_the_item_timeout(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, drop_items=2, request_timeout=60.0) as peer:  # the peer never asks again itself
        out = make(start="none")
        out.submit(_plan(), time.monotonic())
        got = run(out, lambda r: bool(r), timeout=30)
        assert got == [SurveyReport(7, SurveyState.STARTED, got[0].time, index=0)]
        assert out.stats["resent"] == 2 and [i["seq"] for i in peer.items] == [0, 1, 2, 3]
        assert peer.commands_received == []


def test_legacy_mission_request_is_answered(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, legacy=True, fly_interval=0.02) as peer:
        out = make(start="auto_mode")
        out.submit(_plan(depth=5.0, speed=0.7), time.monotonic())
        got = run(out)
        assert got[-1].state == SurveyState.COMPLETED
        assert {r[0] for r in peer.requests_sent} == {"MISSION_REQUEST"}
        assert [i["command"] for i in peer.items] == [16, 178, 16, 16, 16] and peer.items[1]["param2"] == pytest.approx(0.7)
        assert peer.commands_received == [(176, 1.0, 3.0)]  # DO_SET_MODE, custom mode AUTO


def test_start_refused_aborts(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    """Uploaded, but the start command is refused: never STARTED, ABORTED with the MAV_RESULT."""
    with _peer(port, start_result=4, fly_interval=0.02):  # MAV_RESULT_FAILED
        out = make()
        out.submit(_plan(), time.monotonic())
        got = run(out)
        assert [(r.state, r.reason, r.value, r.detail) for r in got] == [
            (SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED, 4.0, "MAV_RESULT_FAILED")]


def test_start_never_answered_is_no_answer(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    """The mission is uploaded, then the autopilot answers no start command: REJECTED
    AUTONOMY_NO_ANSWER with the tries (1 + retries), never STARTED."""
    with _peer(port, start_result=None) as peer:
        out = make(timeout=0.1, retries=2)
        out.submit(_plan(), time.monotonic())
        got = run(out)
        assert [(r.state, r.reason, r.value, r.detail) for r in got] == [
            (SurveyState.REJECTED, SurveyReason.AUTONOMY_NO_ANSWER, 3.0, "MAV_CMD_MISSION_START unanswered")]
        assert peer.acks_sent == [0] and [c[0] for c in peer.commands_received] == [300] * 3


def test_a_lost_start_ack_is_made_up_for_by_the_progress(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, ack_start=False, fly_interval=0.05):
        out = make(timeout=5.0)
        out.submit(_plan(), time.monotonic())
        got = run(out)
        assert [(r.state, r.index) for r in got][:1] == [(SurveyState.STARTED, 0)]
        assert got[-1].state == SurveyState.COMPLETED


def test_a_pilot_taking_over_mid_mission_is_a_manual_override(make: Callable[..., MavlinkAutonomy],
                                                               port: int) -> None:
    with _peer(port, fly_interval=0.3, stop_after=1, heartbeat=0.05):  # to ALT_HOLD
        out = make()
        out.submit(_plan(), time.monotonic())
        got = run(out)
        assert [(r.state, r.index) for r in got] == [(SurveyState.STARTED, 0), (SurveyState.STARTED, 1),
                                                     (SurveyState.ABORTED, None)]
        assert (got[-1].reason, got[-1].value, got[-1].detail) == (
            SurveyReason.MANUAL_OVERRIDE, 2.0, "left AUTO for ALT_HOLD")


def test_leaving_auto_for_another_mode_is_the_autonomy_stopping(make: Callable[..., MavlinkAutonomy],
                                                                port: int) -> None:
    with _peer(port, fly_interval=0.3, stop_after=1, stop_mode=9, heartbeat=0.05):  # SURFACE (a failsafe's)
        out = make()
        out.submit(_plan(), time.monotonic())
        last = run(out)[-1]
        assert (last.state, last.reason, last.value, last.detail) == (
            SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED, 9.0, "left AUTO for SURFACE")
    with _peer(port, fly_interval=0.3, stop_after=1, stop_mode=9, heartbeat=0.05):
        out = make(manual_modes=[9])  # this vehicle's pilots surface it by hand
        out.submit(_plan(8), time.monotonic())
        assert run(out)[-1].reason == SurveyReason.MANUAL_OVERRIDE


def test_target_from_the_vehicles_heartbeat(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    with _peer(port, system=7, component=1, fly_interval=0.02) as peer:
        out = make()
        end = time.monotonic() + 5
        while out.target_system is None and time.monotonic() < end:
            out.poll(time.monotonic())
            time.sleep(0.01)
        assert (out.target_system, out.target_component) == (7, 1)
        out.submit(_plan(), time.monotonic())
        assert run(out)[-1].state == SurveyState.COMPLETED and peer.counts == [4]


def test_new_plan_during_an_upload_restarts_it(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    peer = _peer(port)  # stepped by hand
    try:
        out = make(start="none")
        out.submit(_plan(1, ((1.0, 1.0), (2.0, 2.0))), time.monotonic())
        run(out, lambda _r: len(peer.items) >= 1, peer=peer)  # part of plan 1 is up
        out.submit(_plan(2, ((5.0, 5.0),), depth=3.0), time.monotonic())
        got = run(out, lambda r: bool(r), peer=peer)
        assert got == [SurveyReport(2, SurveyState.STARTED, got[0].time, index=0)]
        assert peer.missions[-1][-1]["z"] == -3.0 and len(peer.missions[-1]) == 2
        assert len(peer.missions) == 1  # plan 1 never completed
    finally:
        peer.close()


def test_an_ack_before_the_last_item_is_not_taken_as_the_answer(make: Callable[..., MavlinkAutonomy],
                                                                port: int) -> None:
    peer = _peer(port)  # stepped by hand
    try:
        out = make(start="none")
        out.poll(time.monotonic())  # our heartbeat: the peer learns where we are
        end = time.monotonic() + 5
        while peer.conn.mav.total_packets_received == 0 and time.monotonic() < end:
            peer.step(time.monotonic())
        out.submit(_plan(), time.monotonic())
        peer.conn.mav.mission_ack_send(1, 191, 0)  # a late "accepted" of an earlier upload
        got = run(out, lambda r: bool(r), peer=peer)
        assert got == [SurveyReport(7, SurveyState.STARTED, got[0].time, index=0)]
        assert len(peer.missions) == 1 and len(peer.missions[0]) == 4 and out.stats["ignored"] == 1
    finally:
        peer.close()


def test_garbage_and_wrong_requests_are_logged_and_ignored(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    peer = _peer(port)  # stepped by hand
    try:
        out = make(start="none")
        out.submit(_plan(), time.monotonic())
        end = time.monotonic() + 5
        while not peer.counts and time.monotonic() < end:
            peer.step(time.monotonic())  # receives MISSION_COUNT, asks for item 0
        assert peer.counts == [4]
        peer.conn.write(b"\xfd\x09garbage, not MAVLink at all\x00\xff")
        peer.conn.mav.mission_request_int_send(1, 191, 99)  # out of range
        peer.conn.mav.mission_request_int_send(1, 191, 1, mission_type=1)  # a geofence upload
        peer.conn.mav.mission_ack_send(42, 0, 4)  # an ack for someone else
        peer.conn.mav.mission_item_reached_send(3)  # progress before the start
        got = run(out, lambda r: bool(r), peer=peer)
        assert got == [SurveyReport(7, SurveyState.STARTED, got[0].time, index=0)]
        assert out.stats["bad"] >= 2 and out.stats["ignored"] >= 2
        assert peer.acks_sent == [0]
    finally:
        peer.close()


def test_mavpeer_as_a_program_prints_each_mission(make: Callable[..., MavlinkAutonomy], port: int) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(ROOT / p) for p in ("", "transports", "runtime", "plugins")))
    proc = subprocess.Popen([sys.executable, "-m", "coex_plugins.autonomy.mavpeer", "--listen",
                             f"udpin:127.0.0.1:{port}", "--duration", "20"], stdout=subprocess.PIPE, text=True,
                            env=env)
    try:
        out = make(start="none", timeout=0.5)
        # the program is up once its heartbeat is heard (its start takes seconds on a loaded
        # machine: the upload's 3 s of retries must not run meanwhile)
        run(out, lambda r: out.heard_at is not None, timeout=60)
        out.submit(_plan(depth=20.0), time.monotonic())
        got = run(out, lambda r: bool(r), timeout=15)
        assert got[0].state == SurveyState.STARTED
        assert proc.stdout is not None
        line = json.loads(proc.stdout.readline())
        assert (line["count"], line["result"], len(line["items"])) == (4, 0, 4)
        assert line["items"][1]["z"] == -20.0 and line["items"][1]["param4"] is None
    finally:
        proc.terminate()
        proc.wait(10)


def test_after_a_restart_the_flown_mission_is_followed_not_uploaded_again(make: Callable[..., MavlinkAutonomy],
                                                                         port: int) -> None:
    with _peer(port, fly_interval=0.4) as peer:
        first = make()
        first.submit(_plan(), time.monotonic())
        got = run(first, until=lambda rs: any(r.state == SurveyState.STARTED for r in rs))
        assert got[0].index == 0
        first.close()  # the daemon stops (kill, restart); the autopilot flies on
        again = make()
        assert again.resume(_plan(), time.monotonic()) is True
        later = run(again)
        assert later[-1].state == SurveyState.COMPLETED and all(r.survey_id == 7 for r in later)
        assert peer.counts == [4]  # uploaded once: the restart did not start the mission over


# ------------------------------------------------------------------ the survey lifecycle (issue 51)
def _mavpeer_process(port: int, *args: str) -> subprocess.Popen[str]:
    """``python -m coex_plugins.autonomy.mavpeer`` as a process of its own (an autopilot that can be
    killed), printing one JSON line per mission received or cleared."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(ROOT / p) for p in ("", "transports", "runtime", "plugins")))
    return subprocess.Popen([sys.executable, "-m", "coex_plugins.autonomy.mavpeer", "--listen",
                             f"udpin:127.0.0.1:{port}", "--heartbeat", "0.2", *args], stdout=subprocess.PIPE,
                            text=True, env=env)


def _lines(proc: subprocess.Popen[str]) -> list[dict[str, object]]:
    """The JSON lines a mavpeer process printed (read in a thread; the list grows)."""
    import threading

    out: list[dict[str, object]] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            out.append(json.loads(line))

    threading.Thread(target=read, daemon=True).start()
    return out


def test_an_ended_survey_is_cleared_and_never_uploaded_to_an_autopilot_started_later(
        make: Callable[..., MavlinkAutonomy], port: int) -> None:
    from ._lifecycle import Vehicle

    out = make(timeout=0.3, item_timeout=0.1, retries=2, silence=1.0)
    v = Vehicle(out, clock=time.monotonic, name="mavlink")
    # no autopilot: the upload is given up (no answer); the clearing of what it may have left
    # waits for the autopilot to be heard
    v.ask(1, x=10.0, depth=5.0)
    v.until("survey 1 given up", lambda: v.state(1) == SurveyState.REJECTED)
    assert v.final(1).reason == SurveyReason.AUTONOMY_NO_ANSWER
    v.until("the clearing kept for later", lambda: out._clear_later == 1)
    uploads = out.stats["uploads"]
    with _peer(port) as peer:  # the autopilot starts: cleared, never handed survey 1
        v.until("the mission cleared", lambda: peer.clears == [0])
        for _ in range(100):
            v.step()
            time.sleep(0.01)
        assert peer.counts == [] and out.stats["uploads"] == uploads
    # completed: the mission is cleared once it ended (AUTO would fly it again)
    with _peer(port, fly_interval=0.05) as peer:
        v.ask(2, x=20.0, depth=5.0)
        v.until("survey 2 completed", lambda: v.state(2) == SurveyState.COMPLETED)
        v.until("its mission cleared", lambda: peer.clears == [0] and not peer.mission_held)
        assert peer.counts == [2] and out.stats["cleared"] == 2
    # refused (ArduPilot's uploads are not atomic: part of it may be there): cleared; an autopilot
    # restarted after gets nothing
    with _peer(port, result=14) as peer:
        v.ask(3, x=30.0, depth=5.0)
        v.until("survey 3 refused", lambda: v.state(3) == SurveyState.REJECTED)
        v.until("its mission cleared", lambda: peer.clears == [0])
    with _peer(port) as peer:
        for _ in range(100):
            v.step()
            time.sleep(0.01)
        assert (peer.counts, peer.clears) == ([], [])
    assert [c for c in (v.final(s).reason for s in (1, 2, 3))] == [
        SurveyReason.AUTONOMY_NO_ANSWER, SurveyReason.NONE, SurveyReason.AUTONOMY_REFUSED]


def test_an_autopilot_killed_mid_mission_is_reported_silent_within_the_bound(
        make: Callable[..., MavlinkAutonomy], port: int) -> None:
    """A mavpeer process (stock pymavlink, heartbeats every 0.2 s) flying survey 1 is killed
    (SIGKILL): the survey is ABORTED, AUTONOMY_SILENT, `silence` seconds after its last
    heartbeat; when an autopilot answers on that link again, the aborted mission is cleared and
    nothing is uploaded."""
    from ._lifecycle import Vehicle

    silence = 2.0
    proc = _mavpeer_process(port, "--fly", "60")
    again = None
    try:
        out = make(timeout=0.5, silence=silence)
        v = Vehicle(out, clock=time.monotonic, name="mavlink")
        v.until("the autopilot process heard", lambda: out.heard_at is not None, 60)
        v.ask(1, x=10.0, depth=5.0)
        v.until("survey 1 started", lambda: v.state(1) == SurveyState.STARTED, 30)
        v.until("heartbeats heard", lambda: time.monotonic() - out.heard_at < 0.5)
        proc.kill()
        killed = time.monotonic()
        proc.wait(10)
        v.until("survey 1 aborted", lambda: v.state(1) == SurveyState.ABORTED, 30)
        took = time.monotonic() - killed
        r = v.final(1)
        assert (r.reason, r.detail) == (SurveyReason.AUTONOMY_SILENT, "no HEARTBEAT from 1/1"), r
        # the bound, plus what a loaded machine adds to the test's own polling
        assert silence <= r.value < silence + 5.0 and took < silence + 5.0, (r.value, took)
        print(f"autopilot killed: survey aborted {took:.2f} s later (silence {silence:g} s)")
        again = _mavpeer_process(port)
        lines = _lines(again)
        v.until("the aborted mission cleared on the restarted autopilot", lambda: any(ln.get("clear") for ln in lines))
        for _ in range(50):
            v.step()
            time.sleep(0.01)
        assert [ln for ln in lines if not ln.get("clear")] == []  # nothing uploaded
        assert v.state(1) == SurveyState.ABORTED
    finally:
        for p in (proc, again):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(10)

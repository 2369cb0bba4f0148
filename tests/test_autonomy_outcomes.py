"""A refused mission and a silent autopilot told apart, end to end: ``coex vehicle`` and ``coex
topside --config`` in one process over a MAVLink (UDP) link, the vehicle's ``mavlink`` autonomy
output uploading each accepted survey to a mission-protocol peer built from stock pymavlink
(:class:`~coex_plugins.autonomy.mavpeer.MissionPeer`). The peer refuses one mission
with ``MAV_MISSION_DENIED``, stays silent for the next, then flies a third: topside (the survey
receiver's records, the console's state and its HTTP ``/api/state``) shows the code and its
name for the first, "no answer" with the tries for the second (not a refusal), and the third
completed; a fourth, whose autopilot dies while flying it, "autopilot silent"."""

from __future__ import annotations

import json
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pymavlink")

from coex_apps.console.cli import TopsideApp, topside_from_config
from coex_apps.vehicle.config import load
from coex_apps.vehicle.daemon import VehicleApp
from coex_plugins.autonomy.mavpeer import MissionPeer
from coex_transports.testing import free_port as _free_udp_port

KEY = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"
COMMON = """
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 1.0
guard = 0.1
"""
VEHICLE = """
[node]
role = "vehicle"
id = 2
command_key_file = "k.key"
store = false
[modalities.survey]
stream = 7
priority = 90
options = {{ geofence = {{ radius = 300.0 }} }}
[[modems]]
uri = "mavlink:udpout:127.0.0.1:{link}?sysid=2&compid=191"
packet_seconds = 0.2
[autonomy]
type = "mavlink"
connection = "udpout:127.0.0.1:{autopilot}"
source_component = 192
timeout = 0.3
item_timeout = 0.1
retries = 2
heartbeat = 0.2
silence = 1.5
""" + COMMON
TOPSIDE = """
[node]
role = "topside"
id = 1
command_key_file = "k.key"
store = false
[modalities.survey]
stream = 7
[console]
http = "127.0.0.1:0"
[[modems]]
uri = "mavlink:udpin:127.0.0.1:{link}?sysid=1&compid=190"
packet_seconds = 0.2
""" + COMMON


def _wait(what: str, cond: Callable[[], Any], timeout: float = 60.0) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = cond()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def pair(tmp_path: Path) -> Iterator[tuple[VehicleApp, TopsideApp, MissionPeer]]:
    link, autopilot = _free_udp_port(), _free_udp_port()
    (tmp_path / "k.key").write_text(KEY)
    (tmp_path / "v.toml").write_text(VEHICLE.format(link=link, autopilot=autopilot))
    (tmp_path / "t.toml").write_text(TOPSIDE.format(link=link))
    peer = MissionPeer(f"udpin:127.0.0.1:{autopilot}", heartbeat=0.2)
    peer.start()
    vehicle = topside = None
    try:
        vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
        topside = topside_from_config(str(tmp_path / "t.toml")).start()
        yield vehicle, topside, peer
    finally:
        if vehicle is not None:
            vehicle.close()
        if topside is not None:
            topside.close()
        peer.close()


def _row(topside: TopsideApp, survey_id: int) -> dict[str, Any]:
    """The survey's row as the console's page gets it, over HTTP."""
    with urllib.request.urlopen(f"{topside.url}/api/state", timeout=10) as r:
        state = json.loads(r.read())
    [row] = [i for i in state["surveys"]["items"] if i["survey_id"] == survey_id]
    return row  # type: ignore[no-any-return]


def test_a_refusal_and_a_silent_autopilot_read_apart_topside(
        pair: tuple[VehicleApp, TopsideApp, MissionPeer]) -> None:
    vehicle, topside, peer = pair
    rx = topside.node.receiver("survey")

    def ask(x: float) -> int:
        with topside.hub.lock:
            cmd = rx.request("line", x, 0.0, time.time(), heading=0.0, length=30.0, depth=10.0)
        return int(cmd.survey_id)

    def ended(sid: int) -> Callable[[], bool]:
        return lambda: rx.surveys[sid].state in ("rejected", "aborted", "completed", "given up")

    # 1. the autopilot refuses the mission: MAV_MISSION_DENIED (14)
    peer.result = 14
    refused = ask(0.0)
    _wait("the refusal topside", ended(refused))
    rec = rx.surveys[refused]
    assert (rec.state, rec.reason) == ("rejected", "AUTONOMY_REFUSED")
    assert rec.text == "the vehicle's autonomy refused it (code 14): MAV_MISSION_DENIED"
    row = _row(topside, refused)
    assert (row["state"], row["outcome"]) == ("rejected", "refused by autonomy")
    assert "code 14" in row["text"] and "MAV_MISSION_DENIED" in row["text"]
    assert peer.acks_sent[0] == 14  # then 0: the ended survey's mission cleared (MISSION_CLEAR_ALL)
    _wait("the refused survey's mission cleared", lambda: peer.clears == [0])

    # 2. the autopilot falls silent: given up after 1 + retries tries, as no answer
    with peer._lock:
        peer.silent, peer.result = True, 0
    counts = len(peer.counts)
    silent = ask(10.0)
    _wait("no answer topside", ended(silent))
    rec = rx.surveys[silent]
    assert (rec.state, rec.reason) == ("rejected", "AUTONOMY_NO_ANSWER")
    assert rec.text.startswith("no answer from the vehicle's autonomy (after 3 tries): MISSION_COUNT unanswered")
    assert "refused" not in rec.text
    row = _row(topside, silent)
    assert (row["state"], row["outcome"]) == ("rejected", "no answer from autonomy")
    assert len(peer.counts) - counts == 3  # MISSION_COUNT sent 3 times, never answered

    # 3. the autopilot answers again and flies the next one
    with peer._lock:
        peer.silent, peer.fly_interval = False, 0.1
    flown = ask(20.0)
    _wait("the third survey completed", ended(flown))
    assert rx.surveys[flown].state == "completed" and _row(topside, flown)["outcome"] == "completed"

    # 4. the autopilot dies while it flies the next one: aborted, autopilot silent, told topside
    with peer._lock:
        peer.fly_interval = 60.0
    dying = ask(30.0)
    _wait("the fourth survey started topside", lambda: rx.surveys[dying].state == "started")
    peer.close()  # no more heartbeats, no more answers
    _wait("the fourth survey ended topside", ended(dying))
    rec = rx.surveys[dying]
    assert (rec.state, rec.reason) == ("aborted", "AUTONOMY_SILENT")
    assert rec.text.startswith("autopilot silent for ") and rec.text.endswith(": no HEARTBEAT from 1/1"), rec.text
    assert _row(topside, dying)["outcome"] == "autopilot silent"

    # the console's event log says each in words, and the vehicle's summary counts the plans
    log = [e["text"] for e in topside.hub.snapshot()["log"]]
    assert any(f"survey {refused} refused by autonomy" in t and "MAV_MISSION_DENIED" in t for t in log), log
    assert any(f"survey {silent} no answer from autonomy" in t and "after 3 tries" in t for t in log), log
    assert any(f"survey {dying} autopilot silent" in t for t in log), log
    assert vehicle.counts["plans"] == 4


def test_a_completed_survey_is_never_uploaded_again_whatever_restarts(tmp_path: Path) -> None:
    """Issue 51, with the vehicle daemon's store: a survey flown to its end leaves the autopilot's
    mission cleared; the daemon restarted afterwards uploads nothing and clears nothing again; one
    restarted before it could tell the output the survey ended (a crash between the two) clears it
    at start; the autopilot restarted meanwhile (a new peer) is handed nothing."""
    link, autopilot = _free_udp_port(), _free_udp_port()
    (tmp_path / "k.key").write_text(KEY)
    (tmp_path / "v.toml").write_text(VEHICLE.format(link=link, autopilot=autopilot)
                                     .replace("store = false", 'store = "vehicle.sqlite"'))
    (tmp_path / "t.toml").write_text(TOPSIDE.format(link=link))
    peer = MissionPeer(f"udpin:127.0.0.1:{autopilot}", heartbeat=0.2, fly_interval=0.1)
    peer.start()
    vehicle = topside = again = None
    try:
        vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
        topside = topside_from_config(str(tmp_path / "t.toml")).start()
        rx = topside.node.receiver("survey")
        with topside.hub.lock:
            sid = int(rx.request("line", 0.0, 0.0, time.time(), heading=0.0, length=30.0, depth=10.0).survey_id)
        _wait("the survey completed topside", lambda: rx.surveys[sid].state == "completed")
        _wait("its mission cleared", lambda: peer.clears == [0] and not peer.mission_held)
        vehicle.close()
        vehicle = None
        assert peer.counts == [3]
        # restarted after the end: nothing uploaded, nothing cleared again
        again = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
        _wait("the restarted vehicle polling", lambda: again.lifecycle is not None and not again.lifecycle._first)
        time.sleep(1.5)
        assert (peer.counts, peer.clears, again.counts["plans"]) == ([3], [0], 0)
        again.close()
        # restarted as if the end had not reached the output: a new autopilot is cleared, nothing more
        peer.close()
        peer = MissionPeer(f"udpin:127.0.0.1:{autopilot}", heartbeat=0.2)
        peer.start()
        again = VehicleApp(load(tmp_path / "v.toml", "vehicle"))
        assert again.lifecycle.ended_key == again.lifecycle.submitted
        again.lifecycle.ended_key = None  # the store as a crash between the report and the end leaves it
        again.start()
        _wait("the ended survey's mission cleared at start", lambda: peer.clears == [0])
        time.sleep(1.0)
        assert peer.counts == [] and again.counts["plans"] == 0
        assert again.node.sender("survey").state_of(sid).name == "COMPLETED"
    finally:
        for app in (vehicle, again, topside):
            if app is not None:
                app.close()
        peer.close()

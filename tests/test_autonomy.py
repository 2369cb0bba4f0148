"""Autonomy outputs: registration, ``log``, ``sim`` and ``lcm`` (the ``mavlink`` output is in
test_autonomy_mavlink.py)."""

from __future__ import annotations

import json
import logging
import math
import re
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from coex import InputContext
from coex_core import registry
from coex_core.errors import ConfigError
from coex_core.messages import SurveyKind, SurveyReason, SurveyState
from coex_plugins.autonomy import DEFAULT, GROUP, Autonomy, open_autonomy
from coex_plugins.autonomy.log import LogAutonomy
from coex_plugins.autonomy.sim import SimAutonomy
from coex_plugins.survey.plan import SurveyPlan, SurveyReport

ROOT = Path(__file__).resolve().parents[1]
CTX = InputContext(origin_lat=41.5, origin_lon=-70.7)


def _entry_points() -> dict[str, str]:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return dict(data["project"]["entry-points"][GROUP])


def _plan(sid: int = 7, pts: tuple[tuple[float, float], ...] = ((10.0, 0.0), (10.0, 10.0), (0.0, 10.0)),
          **kw: object) -> SurveyPlan:
    return SurveyPlan(sid, kw.pop("kind", SurveyKind.WAYPOINTS), pts, **kw)  # type: ignore[arg-type]


# ------------------------------------------------------------------ registration
def test_every_output_is_registered_under_its_name() -> None:
    eps = _entry_points()
    assert set(eps) == {"log", "sim", "mavlink", "lcm", "moos", "ros"} and DEFAULT == "log"
    assert eps["mavlink"].endswith("[mavlink]") and eps["lcm"].endswith("[lcm]")
    for name, value in eps.items():
        cls = metadata.EntryPoint(name, value, GROUP).load()
        assert issubclass(cls, Autonomy) and cls.name == name


def test_open_autonomy_builds_the_named_output(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    eps = {n: metadata.EntryPoint(n, v, GROUP) for n, v in _entry_points().items()}
    real = registry._entry_points
    monkeypatch.setattr(registry, "_entry_points", lambda group: eps if group == GROUP else real(group))
    assert isinstance(open_autonomy(None, CTX), LogAutonomy)  # the default
    sim = open_autonomy({"type": "sim", "speed": 2.0}, CTX)
    assert isinstance(sim, SimAutonomy) and sim.config["speed"] == 2.0
    with pytest.raises(ConfigError, match="unknown option 'sped'"):
        open_autonomy({"type": "sim", "sped": 2.0}, CTX)
    with pytest.raises(ConfigError, match="needs option 'connection'"):
        open_autonomy({"type": "mavlink"}, CTX)
    with pytest.raises(Exception, match=r"no coex\.autonomy plugin named 'dune'"):
        open_autonomy({"type": "dune"}, CTX)


# ------------------------------------------------------------------ log
def test_log_says_the_plan_in_words_and_reports_nothing(caplog: pytest.LogCaptureFixture) -> None:
    out = LogAutonomy({}, CTX)
    with caplog.at_level(logging.INFO, logger="coex_plugins.autonomy.log"):
        out.submit(_plan(kind=SurveyKind.LAWNMOWER, altitude=5.0, speed=1.5), 100.0)
        out.submit(_plan(8, ((3.0, 4.0),), kind=SurveyKind.GOTO, depth=20.0), 101.0)
    assert out.poll(200.0) == []
    first, second = (r.getMessage() for r in caplog.records)
    assert "survey 7 (LAWNMOWER): 3 waypoints (10, 0) (10, 10) (0, 10) at 5 m altitude, 1.5 m/s" in first
    assert "survey 8 (GOTO): 1 waypoint (3, 4) at 20 m depth, the vehicle's own speed" in second


def test_log_appends_one_json_line_per_plan(tmp_path: Path) -> None:
    out = LogAutonomy({"file": "plans.jsonl"}, InputContext(41.5, -70.7, base_dir=str(tmp_path)))
    out.submit(_plan(altitude=5.0), 100.0)
    out.submit(_plan(9, kind=SurveyKind.LINE, depth=12.0, speed=0.8), 110.0)
    lines = (tmp_path / "plans.jsonl").read_text().splitlines()
    assert len(lines) == 2
    a, b = (json.loads(line) for line in lines)
    assert (a["survey_id"], a["kind"], a["altitude"], a["depth"], a["speed"], a["time"]) == (7, "WAYPOINTS", 5.0, None,
                                                                                             None, 100.0)
    assert a["waypoints"] == [[10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]
    assert a["latlon"][0] == pytest.approx(list(CTX.geodetic(10.0, 0.0)))
    assert (b["survey_id"], b["kind"], b["depth"], b["speed"]) == (9, "LINE", 12.0, 0.8)
    out.end(9, 120.0)  # its ended form: a script following the file stops flying it
    assert json.loads((tmp_path / "plans.jsonl").read_text().splitlines()[-1]) == {
        "time": 120.0, "survey_id": 9, "ended": True}


def test_log_checks_its_file_option() -> None:
    with pytest.raises(ConfigError, match="file must be a path"):
        LogAutonomy({"file": 3}, CTX)


# ------------------------------------------------------------------ sim
def test_sim_flies_the_plan_and_reports_each_waypoint_when_reached() -> None:
    sim = SimAutonomy({"speed": 2.0}, CTX)
    sim.submit(_plan(), 100.0)  # legs of 10 m at 2 m/s: 5 s each
    assert sim.poll(100.0) == [SurveyReport(7, SurveyState.STARTED, 100.0, index=0)]
    assert sim.position(102.5) == pytest.approx((5.0, 0.0)) and sim.heading(102.5) == pytest.approx(90.0)
    assert sim.poll(104.9) == []
    assert sim.poll(107.0) == [SurveyReport(7, SurveyState.STARTED, 105.0, index=1)]
    assert sim.position(107.0) == pytest.approx((10.0, 4.0)) and sim.heading(107.0) == pytest.approx(0.0)
    assert sim.poll(130.0) == [SurveyReport(7, SurveyState.STARTED, 110.0, index=2),
                               SurveyReport(7, SurveyState.COMPLETED, 115.0)]
    assert sim.position(200.0) == (0.0, 10.0) and sim.heading(200.0) is None
    assert sim.poll(300.0) == [] and sim.active(300.0) is None


def test_sim_uses_the_plans_speed_and_its_start() -> None:
    sim = SimAutonomy({"start": [-5, 0]}, CTX)
    assert sim.position(0.0) == (-5.0, 0.0)
    sim.submit(_plan(1, ((5.0, 0.0),), kind=SurveyKind.GOTO, speed=0.5), 0.0)  # 10 m at 0.5 m/s
    assert sim.active(10.0) == 1
    assert sim.poll(19.0) == [SurveyReport(1, SurveyState.STARTED, 0.0, index=0)]
    assert sim.poll(20.0) == [SurveyReport(1, SurveyState.COMPLETED, 20.0)]


def test_sim_flies_a_newer_plan_from_where_it_is_without_aborting_anything() -> None:
    sim = SimAutonomy({}, CTX)  # 1 m/s from the origin
    sim.submit(_plan(1, ((10.0, 0.0), (20.0, 0.0))), 0.0)
    sim.submit(_plan(2, ((4.0, 3.0),)), 12.0)  # passed waypoint 0 at t=10, at (12, 0) now
    assert sim.poll(12.0) == [SurveyReport(1, SurveyState.STARTED, 0.0, index=0),
                              SurveyReport(1, SurveyState.STARTED, 10.0, index=1),
                              SurveyReport(2, SurveyState.STARTED, 12.0, index=0)]
    assert sim.position(12.0) == pytest.approx((12.0, 0.0))
    d = math.hypot(12.0 - 4.0, 0.0 - 3.0)
    assert sim.poll(12.0 + d) == [SurveyReport(2, SurveyState.COMPLETED, pytest.approx(12.0 + d))]  # type: ignore[arg-type]
    assert [p.survey_id for p in sim.plans] == [1, 2]


def test_sim_handles_repeated_points_and_a_clock_going_back() -> None:
    sim = SimAutonomy({}, CTX)
    sim.submit(_plan(3, ((0.0, 0.0), (0.0, 0.0), (0.0, 2.0))), 5.0)
    assert [r.index for r in sim.poll(5.0)] == [0, 1, 2]
    assert sim.poll(4.0) == [] and sim.position(4.0) == (0.0, 0.0)
    assert sim.poll(7.0) == [SurveyReport(3, SurveyState.COMPLETED, 7.0)]


@pytest.mark.parametrize("options", [{"speed": 0}, {"speed": "fast"}, {"start": [1]}, {"start": "here"}])
def test_sim_refuses_bad_options(options: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match="autonomy 'sim'"):
        SimAutonomy(options, CTX)


# ------------------------------------------------------------------ lcm
lcm = pytest.importorskip("lcm")

from coex_plugins.autonomy.lcm import LcmAutonomy  # noqa: E402
from coex_transports.lcm._types.survey_request_t import survey_request_t  # noqa: E402
from coex_transports.lcm._types.survey_state_t import survey_state_t  # noqa: E402
from coex_transports.lcm.testing import TEST_UDPM_URL, udpm_works, unique_channel  # noqa: E402


class Planner:
    """The vehicle planner's side: reads requests, answers with states."""

    def __init__(self, lc: lcm.LCM, channel: str, state_channel: str) -> None:
        self.lc, self.state_channel = lc, state_channel
        self.requests: list[survey_request_t] = []
        lc.subscribe(re.escape(channel), lambda _c, data: self.requests.append(survey_request_t.decode(data)))

    def answer(self, survey_id: int, state: int, index: int = -1) -> None:
        msg = survey_state_t()
        msg.utime, msg.survey_id, msg.state, msg.index = 1, survey_id, state, index
        self.lc.publish(self.state_channel, msg.encode())


def _lcm_pair(url: str = "memq://") -> tuple[LcmAutonomy, Planner, lcm.LCM]:
    channel, state = unique_channel("REQ"), unique_channel("STATE")
    lc = lcm.LCM(url)
    out = LcmAutonomy({"url": url, "channel": channel, "state_channel": state}, CTX, instance=lc)
    out.open()
    return out, Planner(lc, channel, state), lc


def test_lcm_publishes_a_survey_request_with_local_and_geodetic_waypoints() -> None:
    out, planner, _lc = _lcm_pair()
    out.submit(_plan(kind=SurveyKind.LAWNMOWER, altitude=5.0, speed=1.5), 1_700_000_000.25)
    out.submit(_plan(8, ((3.0, 4.0),), kind=SurveyKind.GOTO, depth=20.0), 1_700_000_001.0)
    assert out.poll(1.0) == []
    assert len(planner.requests) == 2
    a, b = planner.requests
    assert (a.utime, a.survey_id, a.kind, a.n) == (1_700_000_000_250_000, 7, 2, 3)
    assert list(a.x) == [10.0, 10.0, 0.0] and list(a.y) == [0.0, 10.0, 10.0]
    for i, (x, y) in enumerate(((10.0, 0.0), (10.0, 10.0), (0.0, 10.0))):
        assert (a.lat[i], a.lon[i]) == pytest.approx(CTX.geodetic(x, y), abs=1e-12)
    assert a.altitude == 5.0 and math.isnan(a.depth) and a.speed == 1.5
    assert (b.kind, b.n, b.depth) == (0, 1, 20.0) and math.isnan(b.altitude) and math.isnan(b.speed)


def test_lcm_turns_the_planners_answers_into_reports() -> None:
    out, planner, _lc = _lcm_pair()
    out.submit(_plan(), 0.0)
    planner.answer(7, 2, 0)
    planner.answer(7, 2, 1)
    planner.answer(7, 3)
    planner.answer(8, 1)
    planner.answer(9, 4)
    assert out.poll(50.0) == [
        SurveyReport(7, SurveyState.STARTED, 50.0, index=0),
        SurveyReport(7, SurveyState.STARTED, 50.0, index=1),
        SurveyReport(7, SurveyState.COMPLETED, 50.0),
        SurveyReport(8, SurveyState.REJECTED, 50.0, SurveyReason.AUTONOMY_REFUSED),
        SurveyReport(9, SurveyState.ABORTED, 50.0, SurveyReason.AUTONOMY_STOPPED),
    ]
    assert out.poll(51.0) == []


def test_lcm_drops_garbage_and_unknown_states() -> None:
    out, planner, lc = _lcm_pair()
    lc.publish(planner.state_channel, b"not an lcm message")
    lc.publish(planner.state_channel, _plan_request_bytes())
    planner.answer(7, 9)  # no such state
    planner.answer(7, 0)  # RECEIVED: an answer, but nothing to report (ACCEPTED is the survey sender's)
    planner.answer(7, 2, 2)
    assert out.poll(1.0) == [SurveyReport(7, SurveyState.STARTED, 1.0, index=2)]
    assert out.stats["bad"] == 3 and out.stats["received"] == 2


def test_lcm_maps_override_all_stop_restart_and_the_planners_codes() -> None:
    out, planner, _lc = _lcm_pair()
    planner.answer(1, 1, 42)  # refused, with the planner's code
    planner.answer(2, 4, 7)
    planner.answer(3, 5)
    planner.answer(4, 6)
    planner.answer(5, 7)
    planner.answer(6, 2, -1)  # started, no index: heading for waypoint 0
    assert out.poll(9.0) == [
        SurveyReport(1, SurveyState.REJECTED, 9.0, SurveyReason.AUTONOMY_REFUSED, None, 42.0),
        SurveyReport(2, SurveyState.ABORTED, 9.0, SurveyReason.AUTONOMY_STOPPED, None, 7.0),
        SurveyReport(3, SurveyState.ABORTED, 9.0, SurveyReason.MANUAL_OVERRIDE),
        SurveyReport(4, SurveyState.ABORTED, 9.0, SurveyReason.ALL_STOP),
        SurveyReport(5, SurveyState.ABORTED, 9.0, SurveyReason.AUTONOMY_RESTARTED),
        SurveyReport(6, SurveyState.STARTED, 9.0, index=0),
    ]


def test_lcm_a_silent_planner_gets_the_request_again_then_no_answer() -> None:
    """No answer within answer_timeout: the same request again, ``retries`` times; then
    REJECTED AUTONOMY_NO_ANSWER with the tries made (not AUTONOMY_REFUSED)."""
    out, planner, lc = _lcm_pair()
    out.config.update(answer_timeout=2.0, retries=2)
    out.submit(_plan(), 100.0)
    assert out.poll(101.9) == [] and len(planner.requests) == 1
    assert out.poll(102.0) == [] and out.poll(104.0) == []
    [r] = out.poll(106.0)
    assert len(planner.requests) == 3 and {bytes(q.encode()) for q in planner.requests} == {
        bytes(planner.requests[0].encode())}  # the same request, the same utime
    assert (r.survey_id, r.state, r.time, r.reason, r.value) == (
        7, SurveyState.REJECTED, 106.0, SurveyReason.AUTONOMY_NO_ANSWER, 3.0)
    assert r.detail == f"no survey_state_t on {planner.state_channel}"[:48]
    assert out.poll(500.0) == [] and len(planner.requests) == 3
    # a planner that answers (even only "received") is waited for no longer
    out.submit(_plan(8), 600.0)
    planner.answer(8, 0)
    assert out.poll(601.0) == [] and out.poll(700.0) == [] and out.poll(701.0) == []
    assert len(planner.requests) == 4
    # answer_timeout 0: nothing is waited for
    out.config["answer_timeout"] = 0.0
    out.submit(_plan(9), 800.0)
    assert out.poll(10_000.0) == []
    assert lc is planner.lc


def _plan_request_bytes() -> bytes:
    msg = survey_request_t()
    msg.n, msg.x, msg.y, msg.lat, msg.lon = 0, [], [], [], []
    return bytes(msg.encode())


def test_lcm_over_udp_multicast() -> None:
    if not udpm_works(TEST_UDPM_URL):
        pytest.skip("no multicast route on this host (see coex_transports.lcm.testing)")
    channel, state = unique_channel("REQ"), unique_channel("STATE")
    out = LcmAutonomy({"url": TEST_UDPM_URL, "channel": channel, "state_channel": state}, CTX)
    out.open()
    planner = Planner(lcm.LCM(TEST_UDPM_URL), channel, state)
    out.submit(_plan(), 0.0)
    while not planner.requests:
        assert planner.lc.handle_timeout(2000) > 0, "the request never arrived"
    planner.answer(7, 3)
    got: list[SurveyReport] = []
    for _ in range(200):
        got += out.poll(2.0)
        if got:
            break
        planner.lc.handle_timeout(10)
    assert got == [SurveyReport(7, SurveyState.COMPLETED, 2.0)]
    out.close()


def test_lcm_checks_its_options() -> None:
    with pytest.raises(ConfigError, match="channel is longer"):
        LcmAutonomy({"channel": "X" * 64}, CTX)
    with pytest.raises(ConfigError, match="state_channel must be a non-empty string"):
        LcmAutonomy({"state_channel": ""}, CTX)
    with pytest.raises(ConfigError, match="answer_timeout: -1 is below 0 s"):
        LcmAutonomy({"answer_timeout": -1}, CTX)
    with pytest.raises(ConfigError, match=r"retries: not an integer, got 1\.5"):
        LcmAutonomy({"retries": 1.5}, CTX)
    with pytest.raises(ConfigError, match="silence: not a finite number, got nan"):
        LcmAutonomy({"silence": float("nan")}, CTX)


def test_lcm_an_ended_survey_is_never_handed_to_a_planner_started_later() -> None:
    """Through the daemon's survey lifecycle (tests/_lifecycle.py): after a survey ended (no
    answer, completed, refused) the request is never published again; its ended form (the same
    survey_id, n = 0) goes out once; a planner started later gets nothing of it; an answer after
    the end is recorded in the survey's record; a planner that falls silent mid-survey aborts it
    AUTONOMY_SILENT after `silence` (its repeated state is its heartbeat)."""
    from ._lifecycle import Vehicle

    channel, state = unique_channel("REQ"), unique_channel("STATE")
    lc = lcm.LCM("memq://")
    out = LcmAutonomy({"url": "memq://", "channel": channel, "state_channel": state, "answer_timeout": 2.0,
                       "retries": 1, "silence": 5.0}, CTX, instance=lc)
    out.open()
    clock = [1000.0]
    v = Vehicle(out, clock=lambda: clock[0], name="lcm")

    def run(seconds: float) -> None:
        end = clock[0] + seconds
        while clock[0] < end:
            clock[0] += 0.5
            v.step()

    sent: list[survey_request_t] = []
    lc.subscribe(re.escape(channel), lambda _c, data: sent.append(survey_request_t.decode(data)))
    # 1. nobody answers: published twice, given up, then its ended form, and nothing more
    v.ask(1, clock[0], depth=5.0)
    run(10.0)
    assert v.state(1) == SurveyState.REJECTED and v.final(1).reason == SurveyReason.AUTONOMY_NO_ANSWER
    assert [(q.survey_id, q.n) for q in sent] == [(1, 1), (1, 1), (1, 0)]
    planner = Planner(lc, channel, state)  # a planner that starts now
    run(60.0)
    assert planner.requests == []
    # 2. completed: its ended form once it ended
    v.ask(2, clock[0], depth=5.0)
    run(0.5)
    planner.answer(2, 2, 0)
    run(1.0)
    planner.answer(2, 3)
    run(1.0)
    assert v.state(2) == SurveyState.COMPLETED
    assert [(q.survey_id, q.n) for q in planner.requests] == [(2, 1), (2, 0)]
    # 3. refused: likewise; an answer after the end is recorded, and the survey taken back again
    v.ask(3, clock[0], depth=5.0)
    run(0.5)
    planner.answer(3, 1, 42)
    run(1.0)
    assert v.state(3) == SurveyState.REJECTED and v.final(3).value == 42.0
    planner.answer(3, 2, 0)  # late: the planner flies it all the same
    run(1.0)
    assert v.state(3) == SurveyState.REJECTED and v.sender.late(3)[0][1:3] == ("STARTED", 0)
    assert [(q.survey_id, q.n) for q in planner.requests][2:] == [(3, 1), (3, 0)]  # ended 1 s ago
    run(10.0)
    planner.answer(3, 2, 1)  # still flying it: taken back again
    run(1.0)
    assert [(q.survey_id, q.n) for q in planner.requests][2:] == [(3, 1), (3, 0), (3, 0)]
    run(60.0)
    assert len(planner.requests) == 5  # nothing published again
    # 4. a planner that repeats its state is alive; one that falls silent aborts the survey
    v.ask(4, clock[0], depth=5.0)
    run(0.5)
    for _ in range(8):
        planner.answer(4, 2, 0)
        run(3.0)
    assert v.state(4) == SurveyState.STARTED
    run(6.0)
    r = v.final(4)
    assert (r.state, r.reason, r.detail) == (SurveyState.ABORTED, SurveyReason.AUTONOMY_SILENT,
                                             f"no survey_state_t on {state}"[:48])
    assert 5.0 < r.value <= 6.0
    assert [(q.survey_id, q.n) for q in planner.requests][-1] == (4, 0)
    out.close()

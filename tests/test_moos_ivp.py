"""The MOOS-IvP autonomy path against a real helm (issue 38): pHelmIvP, uSimMarineV22 and
pMarinePIDV22 built from the moos-ivp sources, pCoex (``coex vehicle --moos``) run from
``examples/moos/`` with the shipped ``coex.bhv``, and a topside CoEx node (the survey receiver)
on the same MOOSDB with ``tx``/``rx`` swapped, at a MOOS time warp.

Surveys requested topside are flown by the simulated vehicle: its track passes each waypoint,
and topside sees requested -> accepted -> started (each waypoint) -> completed; the same survey
again is flown again; a survey outside the geofence is refused by the vehicle; one the helm
refuses is rejected with the helm's words and never flown; a manual override, an all-stop and
a helm restart (SIGKILL, started again) end the survey flown with their reasons; every ended
survey leaves its ended form in MOOSDB, so a helm started later flies none of them; a helm killed
while flying (not restarted) is reported "autopilot silent" within the output's `silence`. The
assertions are on what happened, never on how long it took (but for that bound); every wait is
bounded."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ._moos_ivp import Community, Watcher, find_ivp, wait

pytestmark = pytest.mark.slow

WARP = 8.0
#: the shipped coex.bhv's capture radius (metres): a waypoint is reached within it
CAPTURE = 5.0
#: the pCoex lines the test adds: a fast TDMA (MOOS carries frames instantly), status every
#: second, and the depth behaviour's updates variable given as an altitude behaviour's too, so
#: the helm refuses surveys that give an altitude (BHV_ConstantDepth has no `altitude`)
EXTRA = [
    'tdma.slots = ["topside", "vehicle"]',
    "tdma.slot_seconds = 0.5",
    "tdma.guard = 0.05",
    "modems[0].packet_seconds = 0.3",
    "status.interval = 1",
    "autonomy.altitude_var = COEX_DEPTH_UPDATE",
    "autonomy.silence = 4",
]
SILENCE = 4.0
TOPSIDE = """
[node]
role = "topside"
id = 1
peer = 2
command_key_file = "../deploy/coex-example.key"
store = false
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 0.5
guard = 0.05
[[modems]]
uri = "moos://127.0.0.1:{port}?name=pCoexTop&tx=COEX_RX&rx=COEX_TX&warp={warp}"
rate = 5
packet_seconds = 0.3
[modalities.survey]
stream = 7
[console]
http = "127.0.0.1:0"
"""
WATCHED = ["NAV_X", "NAV_Y", "COEX_SURVEY", "COEX_WPT_UPDATE", "COEX_DEPTH_UPDATE", "WPT_INDEX", "IVPHELM_STATE",
           "IVPHELM_ALLSTOP", "IVPHELM_UPDATE_RESULT", "BHV_WARNING", "DESIRED_SPEED", "MOOS_MANUAL_OVERRIDE",
           "IVPHELM_BHV_ACTIVE"]


@pytest.fixture(scope="module")
def ivp_bin() -> Path:
    found, why, _ = find_ivp()
    if found is None:
        pytest.skip(why)
    return found


class Topside:
    """The topside node and what its survey receiver went through, in order."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.rx = app.node.receiver("survey")
        self.seen: dict[int, list[tuple[str, int | None, str | None, str]]] = {}
        original = self.rx.receive

        def receive(message: Any, now: float) -> Any:
            out = original(message, now)
            for sid, rec in self.rx.surveys.items():
                step = (rec.state, rec.index if rec.state == "started" else None, rec.reason, rec.text)
                seq = self.seen.setdefault(sid, [("requested", None, None, "")])
                if seq[-1] != step:
                    seq.append(step)
            return out

        self.rx.receive = receive

    def request(self, kind: str, x: float, y: float, **kw: Any) -> int:
        with self.app.hub.lock:
            cmd = self.rx.request(kind, x, y, time.time(), **kw)
        return int(cmd.survey_id)

    def state(self, sid: int) -> str:
        with self.app.hub.lock:
            rec = self.rx.surveys.get(sid)
            return "" if rec is None else str(rec.state)

    def states(self, sid: int) -> list[tuple[str, int | None, str | None, str]]:
        with self.app.hub.lock:
            return list(self.seen.get(sid, []))

    def plan(self, sid: int) -> list[tuple[float, float]]:
        from coex_plugins.survey.plan import plan_of

        with self.app.hub.lock:
            return [tuple(p) for p in plan_of(self.rx.surveys[sid].command).waypoints]  # type: ignore[misc]


@contextlib.contextmanager
def community(ivp_bin: Path, tmp_path: Path) -> Iterator[tuple[Community, Watcher, Topside]]:
    from coex_apps.console.cli import topside_from_config

    c = Community(ivp_bin, tmp_path, WARP, EXTRA)
    watcher = topside = None
    try:
        c.start("MOOSDB")
        watcher = Watcher(c.port, WARP, WATCHED)
        wait("MOOSDB", lambda: watcher.client.connect(0.5), 20, c)
        watcher.start()
        for app in ("uSimMarineV22", "pMarinePIDV22", "pHelmIvP", "pCoex"):
            c.start(app)
        (tmp_path / "moos" / "topside.toml").write_text(TOPSIDE.format(port=c.port, warp=f"{WARP:g}"))
        topside = Topside(topside_from_config(str(tmp_path / "moos" / "topside.toml")).start())
        yield c, watcher, topside
    finally:
        if topside is not None:
            topside.app.close()
        if watcher is not None:
            watcher.close()
        c.close()


def _min_dist(track: list[tuple[float, float]], p: tuple[float, float]) -> float:
    return min((math.hypot(x - p[0], y - p[1]) for x, y in track), default=math.inf)


def _flown(c: Community, w: Watcher, top: Topside, kind: str, x: float, y: float, **kw: Any) -> int:
    """Request a survey topside, wait until it is completed, and check that it was flown: the
    track passes within the capture radius of every waypoint, in order, and topside saw
    requested, accepted, started for each waypoint, completed."""
    t0 = time.monotonic()
    mark = w.track_mark()
    sid = top.request(kind, x, y, **kw)
    wait(f"survey {sid} ({kind}) finished topside", lambda: top.state(sid) in ("completed", "rejected", "aborted"),
         120, c)
    track, plan = w.track_since(mark), top.plan(sid)
    print(f"survey {sid} {kind}: {top.state(sid)} in {time.monotonic() - t0:.1f} s; closest approach to each "
          f"waypoint {[round(_min_dist(track, p), 1) for p in plan]} m")
    # topside hears the newest state in each of the vehicle's slots: a waypoint's "started" may be
    # superseded by the next before it goes (a loaded machine): those that come are in order, and
    # the track below shows every waypoint flown
    seen = top.states(sid)
    assert seen[:2] == [("requested", None, None, ""), ("accepted", None, None, "")], seen
    assert seen[-1] == ("completed", None, None, ""), seen
    started = seen[2:-1]
    assert started and all(st[0] == "started" and st[3] == f"heading for waypoint {st[1]}" for st in started), seen
    assert [st[1] for st in started] == sorted({st[1] for st in started}) and started[0][1] == 0, seen
    with top.app.hub.lock:  # the console's history says the same, in the same order
        assert [h[1:] for h in top.rx.surveys[sid].history] == [(s[0], s[3]) for s in top.states(sid)]
    at = 0
    for k, p in enumerate(plan):  # each waypoint in turn: the first fix within the capture radius
        near = [i for i in range(at, len(track)) if math.hypot(track[i][0] - p[0], track[i][1] - p[1]) <= CAPTURE]
        assert near, f"waypoint {k} {p} not passed within {CAPTURE} m (closest {_min_dist(track[at:], p):.1f} m)"
        at = near[0]
    return sid


def _ended_form(w: Watcher) -> None:
    """The newest COEX_SURVEY and COEX_WPT_UPDATE pCoex posted are the ended form (what MOOSDB
    hands a helm that starts): the behaviour off, an update without points."""
    wait("the ended form posted", lambda: [m[1] for m in w.since(0, "COEX_WPT_UPDATE") if m[2] == "pCoex_helm"][-1:]
         == ["name=coex_survey"], 30)
    assert [m[1] for m in w.since(0, "COEX_SURVEY") if m[2] == "pCoex_helm"][-1:] == ["false"]


def _iterations(w: Watcher, n: int) -> None:
    """Let the helm iterate ``n`` more times (it posts IVPHELM_STATE every iteration)."""
    mark = w.mark()
    wait(f"{n} helm iterations", lambda: len(w.since(mark, "IVPHELM_STATE")) >= n, 60)


def _started(c: Community, top: Topside, kind: str, x: float, y: float, **kw: Any) -> int:
    sid = top.request(kind, x, y, **kw)
    wait(f"survey {sid} started topside", lambda: top.state(sid) == "started", 60, c)
    return sid


def _ended(c: Community, top: Topside, sid: int) -> tuple[str, str | None, str]:
    wait(f"survey {sid} ended topside", lambda: top.state(sid) in ("completed", "rejected", "aborted"), 60, c)
    state, _, reason, text = top.states(sid)[-1]
    print(f"survey {sid}: {top.states(sid)}")
    return state, reason, text


def _not_flown(w: Watcher, mark: int) -> None:
    """Since ``mark`` nothing activated the survey behaviour and it never ran."""
    assert [m for m in w.since(mark, "COEX_SURVEY") if m[1] == "true"] == []
    assert [m for m in w.since(mark, "IVPHELM_BHV_ACTIVE") if "coex_survey" in str(m[1]).split(",")] == []


def test_a_real_helm_flies_surveys_and_coex_reports_every_outcome(ivp_bin: Path, tmp_path: Path) -> None:
    t_start = time.monotonic()
    with community(ivp_bin, tmp_path) as (c, w, top):
        # the vehicle's navigation reaches topside in real seconds (MOOS times are warped)
        wait("the vehicle status topside", lambda: top.app.hub.state.status, 60, c)
        with top.app.hub.lock:
            age = time.time() - top.app.hub.state.status_t
        assert -5 < age < 30, age
        wait("the helm driving", lambda: any(m[1] == "DRIVE" for m in w.since(0, "IVPHELM_STATE")), 30, c)
        print(f"community up in {time.monotonic() - t_start:.1f} s")

        # a line, then the same line again (the helm must not drop it as a duplicate), then a
        # lawnmower: each flown, each waypoint passed, every state seen topside in order
        # (legs of 20 m and more at 1.5 m/s: more than one TDMA cycle each, so that every
        # waypoint's state reaches topside, as the vehicle sends a survey's newest state in each
        # of its slots; at 1.5 m/s the simulated vehicle turns within the capture radius)
        line = dict(heading=180.0, length=24.0, depth=4.0, speed=1.5)  # ahead of the vehicle
        _flown(c, w, top, "line", 0.0, -40.0, **line)
        _flown(c, w, top, "line", 0.0, -40.0, **line)
        _flown(c, w, top, "lawnmower", 15.0, -60.0, heading=90.0, length=30.0, width=30.0, spacing=30.0,
               depth=4.0, speed=1.5)
        # completed: its ended form stays in MOOSDB (the behaviour off, an update without points)
        _ended_form(w)

        # outside the geofence: refused by the vehicle, the helm never hears of it
        mark = w.mark()
        sid = top.request("goto", 900.0, 0.0, depth=4.0)
        state, reason, text = _ended(c, top, sid)
        assert (state, reason) == ("rejected", "OUTSIDE_GEOFENCE"), (state, reason, text)
        assert w.since(mark, "COEX_WPT_UPDATE") == []

        # refused by the helm (a depth behaviour takes no altitude): rejected with the helm's
        # words, the behaviour never activated, the vehicle does not go there
        here = w.where()
        assert here is not None
        target = (here[0] - 60.0, here[1] + 20.0)
        mark = w.mark()
        sid = top.request("goto", target[0], target[1], altitude=5.0)
        state, reason, text = _ended(c, top, sid)
        assert (state, reason) == ("rejected", "AUTONOMY_REFUSED"), (state, reason, text)
        assert "coex_depth: Bad parameter(s): altitude" in text, text
        assert any("result=param_error" in str(m[1]) for m in w.since(mark, "IVPHELM_UPDATE_RESULT"))
        _iterations(w, 40)
        _not_flown(w, mark)
        now = w.where()
        assert now is not None and math.dist(now, target) > math.dist(here, target) - 2.0, (here, now, target)
        assert [m[1] for m in w.since(mark, "COEX_SURVEY")][-1:] == ["false"]
        _ended_form(w)

        # a manual override while flying: aborted, deactivated, not resumed when released
        sid = _started(c, top, "line", 0.0, -100.0, heading=90.0, length=200.0, depth=4.0)
        w.post("MOOS_MANUAL_OVERRIDE", "true")
        state, reason, text = _ended(c, top, sid)
        assert (state, reason) == ("aborted", "MANUAL_OVERRIDE"), (state, reason, text)
        assert "MOOS_MANUAL_OVERRIDE" in text, text
        mark = w.mark()
        w.post("MOOS_MANUAL_OVERRIDE", "false")
        wait("the helm driving again", lambda: any(m[1] == "DRIVE" for m in w.since(mark, "IVPHELM_STATE")), 30, c)
        _iterations(w, 40)
        _not_flown(w, mark)
        assert top.state(sid) == "aborted"

        # the helm killed and started again while flying: aborted, AUTONOMY_RESTARTED
        sid = _started(c, top, "line", 0.0, -100.0, heading=90.0, length=200.0, depth=4.0)
        c.kill("pHelmIvP")
        c.start("pHelmIvP")
        state, reason, text = _ended(c, top, sid)
        assert (state, reason) == ("aborted", "AUTONOMY_RESTARTED"), (state, reason, text)

        # an all-stop while flying (the depth behaviour ends: MissingDecVars:depth): aborted,
        # ALL_STOP, with the helm's reason
        sid = _started(c, top, "line", 0.0, -100.0, heading=90.0, length=200.0, depth=4.0)
        w.post("COEX_DEPTH_UPDATE", "duration=0")
        state, reason, text = _ended(c, top, sid)
        assert (state, reason) == ("aborted", "ALL_STOP"), (state, reason, text)
        assert "MissingDecVars:depth" in text, text
        _ended_form(w)
        # MOOSDB keeps the test's poke too, and a helm that starts reads it: undo it
        w.post("COEX_DEPTH_UPDATE", "duration=no-time-limit")

        # a helm started after the survey ended (killed and started again) is not handed it: it
        # reads the ended form from MOOSDB, never the survey's points, and flies nothing of it
        mark = w.mark()
        c.kill("pHelmIvP")
        c.start("pHelmIvP")
        wait("the new helm driving", lambda: any(m[1] == "DRIVE" for m in w.since(mark, "IVPHELM_STATE")), 60, c)
        _iterations(w, 40)
        _not_flown(w, mark)
        taken = [m[1] for m in w.since(mark, "IVPHELM_UPDATE_RESULT") if "var=COEX_WPT_UPDATE" in str(m[1])]
        assert not any("points=" in t for t in taken), taken
        assert top.state(sid) == "aborted"

        # the helm killed while flying, not restarted: aborted, autopilot silent, within `silence`
        sid = _started(c, top, "line", 0.0, -100.0, heading=90.0, length=200.0, depth=4.0)
        c.kill("pHelmIvP")
        killed = time.monotonic()
        state, reason, text = _ended(c, top, sid)
        took = time.monotonic() - killed
        print(f"helm killed: survey {sid} {state} ({reason}) topside {took:.1f} s later (silence {SILENCE:g} s)")
        assert (state, reason) == ("aborted", "AUTONOMY_SILENT"), (state, reason, text)
        assert text.startswith("autopilot silent for ") and text.endswith(": no IVPHELM_STATE from the helm"), text
        assert took < SILENCE + 10.0, took  # the bound, then a TDMA slot or two to topside
        _ended_form(w)
        c.start("pHelmIvP")
        mark = w.mark()
        wait("the helm driving again", lambda: any(m[1] == "DRIVE" for m in w.since(mark, "IVPHELM_STATE")), 60, c)
        _iterations(w, 40)
        _not_flown(w, mark)
        assert sorted(c.alive()) == sorted(["MOOSDB", "uSimMarineV22", "pMarinePIDV22", "pHelmIvP", "pCoex"])
    print(f"the real-helm test took {time.monotonic() - t_start:.1f} s")


def test_the_example_runs_as_shipped_with_pantler(ivp_bin: Path, tmp_path: Path) -> None:
    """``cd examples/moos && pAntler coex_alpha.moos``: every application starts (pCoex through
    ./pCoex), the helm is released from MOOS_MANUAL_OVERRIDE by coex.bhv and drives, and pCoex's
    three MOOS clients are on the MOOSDB. Only the port differs from the shipped mission."""
    c = Community(ivp_bin, tmp_path, 1.0, [])
    w = None
    try:
        c.antler(ivp_bin)
        w = Watcher(c.port, 1.0, ["IVPHELM_STATE", "MOOS_MANUAL_OVERRIDE", "DB_CLIENTS", "NODE_REPORT_LOCAL"])
        wait("MOOSDB", lambda: w.client.connect(0.5), 30, c)
        w.start()
        wait("the helm driving", lambda: any(m[1] == "DRIVE" for m in w.since(0, "IVPHELM_STATE")), 60, c)
        assert ("MOOS_MANUAL_OVERRIDE", "false", "pHelmIvP", "HELM_VAR_INIT") in w.since(0, "MOOS_MANUAL_OVERRIDE")
        want = {"pCoex_modem", "pCoex_in", "pCoex_helm", "pHelmIvP", "uSimMarineV22", "pMarinePIDV22",
                "pNodeReporter"}
        wait("every application on the MOOSDB", lambda: any(want <= set(str(m[1]).split(","))
                                                            for m in w.since(0, "DB_CLIENTS")), 60, c)
        assert w.since(0, "NODE_REPORT_LOCAL"), "pNodeReporter reports the vehicle"
    finally:
        if w is not None:
            w.close()
        c.close()


def test_without_the_stack_the_tests_say_why(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the binaries are looked for, and the reason given when they cannot be had."""
    from . import _moos_ivp

    monkeypatch.setenv("COEX_MOOS_IVP_BIN", str(tmp_path))
    found, why, built = find_ivp()
    assert found is None and not built and why.startswith(f"COEX_MOOS_IVP_BIN={tmp_path} lacks MOOSDB, pHelmIvP")
    monkeypatch.delenv("COEX_MOOS_IVP_BIN")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # nothing built there
    monkeypatch.setattr(_moos_ivp, "BUILD_SCRIPT", tmp_path / "no" / "build_ivp.sh")
    found, why, _ = find_ivp()
    assert found is None and "no " + str(tmp_path / "no" / "build_ivp.sh") + " to build it from" in why
    monkeypatch.setattr(_moos_ivp, "BUILD_SCRIPT", tmp_path / "build_ivp.sh")
    (tmp_path / "build_ivp.sh").write_text("exit 3\n")
    monkeypatch.setattr(_moos_ivp.shutil, "which", lambda tool: None if tool == "g++" else "/usr/bin/" + tool)
    found, why, _ = find_ivp()
    assert found is None and why.endswith("and g++ missing to build it")

"""The ``moos`` autonomy output's hand-over to the IvP helm and what it reads back, against a
scripted helm (no MOOSDB): what it posts and in which order, and the outcome each helm post
gives. The helm's posts are worded as pHelmIvP words them (HelmIvP.cpp, IvPBehavior.cpp,
BHV_Waypoint.cpp); tests/test_moos_ivp.py checks the same against a real helm."""

from __future__ import annotations

from typing import Any

import pytest

from coex import InputContext
from coex_core.messages import SurveyKind, SurveyReason, SurveyState
from coex_plugins.autonomy.moos import MoosAutonomy, parse_update_result
from coex_plugins.survey.plan import SurveyPlan
from coex_transports.moos import MoosMessage

WPT = "name=coex_survey#points=0,-40:30,-40#speed=1"
LINE = SurveyPlan(3, SurveyKind.LINE, ((0.0, -40.0), (30.0, -40.0)), depth=4.0, speed=1.0)
GOTO = SurveyPlan(4, SurveyKind.GOTO, ((10.0, 10.0),), altitude=5.0)


class FakeClient:
    """A MoosClient stand-in: what the output posts, and mail the test gives it."""

    def __init__(self) -> None:
        self.posts: list[tuple[str, Any]] = []
        self.inbox: list[MoosMessage] = []
        self.connected = True
        self.registered: list[str] = []

    def register(self, var: str, interval: float = 0.0) -> None:
        self.registered.append(var)

    def connect(self, timeout: float | None = 5.0) -> bool:
        return self.connected

    def notify(self, var: str, value: Any, time: float | None = None) -> None:
        self.posts.append((var, value))

    def fetch(self) -> list[MoosMessage]:
        out, self.inbox = self.inbox, []
        return out

    def flush(self, timeout: float | None = 10.0) -> bool:
        return True

    def close(self) -> None:
        pass


class Bench:
    """The output with a fake client, a clock, and a helm that speaks."""

    def __init__(self, **options: Any) -> None:
        self.client = FakeClient()
        self.a = MoosAutonomy({"depth_var": "COEX_DEPTH_UPDATE", **options}, InputContext(), client=self.client)
        self.a.open()
        self.now = 1000.0
        self.helm("IVPHELM_STATE", "DRIVE")

    def helm(self, key: str, value: Any, source: str = "pHelmIvP", aux: str = "") -> None:
        kind = "D" if isinstance(value, float) else "S"
        self.client.inbox.append(MoosMessage(key, value, kind, self.now * 1.0, source, "alpha", aux))

    def result(self, var: str, val: str, result: str = "success", bhv: str = "coex_survey") -> None:
        self.helm("IVPHELM_UPDATE_RESULT", f"bhv={bhv},var={var},time=12.5,result={result},val={val}")

    def poll(self, dt: float = 0.1) -> list[tuple[int, SurveyState, SurveyReason, int | None, str | None]]:
        self.now += dt
        return [(r.survey_id, r.state, r.reason, r.index, r.detail) for r in self.a.poll(self.now)]

    def posts(self) -> list[tuple[str, Any]]:
        out, self.client.posts = self.client.posts, []
        return out

    def take(self, plan: SurveyPlan = LINE) -> None:
        """Submit ``plan`` and answer success to its updates: the output activates it."""
        self.a.submit(plan, self.now)
        for var, val in self.posts()[2:]:
            self.result(var, val, "duplicate" if var == "COEX_DEPTH_UPDATE" else "success")
        assert self.poll() == []
        assert self.posts() == [("COEX_SURVEY", "true")]


def test_an_update_result_is_parsed_whatever_the_update_holds() -> None:
    assert parse_update_result("bhv=coex_survey,var=COEX_WPT_UPDATE,time=641.85,result=success,"
                               "val=name=coex_survey#points=0,-30:40,-30#speed=1.5") == {
        "bhv": "coex_survey", "var": "COEX_WPT_UPDATE", "time": "641.85", "result": "success",
        "val": "name=coex_survey#points=0,-30:40,-30#speed=1.5"}


def test_a_survey_is_activated_only_once_the_helm_took_every_update_then_flown() -> None:
    b = Bench()
    b.helm("WPT_INDEX", 2.0)  # the survey flown before: not this one's
    b.a.submit(LINE, b.now)
    # the behaviour stopped first; a successful update no survey update equals; the survey
    assert b.posts() == [("COEX_SURVEY", "false"), ("COEX_WPT_UPDATE", "name=coex_survey"),
                         ("COEX_WPT_UPDATE", WPT), ("COEX_DEPTH_UPDATE", "depth=4")]
    b.result("COEX_WPT_UPDATE", "name=coex_survey")  # the separator's answer is not the survey's
    b.helm("WPT_INDEX", 0.0)  # the helm iterating before it read the update
    b.result("COEX_WPT_UPDATE", WPT)
    assert b.poll() == [] and b.posts() == []  # the depth update not answered yet
    b.result("COEX_DEPTH_UPDATE", "depth=4", "duplicate", "coex_depth")  # same depth as before: fine
    assert b.poll() == [] and b.posts() == [("COEX_SURVEY", "true")]
    b.helm("WPT_INDEX", 0.0)
    b.helm("WPT_STAT", "vname=alpha,behavior-name=coex_survey,index=0,hits=0/0,cycles=0,dist=10,eta=10")
    b.helm("WPT_STAT", "vname=alpha,behavior-name=other,index=1,hits=0/0,cycles=0,dist=10,eta=10")
    assert b.poll() == [(3, SurveyState.STARTED, SurveyReason.NONE, 0, None)]
    b.helm("IVPHELM_ALLSTOP", "clear")
    b.helm("WPT_INDEX", 1.0)
    b.helm("WPT_STAT", "behavior-name=other,completed")
    assert b.poll() == [(3, SurveyState.STARTED, SurveyReason.NONE, 1, None)]
    b.helm("WPT_STAT", "behavior-name=coex_survey,completed")
    b.helm("COEX_SURVEY", "false", aux="2053:coex_survey")  # its endflag
    b.helm("IVPHELM_ALLSTOP", "MissingDecVars:speed,course")  # the helm between behaviours
    assert b.poll() == [(3, SurveyState.COMPLETED, SurveyReason.NONE, None, None)]
    assert b.posts() == [] and b.poll(60.0) == []  # nothing after the end, no timeout


def test_the_endflag_alone_completes_a_survey() -> None:
    """A behaviour posts WPT_STAT only when it changes: a survey that ends at once (a go-to
    where the vehicle is, after another that completed) gives only the endflag."""
    b = Bench()
    b.take(GOTO)
    b.helm("IVPHELM_BHV_ACTIVE", "coex_survey,coex_depth")
    b.helm("COEX_SURVEY", "false", aux="77:coex_survey")
    assert b.poll() == [(4, SurveyState.STARTED, SurveyReason.NONE, 0, None),
                        (4, SurveyState.COMPLETED, SurveyReason.NONE, None, None)]


@pytest.mark.parametrize("warning", [True, False])
def test_a_refused_update_is_rejected_with_the_helms_words_and_never_flown(warning: bool) -> None:
    b = Bench()
    b.a.submit(LINE, b.now)
    b.posts()
    b.result("COEX_WPT_UPDATE", WPT)
    b.result("COEX_DEPTH_UPDATE", "depth=4", "param_error", "coex_depth")
    b.helm("BHV_WARNING", "Faulty update for behavior: coex_survey. Bad parameter(s): lead")  # not this one
    if warning:  # a second identical warning is never posted (the helm posts changes only)
        b.helm("BHV_WARNING", "Faulty update for behavior: coex_depth. Bad parameter(s): depth")
    assert b.poll() == ([(3, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, None,
                          "coex_depth: Bad parameter(s): depth")] if warning else [])
    # deactivated at once (the helm applied the good parameters), never activated
    assert b.posts()[0] == ("COEX_SURVEY", "false")
    if not warning:
        b.helm("IVPHELM_STATE", "DRIVE")  # the helm's next iteration: no warning came
        assert b.poll() == [(3, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, None,
                             "coex_depth refused COEX_DEPTH_UPDATE")]
    b.helm("WPT_INDEX", 0.0)
    assert b.poll() == [] and ("COEX_SURVEY", "true") not in b.posts()


@pytest.mark.parametrize(("result", "detail"), [
    ("name_mismatch", "COEX_WPT_UPDATE is wpt's, not coex_survey"),
    ("duplicate", "wpt: duplicate (COEX_WPT_UPDATE)"),
])
def test_an_update_the_helm_did_not_apply_is_rejected(result: str, detail: str) -> None:
    b = Bench()
    b.a.submit(LINE, b.now)
    b.posts()
    b.result("COEX_WPT_UPDATE", WPT, result, bhv="wpt")
    assert b.poll() == [(3, SurveyState.REJECTED, SurveyReason.AUTONOMY_REFUSED, None, detail)]
    assert b.posts() == [("COEX_SURVEY", "false")]


def test_a_parked_helm_refuses_and_an_override_aborts() -> None:
    b = Bench()
    b.helm("IVPHELM_STATE", "PARK")  # read before the survey: the state it was in
    b.helm("IVPHELM_STATE", "DRIVE")
    b.a.submit(LINE, b.now)
    b.posts()
    b.helm("IVPHELM_ALLSTOP", "ManualOverride")
    b.helm("IVPHELM_STATE", "PARK")  # parked: the helm discards updates unread
    assert b.poll() == [(3, SurveyState.REJECTED, SurveyReason.MANUAL_OVERRIDE, None, "helm PARK: ManualOverride")]
    assert b.posts() == [("COEX_SURVEY", "false")]
    b.helm("IVPHELM_STATE", "DRIVE")
    b.take()
    b.helm("WPT_INDEX", 0.0)
    b.helm("MOOS_MANUAL_OVERRIDE", "true", source="uPokeDB")
    b.helm("IVPHELM_STATE", "PARK")
    assert b.poll() == [(3, SurveyState.STARTED, SurveyReason.NONE, 0, None),
                        (3, SurveyState.ABORTED, SurveyReason.MANUAL_OVERRIDE, None,
                         "MOOS_MANUAL_OVERRIDE = true (uPokeDB)")]
    assert b.posts() == [("COEX_SURVEY", "false")]  # not resumed when the override ends
    b.helm("MOOS_MANUAL_OVERRIDE", "false", source="uPokeDB")
    assert b.poll() == [] and b.posts() == []


@pytest.mark.parametrize("how", ["pid", "init", "restart_helm"])
def test_a_helm_restart_loses_the_survey(how: str) -> None:
    b = Bench()
    b.take()
    b.helm("WPT_INDEX", 0.0)
    if how == "pid":
        b.helm("PHELMIVP_PID", 4242.0)
    elif how == "init":
        b.helm("COEX_SURVEY", "false", aux="HELM_VAR_INIT")  # `initialize COEX_SURVEY = false`
    else:
        b.helm("IVPHELM_RESTARTED", "true")  # RESTART_HELM
    got = b.poll()
    assert [(r[1], r[2]) for r in got] == [(SurveyState.STARTED, SurveyReason.NONE),
                                           (SurveyState.ABORTED, SurveyReason.AUTONOMY_RESTARTED)]
    assert "restarted" in str(got[1][4])
    assert b.posts() == [("COEX_SURVEY", "false")]
    # during the hand-over: rejected, the restarted helm never took it
    b.a.submit(LINE, b.now)
    b.posts()
    b.helm("PHELMIVP_PID", 4343.0)
    assert [(r[1], r[2]) for r in b.poll()] == [(SurveyState.REJECTED, SurveyReason.AUTONOMY_RESTARTED)]


def test_an_all_stop_counts_once_the_behaviour_ran() -> None:
    b = Bench()
    b.take()
    b.helm("IVPHELM_ALLSTOP", "NothingToDo")  # the helm idle before it read the activation
    assert b.poll() == []
    b.helm("IVPHELM_BHV_ACTIVE", "coex_survey,coex_depth")  # it runs
    b.helm("IVPHELM_ALLSTOP", "clear")
    b.helm("BHV_ERROR", "MissingDecVars:depth")
    b.helm("IVPHELM_ALLSTOP", "MissingDecVars:depth")
    assert b.poll() == [(3, SurveyState.STARTED, SurveyReason.NONE, 0, None),
                        (3, SurveyState.ABORTED, SurveyReason.ALL_STOP, None, "MissingDecVars:depth")]
    assert b.posts() == [("COEX_SURVEY", "false")]


@pytest.mark.parametrize(("mail", "detail"), [
    (("COEX_SURVEY", "false", "uPokeDB", ""), "COEX_SURVEY = false by uPokeDB"),
    (("COEX_SURVEY", "false", "pHelmIvP", "12:bhv_timer"), "COEX_SURVEY = false by pHelmIvP (12:bhv_timer)"),
    (("IVPHELM_BHV_IDLE", "coex_survey,coex_depth", "pHelmIvP", ""), "coex_survey idle before its last waypoint"),
    (("IVPHELM_STATE", "DISABLED", "pHelmIvP", ""), "helm DISABLED"),
])
def test_other_stops_abort_with_what_was_seen(mail: tuple[str, str, str, str], detail: str) -> None:
    b = Bench()
    b.take()
    b.helm("IVPHELM_BHV_RUNNING", "coex_survey")
    b.helm("COEX_SURVEY", "true", source="uPokeDB")  # activated by someone else too: nothing
    b.helm(mail[0], mail[1], source=mail[2], aux=mail[3])
    assert b.poll() == [(3, SurveyState.STARTED, SurveyReason.NONE, 0, None),
                        (3, SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED, None, detail)]


def test_timeouts_name_what_did_not_answer() -> None:
    b = Bench(timeout=5.0)
    # no helm at all (no IVPHELM_STATE for the timeout)
    b.now += 60
    b.a.submit(LINE, b.now)
    assert b.poll(4.0) == []
    assert b.poll(2.0) == [(3, SurveyState.REJECTED, SurveyReason.AUTONOMY_NO_ANSWER, None,
                            "no helm (no IVPHELM_STATE)")]
    # a helm, but no behaviour takes the update (another updates variable)
    b.helm("IVPHELM_STATE", "DRIVE")
    b.helm("IVPHELM_ALLSTOP", "NothingToDo")
    b.a.submit(LINE, b.now)
    b.client.connected = False  # no mail can come while disconnected: no timeout runs
    assert b.poll(30.0) == []
    b.client.connected = True
    b.helm("IVPHELM_STATE", "DRIVE")
    assert b.poll(4.0) == []
    b.helm("IVPHELM_STATE", "DRIVE")
    assert b.poll(2.0) == [(3, SurveyState.REJECTED, SurveyReason.AUTONOMY_NO_ANSWER, None,
                            "no answer to COEX_WPT_UPDATE (helm DRIVE)")]
    # activated, but the behaviour never ran (another condition of it is false)
    b.take()
    b.helm("IVPHELM_STATE", "DRIVE")
    assert b.poll(6.0) == [(3, SurveyState.ABORTED, SurveyReason.AUTONOMY_STOPPED, None,
                            "coex_survey did not run (NothingToDo)")]
    # flying, then the helm falls silent (killed, not restarted): the output says when it last
    # heard the helm; the daemon's lifecycle aborts the survey after `silence` (its tests)
    b.helm("IVPHELM_STATE", "DRIVE")
    b.take()
    b.helm("WPT_INDEX", 0.0)
    b.helm("IVPHELM_STATE", "DRIVE")
    assert [r[1] for r in b.poll()] == [SurveyState.STARTED]
    heard = b.now
    assert b.poll(60.0) == [] and b.a.heard(b.now) == heard
    assert (b.a.silence(), b.a.silent_detail()) == (10.0, "no IVPHELM_STATE from the helm")
    b.client.connected = False  # MOOSDB out of reach: no helm can be heard, none is called silent
    assert b.a.heard(b.now) == b.now


def test_own_posts_and_mail_without_a_survey_are_ignored() -> None:
    b = Bench(name="pCoex_helm")
    b.helm("COEX_SURVEY", "false", source="pCoex_helm")
    b.helm("WPT_STAT", "behavior-name=coex_survey,completed")
    assert b.poll() == []
    b.take()
    b.helm("COEX_SURVEY", "false", source="pCoex_helm")  # its own deactivation of an older survey
    b.helm("WPT_INDEX", 9.0)  # no waypoint 9: logged, ignored
    assert b.poll() == []
    assert b.a.stats["ignored"] >= 3


def test_registered_variables() -> None:
    b = Bench(endflag="COEX_DONE = true")
    assert set(b.client.registered) == {
        "WPT_INDEX", "WPT_STAT", "BHV_WARNING", "BHV_ERROR", "MOOS_MANUAL_OVERRIDE", "MOOS_MANUAL_OVERIDE",
        "IVPHELM_UPDATE_RESULT", "IVPHELM_STATE", "IVPHELM_ALLSTOP", "IVPHELM_BHV_ACTIVE", "IVPHELM_BHV_RUNNING",
        "IVPHELM_BHV_IDLE", "PHELMIVP_PID", "IVPHELM_RESTARTED", "COEX_SURVEY", "COEX_DONE"}
    b.take()
    b.helm("COEX_DONE", "true")
    assert [r[1] for r in b.poll()] == [SurveyState.STARTED, SurveyState.COMPLETED]


def test_after_a_restart_the_survey_is_followed_again_without_a_post_to_the_helm() -> None:
    b = Bench()  # a new pCoex process: the helm is flying LINE, submitted before the restart
    assert b.a.resume(LINE, b.now) is True
    assert b.posts() == []  # nothing posted: the helm goes on as it was
    b.helm("WPT_INDEX", 1.0)
    b.helm("WPT_STAT", "vname=alpha,behavior-name=coex_survey,index=1,hits=1/1,cycles=0,dist=10,eta=10")
    assert b.poll() == [(3, SurveyState.STARTED, SurveyReason.NONE, 1, None)]
    b.helm("WPT_STAT", "behavior-name=coex_survey,completed")
    assert b.poll() == [(3, SurveyState.COMPLETED, SurveyReason.NONE, None, None)]

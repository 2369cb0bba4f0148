"""Abstract tests every vehicle adapter must pass: inputs (:class:`InputTests`) and autonomy
outputs (:class:`AutonomyTests`), with the fixtures they need (:class:`InputFixtures`,
:class:`AutonomyFixtures`).

A vehicle team's own adapter is tested exactly as the built-ins are::

    from coex_conformance import InputFixtures, InputTests

    class MyFixtures(InputFixtures):
        @pytest.fixture
        def input_class(self): return MySonarInput
        @pytest.fixture
        def input_options(self): return {"port": 5000}
        @pytest.fixture
        def feed(self): return lambda adapter: send_two_pings_to(5000)   # optional

    class TestMySonar(InputTests, MyFixtures):
        pass

What they check is the contract declared on :class:`coex.Adapter`, ``Input`` and
``Autonomy``: declared options (an unknown or a missing one refused by name), ``check`` and
``paths`` answering in their declared forms, ``poll`` never blocking and giving only the item
types the adapter says it feeds, what it skipped counted, ``close`` harmless twice; an autonomy
output's reports about the plans it was given only, in the states an output may report, and a
silent autonomy told apart from a refusal.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import pytest

from coex import (
    FEEDS,
    Adapter,
    Autonomy,
    ConfigError,
    Image,
    Input,
    InputContext,
    Nav,
    Points,
    Problems,
    Samples,
    SurveyPlan,
)
from coex.messages import SurveyKind, SurveyReason, SurveyState

__all__ = ["AutonomyFixtures", "AutonomyTests", "InputFixtures", "InputTests", "survey_plan"]

#: the longest a poll or a submit may take (they never wait for the vehicle's middleware)
NO_WAIT = 2.0
_ITEMS = {"bathymetry": Points, "imagery": Image, "timeseries": Samples, "status": Nav}


def survey_plan(survey_id: int = 7, kind: str = "line") -> SurveyPlan:
    """A small survey plan as the survey sender gives one to an autonomy output (a line, or a
    go-to), for autonomy tests."""
    if kind == "goto":
        return SurveyPlan(survey_id, SurveyKind.GOTO, ((10.0, 20.0),), None, 20.0, 1.0)
    return SurveyPlan(survey_id, SurveyKind.LINE, ((0.0, 0.0), (30.0, 0.0)), 5.0, None, 1.0,
                      heading=90.0, length=30.0)


class _AdapterFixtures:
    @pytest.fixture
    def context(self, tmp_path: Any) -> InputContext:
        """Optional: the daemon's context (origin, the configuration's folder, clock)."""
        return InputContext(41.5, -70.7, str(tmp_path), time.time)


class InputFixtures(_AdapterFixtures):
    """Fixtures an input provides to run :class:`InputTests`."""

    @pytest.fixture
    def input_class(self) -> type[Input]:
        """Required: the :class:`~coex.Input` subclass."""
        raise NotImplementedError("provide an `input_class` fixture")

    @pytest.fixture
    def input_options(self) -> dict[str, Any]:
        """Required: options that make a working input (its table without ``type``)."""
        raise NotImplementedError("provide an `input_options` fixture")

    @pytest.fixture
    def feed(self) -> Callable[[Input], Any] | None:
        """Optional: make the input's source produce data (write a file, publish a message);
        called after ``open``. Without it the data tests are skipped."""
        return None

    @pytest.fixture
    def feed_bad(self) -> Callable[[Input], Any] | None:
        """Optional: make the source produce one item the input cannot use (a corrupt file, a
        message that does not decode). Without it that test is skipped."""
        return None


class AutonomyFixtures(_AdapterFixtures):
    """Fixtures an autonomy output provides to run :class:`AutonomyTests`."""

    @pytest.fixture
    def autonomy_class(self) -> type[Autonomy]:
        """Required: the :class:`~coex.Autonomy` subclass."""
        raise NotImplementedError("provide an `autonomy_class` fixture")

    @pytest.fixture
    def autonomy_options(self) -> dict[str, Any]:
        """Required: options that make a working output, pointed at :func:`peer` when there is one."""
        raise NotImplementedError("provide an `autonomy_options` fixture")

    @pytest.fixture
    def peer(self) -> str | None:
        """Optional: how the vehicle's autonomy behaves in the tests: ``"flies"`` (it takes and
        flies every plan), ``"silent"`` (it never answers; the default: nothing is running) or
        ``None`` (an output with no peer, like ``log``, that reports nothing)."""
        return "silent"

    @pytest.fixture
    def patience(self) -> float:
        """Optional: seconds of ``now`` after which a silent autonomy must have been given up
        (reported ``AUTONOMY_NO_ANSWER``; the tests advance ``now`` themselves), or within which
        a flying peer completes a short line (in real seconds: it flies on the wall clock)."""
        return 600.0


def _declared(cls: type[Adapter]) -> None:
    assert isinstance(cls.name, str) and cls.name, "rule: an adapter has a name (its entry point's)"
    assert isinstance(cls.options, Mapping), "rule: options is a mapping name -> (default, description)"
    for key, spec in cls.options.items():
        assert isinstance(key, str) and isinstance(spec, tuple) and len(spec) == 2 and isinstance(spec[1], str), (
            f"rule: option {key!r} is declared as (default, one-line description), got {spec!r}")


def _unknown_refused(cls: type[Adapter], options: dict[str, Any], context: InputContext) -> None:
    bad = dict(options, coex_no_such_option=1)
    with pytest.raises(ConfigError, match="coex_no_such_option"):
        cls(bad, context)
    required = [k for k, (default, _) in cls.options.items() if default is ...]
    for key in required:
        missing = {k: v for k, v in options.items() if k != key}
        with pytest.raises(ConfigError, match=key):
            cls(missing, context)


def _no_problem(cls: type[Adapter], options: dict[str, Any]) -> None:
    """``check`` answers with a list of sentences or a :class:`~coex.Problems`, and
    finds nothing in working options."""
    problems = cls.check(options)
    assert isinstance(problems, list | Problems), (
        f"rule: check() answers with a list of sentences or a Problems, got {type(problems).__name__}")
    texts = problems.items if isinstance(problems, Problems) else problems
    assert texts == [], f"rule: check() of working options finds no problem, got {texts!r}"


def _paths_declared(cls: type[Adapter], options: dict[str, Any]) -> None:
    paths = cls.paths(options)
    assert isinstance(paths, list), "rule: paths() is a list of (option, path, kind)"
    for entry in paths:
        option, path, kind = entry
        assert option in cls.options, f"rule: paths() names declared options, not {option!r}"
        assert isinstance(path, str) and kind in ("file", "folder", "file or folder", "device"), (
            f"rule: paths() gives (option, path, file|folder|file or folder|device), got {entry!r}")


class InputTests:
    """The input contract (see the module docstring)."""

    def test_declares_name_options_and_what_it_feeds(self, input_class: type[Input]) -> None:
        _declared(input_class)
        assert input_class.feeds and set(input_class.feeds) <= set(FEEDS), (
            f"rule: an input feeds some of {FEEDS}, got {input_class.feeds!r}")

    def test_an_unknown_or_missing_option_is_refused_by_name(self, input_class: type[Input],
                                                            input_options: dict[str, Any],
                                                            context: InputContext) -> None:
        _unknown_refused(input_class, input_options, context)

    def test_check_and_paths_answer_in_their_forms(self, input_class: type[Input],
                                                  input_options: dict[str, Any]) -> None:
        _no_problem(input_class, input_options)
        _paths_declared(input_class, input_options)

    def test_poll_never_blocks_and_close_is_harmless_twice(self, input_class: type[Input],
                                                          input_options: dict[str, Any],
                                                          context: InputContext) -> None:
        inp = input_class(input_options, context)
        assert inp.counts.get("skipped") == 0, "rule: counts['skipped'] starts at 0 (from the base class)"
        inp.open()
        try:
            for _ in range(3):
                t0 = time.monotonic()
                items = inp.poll(time.time())
                assert time.monotonic() - t0 < NO_WAIT, "rule: poll never waits for the middleware"
                assert isinstance(items, list), "rule: poll returns a list of items"
        finally:
            inp.close()
        inp.close()

    def test_what_it_reads_comes_as_the_items_it_feeds(self, input_class: type[Input],
                                                      input_options: dict[str, Any], context: InputContext,
                                                      feed: Callable[[Input], Any] | None) -> None:
        if feed is None:
            pytest.skip("no `feed` fixture: the input's data path is not exercised")
        inp = input_class(input_options, context)
        inp.open()
        try:
            feed(inp)
            items: list[Any] = []
            end = time.monotonic() + 20.0
            while not items and time.monotonic() < end:
                items = inp.poll(time.time())
                time.sleep(0.05)
            assert items, "rule: what the source produced comes out of poll (within 20 s)"
            allowed = tuple(_ITEMS[f] for f in input_class.feeds)
            for item in items:
                assert isinstance(item, allowed), (
                    f"rule: an input gives only the items of what it feeds ({input_class.feeds}), "
                    f"got {type(item).__name__}")
                if isinstance(item, Samples):  # a series: its times, one per value
                    times = np.asarray(item.times, dtype=float)
                    assert times.shape == np.shape(item.values) and bool(np.isfinite(times).all()), (
                        "rule: every sample has its time (POSIX seconds, finite), one per value")
                elif isinstance(item, Points | Image | Nav):
                    assert isinstance(item.time, float) and math.isfinite(item.time), (
                        "rule: every item has its time (POSIX seconds, finite)")
        finally:
            inp.close()

    def test_an_item_it_cannot_use_is_skipped_and_counted(self, input_class: type[Input],
                                                          input_options: dict[str, Any], context: InputContext,
                                                          feed_bad: Callable[[Input], Any] | None) -> None:
        if feed_bad is None:
            pytest.skip("no `feed_bad` fixture")
        inp = input_class(input_options, context)
        inp.open()
        try:
            feed_bad(inp)
            end = time.monotonic() + 20.0
            while inp.skipped == 0 and time.monotonic() < end:
                inp.poll(time.time())  # never raises for bad input
                time.sleep(0.05)
            assert inp.skipped >= 1, "rule: an item that cannot be used is counted in counts['skipped']"
        finally:
            inp.close()


class AutonomyTests:
    """The autonomy-output contract (see the module docstring)."""

    def test_declares_name_and_options(self, autonomy_class: type[Autonomy]) -> None:
        _declared(autonomy_class)

    def test_an_unknown_or_missing_option_is_refused_by_name(self, autonomy_class: type[Autonomy],
                                                            autonomy_options: dict[str, Any],
                                                            context: InputContext) -> None:
        _unknown_refused(autonomy_class, autonomy_options, context)

    def test_check_and_paths_answer_in_their_forms(self, autonomy_class: type[Autonomy],
                                                  autonomy_options: dict[str, Any]) -> None:
        _no_problem(autonomy_class, autonomy_options)
        _paths_declared(autonomy_class, autonomy_options)

    def _reports(self, out: Autonomy, start: float, seconds: float, *, realtime: bool,
                 until: Callable[[list[Any]], bool]) -> list[Any]:
        """Poll ``out`` for ``seconds`` of ``now`` from ``start`` or until ``until(reports)``:
        ``now`` follows the wall clock with a real peer (``realtime``), else it runs ahead
        (a silent peer: its timeouts come from ``now`` alone)."""
        got: list[Any] = []
        t_real = time.monotonic()
        now = start
        while now <= start + seconds and not until(got):
            t0 = time.monotonic()
            got += out.poll(now)
            assert time.monotonic() - t0 < NO_WAIT, "rule: poll never waits for the autonomy"
            if realtime:
                time.sleep(0.02)
                now = start + (time.monotonic() - t_real)
            else:
                now += max(0.5, seconds / 400)
                time.sleep(0.001)
        return got

    def test_reports_are_about_its_plans_in_the_states_an_output_may_report(
            self, autonomy_class: type[Autonomy], autonomy_options: dict[str, Any], context: InputContext,
            peer: str | None, patience: float) -> None:
        out = autonomy_class(autonomy_options, context)
        out.open()
        try:
            plan = survey_plan(7)
            t0 = time.monotonic()
            out.submit(plan, 1000.0)
            assert time.monotonic() - t0 < NO_WAIT, "rule: submit never waits for the autonomy"
            def ended(got: list[Any]) -> bool:
                return any(SurveyState(r.state) != SurveyState.STARTED for r in got)

            reports = self._reports(out, 1000.0, patience + 60.0, realtime=peer == "flies", until=ended)
        finally:
            out.close()
        out.close()
        for r in reports:
            assert r.survey_id == plan.survey_id, f"rule: reports are about the plans given, got survey {r.survey_id}"
            assert SurveyState(r.state) in (SurveyState.STARTED, SurveyState.COMPLETED, SurveyState.ABORTED,
                                            SurveyState.REJECTED), (
                f"rule: an output reports STARTED, COMPLETED, ABORTED or REJECTED, never {SurveyState(r.state).name}")
            assert SurveyReason(r.reason) != SurveyReason.SUPERSEDED, "rule: SUPERSEDED is the survey sender's"
            if r.detail is not None:
                assert isinstance(r.detail, str), "rule: detail is text"
        if peer == "silent":
            final = [r for r in reports if SurveyState(r.state) in (SurveyState.REJECTED, SurveyState.ABORTED)]
            assert final, f"rule: a silent autonomy is given up within {patience:g} s of `now`"
            assert SurveyReason(final[0].reason) == SurveyReason.AUTONOMY_NO_ANSWER, (
                "rule: an autonomy that never answered is AUTONOMY_NO_ANSWER, not a refusal "
                f"(got {SurveyReason(final[0].reason).name})")
        elif peer == "flies":
            states = [SurveyState(r.state) for r in reports]
            assert SurveyState.COMPLETED in states and states[-1] == SurveyState.COMPLETED, (
                f"rule: a plan the autonomy flies ends COMPLETED, got {[s.name for s in states]}")
            started = [r.index for r in reports if SurveyState(r.state) == SurveyState.STARTED]
            assert started == sorted(started), "rule: STARTED reports head for waypoints in order"
        elif peer is None:
            assert reports == [], "rule: an output with no autonomy behind it reports nothing"

    def test_the_survey_lifecycle_hooks_answer_in_their_forms(
            self, autonomy_class: type[Autonomy], autonomy_options: dict[str, Any], context: InputContext) -> None:
        """``end`` (the daemon takes an ended survey back: twice harmless, never waiting; before
        the output was told anything too, as after a restart), ``heard``, ``silence`` and
        ``silent_detail`` (the liveness watch) answer in their declared forms."""
        out = autonomy_class(autonomy_options, context)
        out.open()
        try:
            t0 = time.monotonic()
            out.end(6, 999.0)  # a survey handed over before a restart: nothing known of it
            plan = survey_plan(7)
            out.submit(plan, 1000.0)
            out.poll(1000.5)
            for _ in range(2):
                out.end(plan.survey_id, 1001.0)
                assert isinstance(out.poll(1001.5), list), "rule: poll after an end returns a list"
            assert time.monotonic() - t0 < 3 * NO_WAIT, "rule: end never waits for the autonomy"
            heard = out.heard(1002.0)
            assert heard is None or (isinstance(heard, int | float) and not isinstance(heard, bool)), (
                f"rule: heard() is a time (now's clock) or None, got {heard!r}")
            bound = out.silence()
            assert isinstance(bound, float) and math.isfinite(bound) and bound >= 0, (
                f"rule: silence() is seconds >= 0 (0: not watched), got {bound!r}")
            assert isinstance(out.silent_detail(), str), "rule: silent_detail() is text"
        finally:
            out.close()

"""The console in a real headless browser (Debian chromium driven by Playwright).

``coex topside`` (built with :func:`build_topside`) runs over a ``loopback://`` transport; the
other end is a vehicle node with the real bathymetry sender in a thread. The test loads the page
in two browsers, sees the map fill in as subgrids arrive, draws a region, requests it at the
finest level, and checks that the vehicle's sender received that ``MapRoiRequest``.
Needs ``/usr/bin/chromium`` (``scripts/system-deps.sh``) and the ``playwright`` package
(dev extra); never ``playwright install``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import RealClock, Runner
from coex_apps.console import ConsoleHub, ConsoleState, serve
from coex_apps.console.actions import CommandSink
from coex_apps.console.cli import TopsideApp, build_topside
from coex_apps.console.testing import RecordingSender, feed_sample, survey_points
from coex_core import messages as m
from coex_core.channel.manager import ChannelManager, LinkConfig
from coex_core.channel.queue import StreamConfig
from coex_core.channel.schedule import Schedule
from coex_core.node import Node
from coex_core.registry import open_transport
from coex_core.timefmt import to_stamp
from coex_plugins.bathymetry import BathymetryModality, BathymetrySender

# the console in a real Chromium
pytestmark = pytest.mark.slow

CHROMIUM = os.environ.get("COEX_CHROMIUM", "/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
T0 = 36000.0  # 10:00:00
#: ms a page is waited for before the test fails: a hang guard, not a speed target (CI's two
#: cores run three test workers beside Chromium; a page that is on time passes at once)
WAIT = 60_000
#: Topside slot then vehicle slot, 4 s each: one rate-5 packet (3 s) per slot.
SCHEDULE = Schedule.simple([1, 2], 4.0, 0.5)


class Vehicle:
    """A vehicle node on the other loopback end, with the bathymetry sender and a status."""

    def __init__(self, uri: str) -> None:
        self.transport = open_transport(uri)
        manager = ChannelManager(2, [LinkConfig(0, SCHEDULE, rate=5, dst=1)],
                                 queue_status_interval=8.0)
        self.node = Node(manager)
        self.sender = RecordingSender(BathymetrySender({"send_delay": 0.0, "levels": 4}))
        self.sender.ingest(survey_points(), time.time())
        self.node.add_sender(BathymetryModality, self.sender, StreamConfig(3, "map", priority=30))
        self.runner = Runner(self.node, {0: self.transport}, RealClock())
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        k = 0
        while not self.stop.is_set():
            now = time.time()
            if k % 20 == 0:
                self.node.push_status(m.VehicleStatus(
                    to_stamp(now), 10.0 + k * 0.05, 30.0, 45.0, 20.0, 90.0, 1.5, 77,
                    m.VehicleMode.SURVEY, 0), now)
            self.runner.step()
            k += 1
            self.stop.wait(0.05)

    def requests(self) -> list[m.MapRoiRequest]:
        return [x for x in list(self.sender.handled) if isinstance(x, m.MapRoiRequest)]


@pytest.fixture
def topside() -> Iterator[tuple[TopsideApp, Vehicle]]:
    uri = f"loopback://console-{uuid.uuid4().hex[:8]}?rate=100000"
    app = build_topside(uri, "127.0.0.1", 0, schedule=SCHEDULE,
                        modalities=("bathymetry", "imagery", "timeseries"))
    vehicle = Vehicle(uri)
    app.start()  # the vehicle starts once the page is loaded (the test does it)
    try:
        yield app, vehicle
    finally:
        vehicle.stop.set()
        if vehicle.thread.is_alive():
            vehicle.thread.join(timeout=5)
        app.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    try:
        from playwright import sync_api
    except ImportError:  # a missing test dependency is a failure, not a skip
        pytest.fail("playwright is missing: pip install -e '.[dev]' (never `playwright install`)")
    assert shutil.which(CHROMIUM) or Path(CHROMIUM).exists(), (
        f"{CHROMIUM} missing: install Debian chromium (scripts/system-deps.sh)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            yield b
        finally:
            b.close()


@contextlib.contextmanager
def sample_console(browser: Any, hub_type: type[ConsoleHub], sent: list[m.Message],
                   errors: list[str], prepare: Any = None, hubs: list[ConsoleHub] | None = None) -> Iterator[Any]:
    """A page of a console fed with the sample dive (no link: ``sent`` records what the hub
    would send, ``errors`` the page's script errors), loaded and showing its first update;
    ``prepare(state)`` adds to the sample first; ``hubs`` receives the hub (to feed it events)."""
    state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
    feed_sample(state, t0=T0)
    if prepare is not None:
        prepare(state)
    hub = hub_type(state, sent.append, lambda: T0)
    if hubs is not None:
        hubs.append(hub)
    with serve(hub, "127.0.0.1", 0) as srv:
        page = browser.new_page(bypass_csp=True, viewport={"width": 1400, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(srv.url)
        page.wait_for_function("window.coex && window.coex.updates > 0", timeout=WAIT)
        try:
            yield page
        finally:
            page.close()


#: Map canvas pixels that are neither background nor grid.
PAINTED = """(() => {
    const c = document.querySelector('#map-canvas');
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < d.length; i += 4) if (d[i] + d[i+1] + d[i+2] > 120) n++;
    return n; })()"""


def _painted(page: Any) -> int:
    return int(page.evaluate(PAINTED))


def test_console_map_updates_and_region_request_reaches_vehicle(
        topside: tuple[TopsideApp, Vehicle], browser: Any, tmp_path: Path) -> None:
    app, vehicle = topside
    errors: list[str] = []
    pages = []
    for _ in range(2):  # two operators on the same console
        page = browser.new_page(bypass_csp=True, viewport={"width": 1400, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(app.url)
        pages.append(page)
    page, other = pages
    page.wait_for_function("window.coex && window.coex.connected && window.coex.updates > 0",
                           timeout=WAIT)
    assert page.query_selector_all("#levels-table tbody tr") == []
    empty = _painted(page)
    vehicle.thread.start()

    # the map updates as the vehicle's subgrids arrive (first vehicle slot within 8 s)
    page.wait_for_selector("#levels-table tbody tr", timeout=WAIT)
    page.wait_for_function(
        "document.querySelectorAll('#levels-table tbody tr').length >= 3", timeout=WAIT)
    page.wait_for_function(f"{PAINTED} > {empty + 5000}", timeout=WAIT)  # pictures drawn
    with app.hub.lock:
        rx = app.hub.state.map_receiver
        held = {lv: len(rx.holdings(lv)) for lv in rx.levels()}
    shown = {int(r.get_attribute("data-level")): int(r.query_selector(".n-subgrids").inner_text())
             for r in page.query_selector_all("#levels-table tbody tr")}
    assert shown and all(shown[lv] <= held[lv] for lv in shown)
    other.wait_for_selector("#levels-table tbody tr", timeout=WAIT)

    # draw a region (28..44 m east, 34..46 m north) and request it at level 0
    page.click("#draw-btn")
    a = page.evaluate("window.coex.pagePoint(28, 46)")
    b = page.evaluate("window.coex.pagePoint(44, 34)")
    page.mouse.move(a[0], a[1])
    page.mouse.down()
    page.mouse.move((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
    page.mouse.move(b[0], b[1])
    page.mouse.up()
    page.wait_for_selector("#roi-bar:not(.hidden)")
    page.select_option("#roi-level", "0")
    page.click("#roi-send")

    # both operators see the request; the vehicle's bathymetry sender gets it over the link
    for p in (page, other):
        p.wait_for_function(
            "[...document.querySelectorAll('#commands li')].some(li => li.textContent.includes('map level 0'))",
            timeout=WAIT)
    deadline = time.monotonic() + WAIT / 1000
    while not vehicle.requests() and time.monotonic() < deadline:
        time.sleep(0.2)
    got = vehicle.requests()
    assert got, f"no MapRoiRequest reached the vehicle (topside errors: {app.errors})"
    cells = {(r.x0 + i, r.y0 + j) for r in got for i in range(r.w) for j in range(r.h)}
    assert all(r.level == 0 for r in got)
    assert cells == {(ix, iy) for ix in range(3, 6) for iy in range(4, 6)}  # 8 m subgrids

    # the requested region is drawn on the map with its status, then answered
    page.wait_for_function(
        "window.coex.S.map.requests.some(r => r.level === 0 && r.status !== 'waiting')",
        timeout=WAIT)
    shot = tmp_path / "console.png"
    page.screenshot(path=str(shot), full_page=True)
    assert shot.stat().st_size > 20_000
    if os.environ.get("COEX_CONSOLE_SHOT"):
        shutil.copy(shot, os.environ["COEX_CONSOLE_SHOT"])
    assert not errors, errors
    for p in pages:
        p.close()


def test_console_actions_from_the_page_are_wire_commands(browser: Any) -> None:
    """Images, time series, queues, link and schedule controls of the page, on a sample dive
    made by the real plugins (no link: the hub records what it would send)."""
    sent: list[m.Message] = []
    errors: list[str] = []
    with sample_console(browser, ConsoleHub, sent, errors) as page:
        # three image cards with decoded thumbnails
        page.wait_for_function(
            "[...document.querySelectorAll('#gallery .card img')].filter(i => i.naturalWidth > 0).length === 3",
            timeout=WAIT)
        assert "SURVEY" in page.inner_text("#vehicle-status")
        assert page.is_disabled("#survey-btn")  # no survey receiver behind this console

        # a click on the vehicle track sets the image time to when the vehicle was there
        # (the sample's 11th status: x 31.0 m, y 20 m at 09:51:30)
        x, y = page.evaluate("window.coex.pagePoint(31.0, 20.0)")
        page.mouse.click(x, y)
        assert page.input_value("#img-time") == "09:51:30"

        card = page.locator('#gallery .card[data-image="1"]')
        card.locator("select").select_option("full")
        card.locator("button").click()
        page.fill("#img-time", "09:57:40")
        page.click('.img-time-btn[data-dir="previous"]')

        plot = page.locator('#series canvas[data-channel="0"]')
        box = plot.bounding_box()
        y = box["y"] + box["height"] / 2
        # the plot area: right of the value axis (48 px), 6 px short of the right edge
        def at(f: float) -> float:
            return float(box["x"] + 48 + f * (box["width"] - 54))
        page.mouse.move(at(0.25), y)
        page.mouse.down()
        page.mouse.move(at(0.5), y)
        page.mouse.up()
        page.fill("#series-err", "0.05")
        page.click("#series-refine")

        row = page.locator('#queues-table tr[data-stream="3"]')
        row.locator("input").fill("99")
        row.locator("button", has_text="Set").click()
        page.locator('#queues-table tr[data-stream="4"]').locator("button", has_text="Flush").click()
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 5",
                               timeout=WAIT)
        page.locator('#links-table tr[data-link="0"] select').select_option("0")  # spare traffic off
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 6",
                               timeout=WAIT)
        page.locator('#links-table tr[data-link="0"]').locator("button").click()
        page.click("#schedule-editor summary")
        page.fill("#sched-slots", "1:10:1, 2:30:2")
        page.click("#sched-send")
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 8",
                               timeout=WAIT)
    assert not errors, errors
    goal, by_time, refine, prio, flush, spare, link, sched = sent
    assert spare == m.SpareConfig(spare.command_id, 0, None, 0)
    assert goal == m.ImageGoal(goal.command_id, 1, m.GoalKind.FULL, 0)
    assert by_time.direction == m.TimeDirection.BEFORE and by_time.stamp == to_stamp(T0 - 140)
    assert isinstance(refine, m.TimeSeriesRequest) and refine.channel == 0
    t0, t1 = T0 - 1800, T0 - 1
    assert abs(refine.start - to_stamp(t0 + 0.25 * (t1 - t0))) <= 30
    assert abs(refine.end - to_stamp(t0 + 0.5 * (t1 - t0))) <= 30
    assert refine.max_error == pytest.approx(0.05, rel=1e-6)
    assert (prio.stream, prio.priority, prio.flush) == (3, 99, False)
    assert (flush.stream, flush.flush) == (4, True)
    assert link == m.LinkControl(link.command_id, 0, False, False)
    assert [(s.owner, s.duration, s.guard) for s in sched.slots] == [(1, 10.0, 1.0), (2, 30.0, 2.0)]


class _SlowFirstAction(ConsoleHub):
    """A hub that takes its time over the first action, as a busy console would."""

    def act(self, action: str, args: dict[str, Any], operator: str = "") -> list[Any]:
        if not getattr(self, "_slowed", False):
            self._slowed = True
            time.sleep(0.8)
        return super().act(action, args, operator)


def test_console_actions_reach_the_vehicle_in_the_order_given(browser: Any) -> None:
    """Two quick clicks (flush a queue, then disable the link) become commands in that order,
    even when the server is slow with the first: the page sends one action at a time."""
    sent: list[m.Message] = []
    errors: list[str] = []
    with sample_console(browser, _SlowFirstAction, sent, errors) as page:
        page.wait_for_selector('#queues-table tr[data-stream="4"]', timeout=WAIT)
        page.locator('#queues-table tr[data-stream="4"]').locator("button", has_text="Flush").click()
        page.locator('#links-table tr[data-link="0"]').locator("button").click()
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 2",
                               timeout=WAIT)
    assert not errors, errors
    assert [type(x) for x in sent] == [m.QueueConfig, m.LinkControl], sent


def test_a_third_party_modality_shows_in_the_generic_panel(browser: Any, tmp_path: Path) -> None:
    """The sample plugin's pings (no panel of their own) appear in "Other data"; the panel
    stays hidden on a console without such data."""
    from coex_core.registry import load_modality

    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors) as page:
        assert page.is_hidden("#other-panel")
    state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
    feed_sample(state, t0=T0)
    pings = load_modality("pings")().sender(None)
    for k in range(12):
        pings.ingest((T0 - 60 + 5 * k, 30.0 + k), T0)
    state.apply_messages(pings.fill(400, T0), T0)
    with serve(ConsoleHub(state, lambda msg: None, lambda: T0), "127.0.0.1", 0) as srv:
        page = browser.new_page(bypass_csp=True, viewport={"width": 1400, "height": 1300})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(srv.url)
        page.wait_for_function("window.coex && window.coex.updates > 0", timeout=WAIT)
        assert page.is_visible("#other-panel")
        text = page.inner_text("#other")
        assert "pings" in text and "count: 12" in text
        page.screenshot(path=str(tmp_path / "other-panel.png"), full_page=True)
        page.close()
    assert errors == []


def test_a_big_level_zoomed_in_is_drawn_from_what_is_on_screen(browser: Any) -> None:
    """A level too big to draw whole comes as a decimated overview (16 m pixels here); the page
    asks the server for the part on screen at the screen's resolution, read from the
    receiver's tiles, and draws it (zoomed in further, again)."""
    import numpy as np

    from coex_plugins.bathymetry import BathymetryReceiver, encode_subgrid

    rx = BathymetryReceiver({"levels": 1, "max_mosaic_cells": 4096, "memory_budget": 1,
                             "tile_subgrids": 4})
    state = ConsoleState(receivers={"bathymetry": rx})
    yy, xx = np.mgrid[0:8, 0:8]
    for iy in range(40):
        for ix in range(40):
            q = -4000 + 3 * (ix * 8 + xx) + ((iy * 8 + yy) // 4) % 7
            sg = encode_subgrid(q, np.ones((8, 8), bool), level=0, ix=ix, iy=iy,
                                stamp=to_stamp(T0), resolution=1.0, vertical_resolution=0.1)
            for p in rx.receive(sg, T0):
                state.apply_product("bathymetry", p, T0)
    assert state.snapshot()["map"]["levels"][0]["step"] == 16
    errors: list[str] = []
    windows: list[str] = []
    hub = ConsoleHub(state, lambda msg: None, lambda: T0)
    with serve(hub, "127.0.0.1", 0) as srv:
        page = browser.new_page(bypass_csp=True, viewport={"width": 1400, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("requestfinished", lambda r: windows.append(r.url) if "/window.png" in r.url else None)
        page.goto(srv.url)
        page.wait_for_function("window.coex && window.coex.updates > 0", timeout=WAIT)
        deadline = time.monotonic() + WAIT / 1000
        while not windows and time.monotonic() < deadline:
            page.wait_for_timeout(100)
        assert windows and "step=1&" in windows[0]  # about 2 screen pixels a metre
        x, y = page.evaluate("window.coex.pagePoint(100, 100)")
        page.mouse.move(x, y)
        seen = len(windows)
        for _ in range(6):
            page.mouse.wheel(0, -400)
            page.wait_for_timeout(50)
        deadline = time.monotonic() + WAIT / 1000
        while len(windows) == seen and time.monotonic() < deadline:
            page.wait_for_timeout(100)
        assert len(windows) > seen  # the part now on screen
        assert _painted(page) > 100_000
        if os.environ.get("COEX_BIG_MAP_SHOT"):  # to look at it: COEX_BIG_MAP_SHOT=big.png
            page.wait_for_timeout(500)
            page.screenshot(path=os.environ["COEX_BIG_MAP_SHOT"])
        page.close()
    assert not errors, errors


class VehicleEnd:
    """The vehicle's end of a loopback link, by hand: what topside sends, and frames of
    messages "from the vehicle" (src 2)."""

    def __init__(self, uri: str) -> None:
        from coex_core import wire

        self.wire = wire
        self.transport = open_transport(uri)
        self.seq = 0
        self.heard: list[m.Message] = []

    def send(self, msgs: list[m.Message]) -> None:
        """Pack ``msgs`` into as few frames as fit and send them to topside."""
        budget = int(self.transport.mtu)
        batch: list[m.Message] = []
        for msg in [*msgs, None]:
            if msg is not None and self.wire.header_size() + sum(
                    len(self.wire.encode(x)) for x in [*batch, msg]) <= budget:
                batch.append(msg)
                continue
            if batch:
                self.seq = (self.seq + 1) % 256
                self.transport.send(self.wire.pack(batch, budget, m.FrameHeader(src=2, dst=1, seq=self.seq)))
            batch = [msg] if msg is not None else []

    def wait_for(self, kind: type, timeout: float = WAIT / 1000) -> Any:
        """The first message of type ``kind`` topside sends."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            frame = self.transport.recv(0.2)
            if frame is None:
                continue
            for msg in self.wire.unpack_frame(frame).messages:
                self.heard.append(msg)
                if isinstance(msg, kind):
                    return msg
        raise AssertionError(f"topside sent no {kind.__name__} (heard {self.heard})")


def _surveys_row(page: Any, sid: int) -> str:
    return f'#surveys-table tr[data-survey="{sid}"]'


def test_a_survey_drawn_on_the_map_is_sent_and_its_rejection_shown(browser: Any, tmp_path: Path) -> None:
    """The operator draws a lawnmower box with the mouse on a ``coex topside`` page (the
    survey receiver runs by default), sees the path previewed, sends it and sees it listed as
    requested; the SurveyCommand goes out over the link. The vehicle answers CommandAck
    REJECTED and SurveyStatus REJECTED OUTSIDE_GEOFENCE: the page shows "rejected" with the
    reason in words. A line survey then shows accepted, then started towards its waypoint."""
    from coex_apps.console.testing import drain
    from coex_plugins.bathymetry import BathymetrySender

    uri = f"loopback://survey-{uuid.uuid4().hex[:8]}?rate=100000&mtu=1024"
    app = build_topside(uri, "127.0.0.1", 0, schedule=SCHEDULE)
    vehicle = VehicleEnd(uri)
    app.start()
    errors: list[str] = []
    try:
        # a map and a vehicle to draw over
        now = time.time()
        bathy = BathymetrySender({"send_delay": 0.0, "levels": 4})
        bathy.ingest(survey_points(), now)
        vehicle.send([m.VehicleStatus(to_stamp(now), 30.0, 20.0, 45.0, 20.0, 90.0, 1.5, 77,
                                      m.VehicleMode.SURVEY, 0), *drain(bathy, now)])
        page = browser.new_page(bypass_csp=True, viewport={"width": 1280, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(app.url)
        page.wait_for_function("window.coex && window.coex.connected && window.coex.updates > 0",
                               timeout=WAIT)
        page.wait_for_function("document.querySelectorAll('#levels-table tbody tr').length >= 3",
                               timeout=WAIT)
        assert "No survey requested yet" in page.inner_text("#surveys-table")

        # draw a lawnmower: a 60 x 30 m box from (20, 75) to (80, 45)
        page.click("#survey-btn")
        page.wait_for_selector("#survey-bar:not(.hidden)")
        assert page.input_value("#survey-kind") == "lawnmower"
        assert page.is_disabled("#survey-send")  # nothing drawn yet
        a = page.evaluate("window.coex.pagePoint(20, 75)")
        b = page.evaluate("window.coex.pagePoint(80, 45)")
        page.mouse.move(a[0], a[1])
        page.mouse.down()
        page.mouse.move((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
        page.mouse.move(b[0], b[1])
        page.mouse.up()
        desc = page.inner_text("#survey-desc")
        assert "lawnmower 60 \u00d7 30 m" in desc and "heading 90°" in desc and "4 rows" in desc, desc
        page.fill("#survey-spacing", "10")
        page.fill("#survey-z", "8")
        if os.environ.get("COEX_SURVEY_SHOT"):
            page.screenshot(path=os.environ["COEX_SURVEY_SHOT"].replace(".png", "-preview.png"))
        page.click("#survey-send")
        page.wait_for_selector("#survey-bar.hidden", state="attached", timeout=WAIT)

        # listed as requested, in the commands too; the command goes out over the link
        rx = app.node.receiver("survey")
        page.wait_for_selector('#surveys-table tr[data-state="requested"]', timeout=WAIT)
        with app.hub.lock:
            ((sid, rec),) = rx.surveys.items()
            cmd = rec.command
        row = _surveys_row(page, sid)
        assert "lawnmower" in page.inner_text(row) and "requested" in page.inner_text(row)
        assert cmd.kind == m.SurveyKind.LAWNMOWER and cmd.altitude == 8.0 and cmd.spacing == 10.0
        assert (cmd.heading, cmd.length, cmd.width) == (90.0, 60.0, 30.0)
        assert abs(cmd.x - 50) <= 0.5 and abs(cmd.y - 60) <= 0.5
        got = vehicle.wait_for(m.SurveyCommand)
        assert got == cmd

        # the vehicle refuses it: outside its geofence
        text = "waypoint 6 is 12.5 m outside the geofence"
        vehicle.send([m.CommandAck(cmd.command_id, m.AckStatus.REJECTED)])
        vehicle.send([m.SurveyStatus(sid, m.SurveyState.REJECTED, m.SurveyReason.OUTSIDE_GEOFENCE,
                                     to_stamp(time.time()), 6, 12.5)])
        page.wait_for_function(
            f"(() => {{ const r = document.querySelector('{row}');"
            f" return r && r.dataset.state === 'rejected' && r.textContent.includes('{text}'); }})()",
            timeout=WAIT)
        assert "rejected" in page.inner_text(row)
        assert "SurveyCommand" not in page.inner_text("#commands")  # in words there too
        assert any("survey" in li and "rejected" in li for li in
                   page.eval_on_selector_all("#commands li", "els => els.map(e => e.textContent)"))
        assert text in page.inner_text("#log")

        # a line inside the fence: accepted, then started towards waypoint 1
        page.click("#survey-btn")
        page.select_option("#survey-kind", "line")
        a = page.evaluate("window.coex.pagePoint(10, 10)")
        b = page.evaluate("window.coex.pagePoint(70, 10)")
        page.mouse.move(a[0], a[1])
        page.mouse.down()
        page.mouse.move(b[0], b[1])
        page.mouse.up()
        assert "heading 90°" in page.inner_text("#survey-desc")
        page.fill("#survey-z", "9999")  # beyond what a SurveyCommand carries: refused at once
        page.click("#survey-send")
        page.wait_for_selector("#survey-error:not(.hidden)", timeout=WAIT)
        assert "cannot be sent" in page.inner_text("#survey-error")
        assert len(rx.surveys) == 1 and page.is_visible("#survey-bar")  # nothing sent, drawing kept
        page.fill("#survey-z", "8")
        page.click("#survey-send")
        page.wait_for_function("document.querySelectorAll('#surveys-table tr[data-survey]').length === 2",
                               timeout=WAIT)
        with app.hub.lock:
            line = max(rx.surveys.values(), key=lambda r: r.time).command
        assert line.kind == m.SurveyKind.LINE and abs(line.length - 60) <= 0.5
        vehicle.wait_for(m.SurveyCommand)
        vehicle.send([m.CommandAck(line.command_id, m.AckStatus.ACCEPTED)])
        page.wait_for_selector(f'{_surveys_row(page, line.survey_id)}[data-state="accepted"]', timeout=WAIT)
        vehicle.send([m.SurveyStatus(line.survey_id, m.SurveyState.STARTED, m.SurveyReason.NONE,
                                     to_stamp(time.time()), 1)])
        page.wait_for_selector(f'{_surveys_row(page, line.survey_id)}[data-state="started"]', timeout=WAIT)
        assert "heading for waypoint 1" in page.inner_text(_surveys_row(page, line.survey_id))
        assert text in page.inner_text(row)  # the rejected one stays listed with its reason

        # a reload shows the same (the state comes from the receiver's records)
        page.reload()
        page.wait_for_function("window.coex && window.coex.updates > 0", timeout=WAIT)
        assert text in page.inner_text(row)
        assert page.get_attribute(_surveys_row(page, line.survey_id), "data-state") == "started"
        page.wait_for_timeout(300)  # the map pictures
        shot = tmp_path / "survey.png"
        page.screenshot(path=str(shot), full_page=True)
        if os.environ.get("COEX_SURVEY_SHOT"):
            shutil.copy(shot, os.environ["COEX_SURVEY_SHOT"])
        page.close()
    finally:
        app.close()
        vehicle.transport.close()
    assert not errors, errors


class _SameIds(list[m.Message], CommandSink):
    """A send that numbers every command 5, as a node does after its ids wrap around."""

    def __call__(self, msg: m.Message) -> None:
        self.append(msg)

    def next_command_id(self) -> int:
        return 5


def test_a_rejected_command_stays_rejected_with_its_reason(browser: Any) -> None:
    """A "previous image" request is rejected; the vehicle answers it again (re-sends), and a
    later command reuses its id and is accepted: the first stays rejected with its reason in
    words, the answer is logged once, and the later one shows accepted."""
    from coex_core.channel.events import CommandResult

    state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
    feed_sample(state, t0=T0)
    sent = _SameIds()
    hub = ConsoleHub(state, sent, lambda: T0)
    errors: list[str] = []
    with serve(hub, "127.0.0.1", 0) as srv:
        page = browser.new_page(bypass_csp=True, viewport={"width": 1280, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(srv.url)
        page.wait_for_function("window.coex && window.coex.updates > 0", timeout=WAIT)
        page.fill("#img-time", "09:20:00")
        page.click('.img-time-btn[data-dir="previous"]')
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 1",
                               timeout=WAIT)
        (asked,) = sent
        assert "previous image before 09:20:00" in page.inner_text("#commands")
        hub.update(lambda st: st.apply_event(CommandResult(T0 + 5, 5, m.AckStatus.REJECTED, asked)))
        for k in range(3):  # the vehicle answers every re-send; the node passes them on bare
            hub.update(lambda st, k=k: st.apply_event(CommandResult(T0 + 10 + k, 5, m.AckStatus.REJECTED)))
        # the id comes round again: a queue flush numbered 5, accepted (and answered twice)
        page.wait_for_selector('#queues-table tr[data-stream="4"]', timeout=WAIT)
        page.locator('#queues-table tr[data-stream="4"]').locator("button", has_text="Flush").click()
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 2",
                               timeout=WAIT)
        flush = sent[1]
        assert flush.command_id == 5
        hub.update(lambda st: st.apply_event(CommandResult(T0 + 30, 5, m.AckStatus.ACCEPTED, flush)))
        hub.update(lambda st: st.apply_event(CommandResult(T0 + 40, 5, m.AckStatus.ACCEPTED)))
        hub.update(lambda st: st.apply_message(m.CommandAck(5, m.AckStatus.REJECTED), T0 + 50))
        page.wait_for_selector('#commands li[data-status="accepted"]', timeout=WAIT)
        rows = page.eval_on_selector_all("#commands li[data-status]",
                                         "els => els.map(e => [e.dataset.status, e.textContent])")
        assert [r[0] for r in rows] == ["accepted", "rejected"], rows
        assert "the vehicle holds no image before that time" in rows[1][1]
        assert page.is_visible('#commands li[data-status="rejected"] .reason')
        log = page.inner_text("#log")
        assert log.count("previous image before 09:20:00: rejected") == 1, log
        assert log.count("flush: accepted") == 1, log
        page.close()
    assert not errors, errors


def test_the_map_has_axis_labels_a_north_arrow_and_colour_bar_numbers(browser: Any, tmp_path: Path) -> None:
    """Metres east and north along the map's edges, and the colour bar's depths written out;
    the gaps of the finest level are hatched, and the levels table says how many."""
    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors) as page:
        page.set_viewport_size({"width": 1280, "height": 1000})
        page.wait_for_function("window.coex.axes && window.coex.axes.x.length >= 3 && window.coex.axes.y.length >= 2",
                               timeout=WAIT)
        axes = page.evaluate("window.coex.axes")
        xs = [float(v) for v in axes["x"]]
        assert xs == sorted(xs) and len(set(xs)) == len(xs) and xs[-1] >= 60, axes
        ticks = page.eval_on_selector_all("#colorbar .tick", "els => els.map(e => e.textContent)")
        zr = page.evaluate("window.coex.S.map.zrange")
        assert len(ticks) == 5 and float(ticks[0]) == pytest.approx(zr[0], abs=0.6), (ticks, zr)
        assert float(ticks[-1]) == pytest.approx(zr[1], abs=0.6)
        assert "seafloor elevation (m)" in page.inner_text("#colorbar")
        page.check("#show-age")
        assert page.is_visible("#age-legend") and "30 min" in page.inner_text("#age-legend")
        row = page.inner_text('#levels-table tr[data-level="0"]')
        assert "%" in row and ("empty" in row or "none" in row or "between swaths" in row), row
        assert "dive 0:" in page.inner_text("#clock")
        page.screenshot(path=str(tmp_path / "axes.png"))
        if os.environ.get("COEX_AXES_SHOT"):
            shutil.copy(tmp_path / "axes.png", os.environ["COEX_AXES_SHOT"])
    assert not errors, errors


def test_clicking_an_image_opens_it_full_size(browser: Any, tmp_path: Path) -> None:
    """A card opens the viewer: the picture at its full size (one image pixel a screen pixel
    at 100 %), its bytes and quality layers; its position and footprint are on the map."""
    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors) as page:
        page.set_viewport_size({"width": 1280, "height": 1000})
        page.wait_for_function(
            "[...document.querySelectorAll('#gallery .card img')].filter(i => i.naturalWidth > 0).length === 3",
            timeout=WAIT)
        it = page.evaluate("window.coex.S.images.items.find(i => i.image_id === 1)")
        page.click('#gallery .card[data-image="1"] img')
        page.wait_for_selector("#viewer:not(.hidden)")
        page.wait_for_function("document.querySelector('#viewer-img').naturalWidth > 0", timeout=WAIT)
        assert page.evaluate("document.querySelector('#viewer-img').naturalWidth") == it["width"]
        meta = page.inner_text("#viewer-meta")
        assert "bytes" in meta and "quality layers" in meta and "of" in meta, meta
        assert "#1" in page.inner_text("#viewer-title")
        page.click("#viewer-zoom")  # 100 %: image pixels as they are
        assert page.evaluate("document.querySelector('#viewer-img').getBoundingClientRect().width") == it["width"]
        page.screenshot(path=str(tmp_path / "viewer.png"))
        if os.environ.get("COEX_VIEWER_SHOT"):
            shutil.copy(tmp_path / "viewer.png", os.environ["COEX_VIEWER_SHOT"])
        page.keyboard.press("Escape")
        page.wait_for_selector("#viewer.hidden", state="attached")
        # the image's position on the map opens it too
        x, y = page.evaluate(f"window.coex.pagePoint({it['x']}, {it['y']})")
        page.mouse.click(x, y)
        page.wait_for_selector("#viewer:not(.hidden)")
    assert not errors, errors


def test_a_by_time_request_names_the_image_that_answered_it(browser: Any) -> None:
    """"previous" before 09:57:40 is answered by image #0 (taken 09:56:40): the command says
    so, and that image's card is marked."""
    from coex_core.channel.events import CommandResult

    state = ConsoleState(schedules={0: Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)})
    feed_sample(state, t0=T0)
    sent: list[m.Message] = []
    hub = ConsoleHub(state, sent.append, lambda: T0)
    errors: list[str] = []
    with serve(hub, "127.0.0.1", 0) as srv:
        page = browser.new_page(bypass_csp=True, viewport={"width": 1280, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(srv.url)
        page.wait_for_function("window.coex && window.coex.updates > 0", timeout=WAIT)
        page.wait_for_selector('#gallery .card[data-image="0"]', timeout=WAIT)
        page.fill("#img-time", "09:57:40")
        page.click('.img-time-btn[data-dir="previous"]')
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 1",
                               timeout=WAIT)
        (asked,) = sent
        hub.update(lambda st: st.apply_event(CommandResult(T0 + 5, asked.command_id,
                                                           m.AckStatus.ACCEPTED, asked)))
        page.wait_for_selector('#commands li[data-status="accepted"] .answer', timeout=WAIT)
        text = page.inner_text('#commands li[data-status="accepted"]')
        assert "answered by image #0 taken 09:56:40" in text, text
        page.wait_for_selector('#gallery .card.answer[data-image="0"]', timeout=WAIT)
        assert page.locator("#gallery .card.answer").count() == 1
        page.close()
    assert not errors, errors


def test_a_region_over_unsurveyed_ground_waits_then_fills(browser: Any, tmp_path: Path) -> None:
    """A region asked where the vehicle has not surveyed yet shows "waiting for data" (the
    request stands on the vehicle), then "in flight" and "filled" when its subgrids arrive; the
    bar says the size sent (whole 8 m subgrids), not only the size drawn."""
    import numpy as np

    from coex_apps.console.testing import drain
    from coex_plugins.bathymetry import BathymetrySender, encode_subgrid

    uri = f"loopback://roi-{uuid.uuid4().hex[:8]}?rate=100000&mtu=1024"
    app = build_topside(uri, "127.0.0.1", 0, schedule=SCHEDULE)
    app.node.receiver("bathymetry").auto_fill = False  # only the operator's request
    vehicle = VehicleEnd(uri)
    app.start()
    errors: list[str] = []
    try:
        now = time.time()
        bathy = BathymetrySender({"send_delay": 0.0, "levels": 4})
        bathy.ingest(survey_points(), now)
        vehicle.send(drain(bathy, now))
        page = browser.new_page(bypass_csp=True, viewport={"width": 1280, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(app.url)
        page.wait_for_function("window.coex && window.coex.connected && document.querySelectorAll('#levels-table tbody tr').length >= 3",
                               timeout=WAIT)
        # a 20 x 12 m box east of the survey: 3 x 2 subgrids of 8 m are asked (24 x 16 m)
        page.click("#draw-btn")
        a = page.evaluate("window.coex.pagePoint(170, 30)")
        b = page.evaluate("window.coex.pagePoint(190, 18)")
        page.mouse.move(a[0], a[1])
        page.mouse.down()
        page.mouse.move(b[0], b[1])
        page.mouse.up()
        page.select_option("#roi-level", "0")
        desc = page.inner_text("#roi-desc")
        times = "\u00d7"
        assert f"drawn 20 {times} 12 m" in desc and f"asks 24 {times} 16 m (3 {times} 2 subgrids of 8 m)" in desc, desc
        page.click("#roi-send")
        req = vehicle.wait_for(m.MapRoiRequest)
        while (req.level, req.w, req.h) != (0, 3, 2):  # the receiver's own gap filling
            req = vehicle.wait_for(m.MapRoiRequest)
        # the page learns of the command by the server's next push: wait for it, not read at once
        # (read at once it raced the push under `pytest -n 4`: "No command sent yet.")
        page.wait_for_function("document.querySelector('#commands').innerText.includes('24 x 16 m at (168, 16) m')",
                               timeout=WAIT)
        # not surveyed yet: the request stands on the vehicle
        vehicle.send([m.MapRoiReply(req.request_id, 0, 0, 6)])
        page.wait_for_function("window.coex.S.map.requests.some(r => r.state === 'waiting for data')",
                               timeout=WAIT)
        page.wait_for_function("document.querySelector('#commands').innerText.includes('6 subgrids not surveyed yet')", timeout=WAIT)
        # surveyed now: the vehicle queues them, they arrive, and it has nothing newer
        vehicle.send([m.MapRoiReply(req.request_id, 0, 6, 0)])
        page.wait_for_function("window.coex.S.map.requests.some(r => r.state === 'in flight')", timeout=WAIT)
        yy, xx = np.mgrid[0:8, 0:8]
        sgs = [encode_subgrid(-450 + xx + yy, np.ones((8, 8), bool), level=0, ix=ix, iy=iy,
                              stamp=to_stamp(time.time()), resolution=1.0, vertical_resolution=0.1)
               for ix in range(req.x0, req.x0 + 3) for iy in range(req.y0, req.y0 + 2)]
        vehicle.send([*sgs, m.MapRoiReply(req.request_id, 0, 0, 0)])
        page.wait_for_function("window.coex.S.map.requests.some(r => r.state === 'filled')", timeout=WAIT)
        page.wait_for_function("document.querySelector('#commands').innerText.includes('filled (6 subgrids)')", timeout=WAIT)
        page.wait_for_timeout(300)
        page.screenshot(path=str(tmp_path / "roi.png"))
        if os.environ.get("COEX_ROI_SHOT"):
            shutil.copy(tmp_path / "roi.png", os.environ["COEX_ROI_SHOT"])
        page.close()
    finally:
        app.close()
        vehicle.transport.close()
    assert not errors, errors


def _link_history(state: ConsoleState) -> None:
    """Twenty minutes of modem reports and received statuses on link 0 (SNR falling)."""
    for k in range(40):
        t = T0 - 590 + 15 * k
        state.apply_message(m.LinkStatus(to_stamp(t), 0, 3, 1 if k % 7 == 0 else 0,
                                         float(14 - k * 0.2), 0.1), t, 0)
        state.apply_message(m.VehicleStatus(to_stamp(t), 5.0, 5.0, 40.0, 20.0, 90.0, 1.5, 80,
                                            m.VehicleMode.SURVEY, 0), t, 0)


def test_the_link_has_throughput_and_snr_plots_and_counters_in_words(browser: Any, tmp_path: Path) -> None:
    """Throughput (bytes per cycle) and SNR are drawn over dive time with axis labels, and the
    counters of the link and queue tables are words a non-expert reads."""
    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors, prepare=_link_history) as page:
        page.set_viewport_size({"width": 1280, "height": 1000})
        page.wait_for_selector('#link-plots canvas[data-plot="throughput"][data-xticks]', timeout=WAIT)
        for kind, ylabel in (("throughput", "bytes / cycle"), ("snr", "SNR (dB)")):
            cv = page.query_selector(f'#link-plots canvas[data-plot="{kind}"]')
            assert cv is not None and cv.is_visible(), kind
            assert cv.get_attribute("data-ylabel") == ylabel
            assert cv.get_attribute("data-xlabel") == "dive time"
            ticks = json.loads(cv.get_attribute("data-xticks") or "[]")
            assert len(ticks) >= 3 and any("min" in t for t in ticks), ticks
        th = page.evaluate("window.coex.S.link.links[0].throughput")
        assert len(th) >= 10 and all(b[1] > 0 for b in th), th
        row = page.inner_text('#links-table tr[data-link="0"]')
        assert "packets heard" in row and "frames" in row and "garbled" in row, row
        assert "signal" in row, row
        q = page.inner_text('#queues-table tr[data-stream="3"]')
        assert "dropped in the last report" in q and "in all" in q, q
        page.screenshot(path=str(tmp_path / "link.png"), full_page=True)
        if os.environ.get("COEX_LINK_SHOT"):
            shutil.copy(tmp_path / "link.png", os.environ["COEX_LINK_SHOT"])
    assert not errors, errors


def test_a_stale_time_series_says_so_and_its_axis_has_dive_time_ticks(browser: Any) -> None:
    """Fresh series carry no warning; ten minutes without a new sample, each plot says "no new
    samples for 10 min"; the time axis is ticked in dive time, not two end labels."""
    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors) as page:
        page.set_viewport_size({"width": 1280, "height": 1000})
        page.wait_for_selector("#series canvas[data-xticks]", timeout=WAIT)
        assert page.eval_on_selector_all("#series .plot[data-stale]", "els => els.length") == 0
        ticks = json.loads(page.get_attribute("#series canvas", "data-xticks") or "[]")
        assert len(ticks) >= 4, ticks
        assert page.get_attribute("#series canvas", "data-xlabel") == "dive time"

    def later(state: ConsoleState) -> None:
        state.now = T0 + 600  # ten minutes on, nothing new
    with sample_console(browser, ConsoleHub, [], errors, prepare=later) as page:
        page.wait_for_selector("#series .plot[data-stale]", timeout=WAIT)
        words = page.eval_on_selector_all("#series .plot", "els => els.map(e => e.dataset.stale)")
        assert words and all(w and w.startswith("no new samples for 10 min") for w in words), words
        assert "no new samples for 10 min" in page.inner_text("#series")
    assert not errors, errors


def test_the_header_says_when_contact_is_lost_or_ended_and_the_page_fits_a_wide_screen(browser: Any, tmp_path: Path) -> None:
    """"live" while statuses come; "no contact for 10 min" once they stop; "ended" after the
    dive. The vehicle's mode is the one it reports. At 1600 x 1000 the queue table and the
    commands are above the fold; the TDMA timeline is drawn at its natural aspect."""
    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors, prepare=_link_history) as page:
        page.set_viewport_size({"width": 1600, "height": 1000})
        page.wait_for_function("document.querySelector('#conn').textContent === 'live'", timeout=WAIT)
        assert "reports SURVEY" in page.inner_text("#vehicle-status")
        for sel in ("#queues-table", "#commands", "#links-table", "#series canvas"):
            box = page.locator(sel).first.bounding_box()
            assert box is not None and box["y"] + min(box["height"], 60) <= 1000, (sel, box)
        # nothing wider than its panel (the queue buttons are on screen)
        for sel in ("#link-panel", "#images-panel", "#series-panel", "#log-panel"):
            over = page.evaluate(f"(e => e.scrollWidth - e.clientWidth)(document.querySelector('{sel}'))")
            assert over <= 1, (sel, over)
        flush = page.locator('#queues-table tr[data-stream="3"] button', has_text="Flush").bounding_box()
        panel = page.locator("#link-panel").bounding_box()
        assert flush["x"] + flush["width"] <= panel["x"] + panel["width"], (flush, panel)
        cv = page.locator("#tdma canvas").first
        ratio = page.evaluate("(c => c.getBoundingClientRect().height / c.height)(document.querySelector('#tdma canvas'))")
        assert ratio == pytest.approx(1.0, abs=0.02)
        assert cv.bounding_box()["width"] == pytest.approx(page.evaluate(
            "document.querySelector('#tdma canvas').width"), abs=1)
        page.screenshot(path=str(tmp_path / "wide.png"))
        if os.environ.get("COEX_WIDE_SHOT"):
            shutil.copy(tmp_path / "wide.png", os.environ["COEX_WIDE_SHOT"])

    def silent(state: ConsoleState) -> None:
        state.now = T0 + 600  # no status for ten minutes
    with sample_console(browser, ConsoleHub, [], errors, prepare=silent) as page:
        page.wait_for_function("document.querySelector('#conn').textContent.startsWith('no contact for')",
                               timeout=WAIT)
        assert page.inner_text("#conn") == "no contact for 10 min"

    def over(state: ConsoleState) -> None:
        state.end_contact(T0 + 5, "the dive is over")
    with sample_console(browser, ConsoleHub, [], errors, prepare=over) as page:
        page.wait_for_function("document.querySelector('#conn').textContent.startsWith('ended')",
                               timeout=WAIT)
        assert page.inner_text("#conn") == "ended: the dive is over"
    assert not errors, errors


def _picture_point(page: Any, x: float, y: float) -> tuple[float, float]:
    """Where image pixel (x, y) is on the page: the viewer's <img> box, less the bars that
    ``object-fit: contain`` leaves around the picture (computed here, not by the page)."""
    b = page.locator("#viewer-img").bounding_box()
    nw, nh, fit = page.evaluate("[document.querySelector('#viewer-img').naturalWidth, "
                                "document.querySelector('#viewer-img').naturalHeight, "
                                "document.querySelector('#viewer-img').classList.contains('fit')]")
    k = min(b["width"] / nw, b["height"] / nh) if fit else 1.0
    left = b["x"] + (b["width"] - nw * k) / 2
    top = b["y"] + (b["height"] - nh * k) / 2
    return left + x * k, top + y * k


def _drag(page: Any, a: tuple[float, float], b: tuple[float, float]) -> None:
    page.mouse.move(*a)
    page.mouse.down()
    page.mouse.move((a[0] + b[0]) / 2, (a[1] + b[1]) / 2)
    page.mouse.move(*b)
    page.mouse.up()


def test_an_image_region_dragged_in_the_viewer_is_asked_and_outlined(browser: Any, tmp_path: Path) -> None:
    """The Region tool of the full-size viewer: a rectangle dragged on the (scaled) picture is
    asked in image pixels at 30 dB (300 on the wire), outlined on the picture and on the card's
    thumbnail with its state, at any zoom; the vehicle's refusal shows with its reason."""
    from coex_core.channel.events import CommandResult

    sent: list[m.Message] = []
    errors: list[str] = []
    hubs: list[ConsoleHub] = []
    with sample_console(browser, ConsoleHub, sent, errors, hubs=hubs) as page:
        (hub,) = hubs
        page.wait_for_function(
            "[...document.querySelectorAll('#gallery .card img')].filter(i => i.naturalWidth > 0).length === 3",
            timeout=WAIT)
        page.click('#gallery .card[data-image="1"] img')
        page.wait_for_selector("#viewer:not(.hidden)")
        page.wait_for_function("document.querySelector('#viewer-img').naturalWidth > 0", timeout=WAIT)
        assert page.is_visible("#region-draw") and page.is_disabled("#region-send")

        # drag from image pixel (100, 60) to (20, 10) on the picture shown about 5x
        page.click("#region-draw")
        _drag(page, _picture_point(page, 100, 60), _picture_point(page, 20, 10))
        assert "80 \u00d7 50 px" in page.inner_text("#region-box")  # 80 x 50
        assert page.input_value("#region-value") == "30"
        page.click("#region-send")
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 1",
                               timeout=WAIT)
        (asked,) = sent
        assert isinstance(asked, m.ImageRegionRequest), asked
        assert (asked.image_id, asked.kind, asked.value) == (1, m.RegionGoal.QUALITY, 300)
        for got, want in zip((asked.x0, asked.y0, asked.x1, asked.y1), (20, 10, 100, 60)):
            assert abs(got - want) <= 2, asked
        assert "image 1 region" in page.inner_text("#commands") and "to 30 dB" in page.inner_text("#commands")

        # outlined where it was drawn, with its state in words, on the picture and the thumbnail
        outline = page.locator('#viewer-overlay .iregion[data-state="requested"]')
        outline.wait_for(timeout=WAIT)

        def placed(loc: Any, box: tuple[int, int, int, int]) -> None:
            b = loc.bounding_box()
            x0, y0 = _picture_point(page, box[0], box[1])
            x1, y1 = _picture_point(page, box[2], box[3])
            assert abs(b["x"] - x0) <= 3 and abs(b["y"] - y0) <= 3, (b, x0, y0)
            assert abs(b["x"] + b["width"] - x1) <= 3 and abs(b["y"] + b["height"] - y1) <= 3, (b, x1, y1)

        box = (asked.x0, asked.y0, asked.x1, asked.y1)
        placed(outline, box)
        assert "requested" in page.inner_text("#viewer-overlay")
        assert page.locator('#gallery .card[data-image="1"] svg.thumb-regions rect').count() == 1

        # a second one within a byte budget, then the vehicle refuses the first
        page.click("#region-draw")
        _drag(page, _picture_point(page, 110, 70), _picture_point(page, 150, 110))
        page.select_option("#region-kind", "bytes")
        assert page.input_value("#region-value") == "2000"
        page.click("#region-send")
        page.wait_for_function("document.querySelectorAll('#commands li[data-status]').length === 2",
                               timeout=WAIT)
        assert (sent[1].kind, sent[1].value) == (m.RegionGoal.BYTES, 2000)
        hub.update(lambda st: st.apply_event(CommandResult(T0 + 5, asked.command_id,
                                                           m.AckStatus.REJECTED, asked)))
        hub.update(lambda st: st.apply_event(CommandResult(T0 + 6, sent[1].command_id,
                                                           m.AckStatus.ACCEPTED, sent[1])))
        page.wait_for_selector('#region-list li[data-state="rejected"] .why', timeout=WAIT)
        assert "coded without precincts" in page.inner_text('#region-list li[data-state="rejected"]')
        assert page.locator('#viewer-overlay .iregion[data-state="accepted"]').count() == 1
        page.screenshot(path=str(tmp_path / "region.png"))
        if os.environ.get("COEX_REGION_SHOT"):
            shutil.copy(tmp_path / "region.png", os.environ["COEX_REGION_SHOT"])

        # at 100 % the outline follows the picture
        page.click("#viewer-zoom")
        page.wait_for_function("!document.querySelector('#viewer-img').classList.contains('fit')")
        placed(page.locator('#viewer-overlay .iregion[data-state="rejected"]'), box)
        page.close()
    assert not errors, errors


def test_the_region_tool_shows_the_crop_that_answered_a_region(browser: Any, tmp_path: Path) -> None:
    """A region the vehicle served as a crop (the region coded on its own): the viewer's picture
    is the image with the crop pasted over it, the region's outline is accepted, and the list
    beside it says "crop", its bytes, and shows the crop itself."""
    from coex_plugins.imagery import codec
    from coex_plugins.imagery.sim import region_transfer
    from coex_plugins.imagery.synth import seafloor

    frame = seafloor(240, 320, seed=4)
    box = (0, 0, 160, 120)
    run = region_transfer(frame, box, "quality", 35.0, mtu=128, base="layer:1")
    assert run.crop is not None and run.region["served"] == "crop"
    crop_id = run.crop.image_id

    def regions(state: ConsoleState) -> None:
        state.images.clear()  # only the image with its region
        for p in run.receiver.products():
            state.apply_product("imagery", p, T0)

    errors: list[str] = []
    hubs: list[ConsoleHub] = []
    with sample_console(browser, ConsoleHub, [], errors, prepare=regions, hubs=hubs) as page:
        (hub,) = hubs
        page.wait_for_selector('#gallery .card[data-image="0"] img', timeout=WAIT)
        assert page.locator("#gallery .card").count() == 1  # the crop is not an image of the gallery
        page.click('#gallery .card[data-image="0"] img')
        page.wait_for_selector("#viewer:not(.hidden)")
        page.wait_for_function("document.querySelector('#viewer-img').naturalWidth === 320", timeout=WAIT)
        item = page.locator('#region-list li[data-served="crop"]')
        item.wait_for(timeout=WAIT)
        text = item.inner_text()
        size = len(run.crop.enc.body)
        assert "crop 160 \u00d7 120 px" in text and f"{size} B of {size} B" in text and "shown over the picture" in text
        page.wait_for_function("document.querySelector('#region-list img.region-crop').naturalWidth === 160",
                               timeout=WAIT)
        assert page.locator('#viewer-overlay .iregion[data-state="accepted"]').count() == 1
        assert "accepted · crop" in page.locator("#viewer-overlay .iregion-label").first.inner_text()
        # the picture served is the image as topside shows it: the crop pasted over it
        with hub.lock:
            png = hub.state.image_png(0, full=True)
            crop_png = hub.state.crop_png(crop_id)
        import io

        from PIL import Image

        shown = np.asarray(Image.open(io.BytesIO(png)).convert("L"))
        np.testing.assert_array_equal(shown, run.receiver.image(0))
        assert codec.psnr(shown[:120, :160], frame[:120, :160]) >= 35.0
        np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(crop_png)).convert("L")), shown[:120, :160])
        page.screenshot(path=str(tmp_path / "crop.png"))
        if os.environ.get("COEX_CROP_SHOT"):
            shutil.copy(tmp_path / "crop.png", os.environ["COEX_CROP_SHOT"])
    assert not errors, errors


def test_the_region_tool_says_why_an_image_without_precincts_has_none(browser: Any) -> None:
    """An image coded without precincts cannot send a region on its own: the viewer's Region
    tool is off and says so, and asks the operator for more of the whole image instead."""
    def no_precincts(state: ConsoleState) -> None:
        state.images[2].decoded_meta["precincts"] = 0

    errors: list[str] = []
    with sample_console(browser, ConsoleHub, [], errors, prepare=no_precincts) as page:
        page.wait_for_selector('#gallery .card[data-image="2"] img', timeout=WAIT)
        page.click('#gallery .card[data-image="2"] img')
        page.wait_for_selector("#viewer:not(.hidden)")
        page.wait_for_selector("#region-off:not(.hidden)")
        assert "coded without precincts" in page.inner_text("#region-off")
        assert "whole image" in page.inner_text("#region-off")
        assert not page.is_visible("#region-draw") and not page.is_visible("#region-send")
        page.keyboard.press("Escape")
        page.click('#gallery .card[data-image="1"] img')  # another image has the tool
        page.wait_for_selector("#region-draw", state="visible")
        assert not page.is_visible("#region-off")
    assert not errors, errors


def test_survey_outcomes_read_apart_with_their_history_in_the_vehicles_order(browser: Any, tmp_path: Path) -> None:
    """Seven surveys end seven ways, as the vehicle reports them over the link to a ``coex
    topside`` page: refused by the autopilot (its code and name), no answer from it (the tries),
    taken over by a pilot, a helm restart, an all-stop, completed, and refused by the geofence.
    Each row says which, in words; a refusal is not mistaken for no answer. The completed one's
    reports arrive out of order: its history, opened with a click, is in the vehicle's time
    order. A stream dropping a message every few seconds takes one counted line in the event
    log, not sixty. ``COEX_OUTCOME_SHOT=path.png`` keeps the screenshot."""
    from coex_apps.console.testing import drain
    from coex_core.channel.events import Dropped
    from coex_plugins.bathymetry import BathymetrySender

    uri = f"loopback://outcomes-{uuid.uuid4().hex[:8]}?rate=100000&mtu=1024"
    app = build_topside(uri, "127.0.0.1", 0, schedule=SCHEDULE)
    vehicle = VehicleEnd(uri)
    app.start()
    errors: list[str] = []
    try:
        now = time.time()
        bathy = BathymetrySender({"send_delay": 0.0, "levels": 4})
        bathy.ingest(survey_points(), now)
        vehicle.send([m.VehicleStatus(to_stamp(now), 30.0, 20.0, 45.0, 20.0, 90.0, 1.5, 77,
                                      m.VehicleMode.SURVEY, 0), *drain(bathy, now)])
        page = browser.new_page(bypass_csp=True, viewport={"width": 1600, "height": 1000})
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(app.url)
        page.wait_for_function("window.coex && window.coex.connected && window.coex.updates > 0",
                               timeout=WAIT)
        rx = app.node.receiver("survey")
        with app.hub.lock:
            cmds = [rx.request("line", 8.0 + 12.0 * k, 10.0 + 4.0 * k, now, heading=0.0, length=40.0, altitude=5.0)
                    for k in range(6)]
            cmds.append(rx.request("line", 0.0, 0.0, now, heading=0.0, length=900.0, altitude=5.0))
        for _ in cmds:
            vehicle.wait_for(m.SurveyCommand)
        ids = [c.survey_id for c in cmds]
        R, S = m.SurveyReason, m.SurveyState

        def status(k: int, state: m.SurveyState, dt: float, reason: m.SurveyReason = R.NONE, index: int | None = None,
                   value: float | None = None, detail: str | None = None) -> m.SurveyStatus:
            return m.SurveyStatus(ids[k], state, reason, to_stamp(now + dt), index, value, detail)

        vehicle.send([m.CommandAck(c.command_id, m.AckStatus.ACCEPTED) for c in cmds[:6]]
                     + [m.CommandAck(cmds[6].command_id, m.AckStatus.REJECTED)])
        vehicle.send([
            status(0, S.REJECTED, 2, R.AUTONOMY_REFUSED, None, 14.0, "MAV_MISSION_DENIED"),
            status(1, S.REJECTED, 12, R.AUTONOMY_NO_ANSWER, None, 6.0, "MISSION_COUNT unanswered, no heartbeat heard"),
            status(2, S.STARTED, 2, index=0), status(2, S.ABORTED, 20, R.MANUAL_OVERRIDE, None, 2.0,
                                                      "left AUTO for ALT_HOLD"),
            status(3, S.STARTED, 2, index=0), status(3, S.ABORTED, 30, R.AUTONOMY_RESTARTED),
            status(4, S.STARTED, 2, index=0), status(4, S.ABORTED, 40, R.ALL_STOP, None, None, "MissingDecVars:depth"),
            status(6, S.REJECTED, 1, R.OUTSIDE_GEOFENCE, 1, 400.0),
        ])
        # the completed one: its end first, the states before it late (lost frames re-sent)
        vehicle.send([status(5, S.COMPLETED, 60)])
        vehicle.send([status(5, S.STARTED, 40, index=1), status(5, S.STARTED, 20, index=0)])
        # a stream dropping superseded messages every few seconds: stream 61, one no node here
        # uses. It was stream 2, the nodes' control stream, whose own superseded requests are
        # counted into the same line; once, under `pytest -n 4`, the page never read "60
        # dropped" in 60 s (the likely cause, not shown)
        for k in range(60):
            app.hub.update(lambda st, k=k: st.apply_event(Dropped(now + 5.0 * k, 61, "superseded")))

        def row(k: int) -> str:
            return _surveys_row(page, ids[k])

        page.wait_for_function(
            "(() => { const r = document.querySelector('" + row(5) + "');"
            " return r && r.dataset.state === 'completed'; })()", timeout=WAIT)
        page.wait_for_function(
            "[...document.querySelectorAll('#surveys-table tr[data-survey]')]"
            ".filter(r => !['requested', 'accepted', 'started'].includes(r.dataset.state)).length === 7",
            timeout=WAIT)
        expect = [
            ("refused by autonomy", "the vehicle's autonomy refused it (code 14): MAV_MISSION_DENIED"),
            ("no answer from autonomy", "no answer from the vehicle's autonomy (after 6 tries): MISSION_COUNT "
                                        "unanswered, no heartbeat heard"),
            ("taken over", "taken over on the vehicle (manual override): left AUTO for ALT_HOLD"),
            ("autonomy restarted", "the vehicle's autonomy restarted and dropped it"),
            ("all-stop", "the vehicle's autonomy stopped all motion: MissingDecVars:depth"),
            ("completed", "40 m, heading 0°, altitude 5 m"),
            ("rejected", "waypoint 1 is 400 m outside the geofence"),
        ]
        for k, (outcome, words) in enumerate(expect):
            assert page.get_attribute(row(k), "data-outcome") == outcome, k
            text = page.inner_text(row(k))
            assert outcome in text and words in text, (k, text)
        assert "refused" not in page.inner_text(row(1))  # no answer is not a refusal
        assert "refused" in page.inner_text(row(0))

        # the history of the completed survey, opened under its row: the vehicle's order
        page.click(row(5))
        hist = f'#surveys-table tr[data-history="{ids[5]}"] li'
        page.wait_for_selector(hist, timeout=WAIT)
        lines = page.eval_on_selector_all(hist, "els => els.map(e => e.textContent)")
        assert [ln.split(" ", 1)[1].split(":")[0] for ln in lines] == [
            "requested", "accepted", "started", "started", "completed"], lines
        assert "heading for waypoint 0" in lines[2] and "heading for waypoint 1" in lines[3], lines

        # sixty drops: one counted line, and the events that matter still listed
        page.wait_for_function("document.querySelector('#log').textContent.includes('stream 61: 60 dropped')",
                               timeout=WAIT)
        log = page.eval_on_selector_all("#log li", "els => els.map(e => e.textContent)")
        drops = [ln for ln in log if "stream 61:" in ln]
        assert len(drops) == 1 and "stream 61: 60 dropped (superseded) in 4 min 55 s" in drops[0], drops
        assert any("no answer from autonomy" in ln for ln in log), log
        page.wait_for_timeout(300)
        shot = tmp_path / "outcomes.png"
        page.screenshot(path=str(shot), full_page=True)
        if os.environ.get("COEX_OUTCOME_SHOT"):
            shutil.copy(shot, os.environ["COEX_OUTCOME_SHOT"])
            page.locator("#map-panel").screenshot(path=os.environ["COEX_OUTCOME_SHOT"].replace(".png", "-map.png"))
        page.close()
    finally:
        app.close()
        vehicle.transport.close()
    assert not errors, errors


def test_the_vehicles_detections_show_on_the_map_as_suggestions(browser: Any, tmp_path: Path) -> None:
    """Detections (what the vehicle's own detectors found) are drawn on the map apart from the
    candidate targets, labelled as the vehicle's suggestions with their measures, named in the
    legend, logged once each, and a double-click on one selects the region around it."""
    errors: list[str] = []

    def prepare(state: ConsoleState) -> None:
        state.apply_message(m.Detection(3, m.DetectionSource.MAP, to_stamp(T0 - 30), 40.0, 40.0, 0.87, 1.5, 4.6,
                                        1.8, 30.0, 8), T0 - 20)
        state.apply_message(m.Detection(4, m.DetectionSource.MAP, to_stamp(T0 - 30), 70.0, 30.0, 0.12, 0.9, 2.2,
                                        2.0, 100.0, 4), T0 - 20)
        state.apply_message(m.Detection(3, m.DetectionSource.MAP, to_stamp(T0 - 10), 40.2, 40.1, 0.9, 1.5, 4.6,
                                        1.8, 32.0, 8), T0 - 5)  # a newer version of the first

    with sample_console(browser, ConsoleHub, [], errors, prepare) as page:
        page.wait_for_function("window.coex.detections && window.coex.detections.length === 2", timeout=WAIT)
        shown = {d["id"]: d for d in page.evaluate("window.coex.detections")}
        assert shown[3]["text"] == "suggested D3: score 0.90 1.5 m high 4.6\u00d71.8 m"
        assert shown[4]["text"].startswith("suggested D4: score 0.12")
        assert "vehicle's detection (suggestion)" in page.inner_text(".legend")
        log = page.inner_text("#log")
        assert log.count("the vehicle suggests a detection") == 2, log
        assert "(40, 40), 1.5 m high, 4.6 x 1.8 m, score 0.87 (detection 3, in its map)" in log
        page.screenshot(path=str(tmp_path / "detections.png"))
        if os.environ.get("COEX_DETECTIONS_SHOT"):
            shutil.copy(tmp_path / "detections.png", os.environ["COEX_DETECTIONS_SHOT"])
        page.mouse.dblclick(*_on_canvas(page, shown[4]["x"], shown[4]["y"]))
        page.wait_for_selector("#roi-bar:not(.hidden)", timeout=WAIT)
    assert not errors, errors


def _on_canvas(page: Any, x: float, y: float) -> tuple[float, float]:
    """Page coordinates of canvas pixel (x, y)."""
    box = page.evaluate("""(() => { const c = document.querySelector('#map-canvas');
        const r = c.getBoundingClientRect(); return [r.left, r.top, r.width / c.width, r.height / c.height]; })()""")
    return box[0] + x * box[2], box[1] + y * box[3]

"""The console shows the navigation's uncertainty (issue 56): the ship's USBL fixes, the vehicle's
raw (dead-reckoned) and corrected tracks, and the correction's size and age, in a real headless
browser (Debian chromium driven by Playwright, as ``tests/test_console_browser.py``)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from coex_apps.console import ConsoleHub, ConsoleState
from coex_plugins.navigation import Navigation

from .test_console_browser import T0, browser, sample_console  # noqa: F401  (browser: the fixture)

#: pixels of the colour the page draws the corrected track in (#5fd3a6) and the fixes in
COUNT = """((rgb, tol) => {
    const c = document.querySelector('#map-canvas');
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < d.length; i += 4)
      if (Math.abs(d[i] - rgb[0]) <= tol && Math.abs(d[i+1] - rgb[1]) <= tol && Math.abs(d[i+2] - rgb[2]) <= tol) n++;
    return n; })"""


def _navigation(state: ConsoleState) -> Navigation:
    """Topside's navigation over the sample dive: the vehicle's received track is its own
    (drifting) one; the ship's fixes see it where it truly was (the drift grows from 2 to 6 m
    east and 1 to 3 m south), 2 m of noise, two wild fixes."""
    nav = Navigation()
    rng = np.random.default_rng(4)
    track = np.array([(t, x, y) for t, x, y, _d in state.track])
    t0, t1 = track[0, 0], track[-1, 0]
    from coex import to_stamp
    from coex.messages import VehicleMode, VehicleStatus

    for t, x, y in track:  # received as statuses (Navigation.track is what topside received)
        nav.status(state.vehicle_id, VehicleStatus(to_stamp(float(t)), float(x), float(y), 0.0, None, float("nan"), 0.0, 100,
                                                   VehicleMode(0), 0), float(t))
    for k, t in enumerate(np.arange(t0, t1, 10.0)):
        f = (t - t0) / (t1 - t0)
        bx, by = np.interp(t, track[:, 0], track[:, 1]), np.interp(t, track[:, 0], track[:, 2])
        true = np.array([bx - (2 + 4 * f), by + (1 + 2 * f)]) + rng.normal(0.0, 2.0, 2)
        if k in (7, 31):
            true += 40.0  # wild
        nav.fix(_nav(float(t), float(true[0]), float(true[1])), state.vehicle_id)
    return nav


def _nav(t: float, x: float, y: float) -> Any:
    from coex import Nav

    return Nav(t, x=x, y=y)


def test_the_console_shows_usbl_fixes_both_tracks_and_the_corrections_size_and_age(
        browser: Any, tmp_path: Path) -> None:  # noqa: F811
    errors: list[str] = []

    def prepare(state: ConsoleState) -> None:
        state.navigation = _navigation(state)
        state.navigation_changed()

    with sample_console(browser, ConsoleHub, [], errors, prepare) as page:
        page.wait_for_function("window.coex && !document.querySelector('#nav-status').classList.contains('hidden')",
                               timeout=10_000)
        text = page.inner_text("#nav-status")
        assert text.startswith("Navigation corrected: correction ") and "m (east " in text, text
        assert "newest fix used" in text and "USBL fixes, 2 rejected as wild" in text, text
        nav = page.evaluate("S.navigation")
        assert nav["correction"]["size"] > 4.0 and len(nav["raw_track"]) == len(nav["corrected_track"]) > 10
        assert sum(1 for f in nav["fixes"] if f[4]) == 2
        page.wait_for_timeout(300)
        shot = tmp_path / "navigation.png"
        page.screenshot(path=str(shot), full_page=True)
        if os.environ.get("COEX_NAVIGATION_SHOT"):
            shutil.copy(shot, os.environ["COEX_NAVIGATION_SHOT"])
        green = page.evaluate(f"{COUNT}([95, 211, 166], 20)")
        red = page.evaluate(f"{COUNT}([239, 95, 95], 20)")
        assert green > 50, green  # the corrected track is drawn
        page.click("#show-usbl")  # off: the overlay goes
        page.wait_for_timeout(200)
        assert page.evaluate(f"{COUNT}([95, 211, 166], 20)") < green / 5
        assert page.evaluate(f"{COUNT}([239, 95, 95], 20)") <= red
    assert not errors, errors

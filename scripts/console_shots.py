#!/usr/bin/env python3
"""Screenshots of the console during a quick demo dive: ``python scripts/console_shots.py OUT``.

Runs ``coex demo --quick --gui`` (the scripted operator, so that regions and camera lines are
asked), opens the console in headless Chromium at 1280 px wide and writes five full-page
screenshots into OUT:

1. ``1-survey.png``: during the survey, the map filling in;
2. ``2-regions.png``: after the first region requests;
3. ``3-camera.png``: at the camera pass (a camera line started);
4. ``4-image.png``: an image opened full size in the viewer;
5. ``5-after.png``: after the dive.

docs/console.md ("Screenshots of a dive") says what each one shows. Needs ``/usr/bin/chromium``
and the ``playwright`` package (never ``playwright install``).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

#: what the page holds, for deciding the moments
PROBE = """(() => {
  const S = window.coex.S, v = S.vehicle && S.vehicle.status;
  const t0 = S.vehicle && S.vehicle.track.length ? S.vehicle.track[0][0] : null;
  return {
    dive: t0 === null ? 0 : S.now - t0,
    levels: S.map ? S.map.levels.length : 0,
    requests: S.map ? S.map.requests.length : 0,
    started: ((S.surveys && S.surveys.items) || []).filter(s => s.state === 'started').length,
    images: ((S.images && S.images.items) || []).filter(i => i.full).map(
      i => [i.image_id, i.fraction || 0]),
    altitude: v ? v.altitude : null,
    ended: !!(S.vehicle && S.vehicle.ended),
  };
})()"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="directory for the screenshots")
    ap.add_argument("--speed", type=float, default=40.0,
                    help="simulated seconds per second (default 40: the 50-minute quick dive takes "
                         "75 s)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=900)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="coex-shots-") as tmp:
        cmd = [sys.executable, "-m", "coex_core.cli", "demo", "--quick", "--gui", "--operator", "script",
               "--http", "127.0.0.1:0", "--speed", str(args.speed), "--quiet", "--out", tmp]
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        url = None
        over = threading.Event()
        try:
            assert proc.stderr is not None
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline and url is None:
                line = proc.stderr.readline()
                if not line and proc.poll() is not None:
                    break
                found = re.search(r"web console at (http://\S+)", line)
                if found:
                    url = found.group(1).rstrip("/")
            if url is None:
                print("the demo did not announce its console", file=sys.stderr)
                return 1

            def drain() -> None:  # keep reading stderr: the demo never blocks on a full pipe
                assert proc.stderr is not None
                for line in proc.stderr:
                    if "the dive is over" in line:
                        over.set()
            threading.Thread(target=drain, daemon=True).start()
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
                page = browser.new_page(viewport={"width": args.width, "height": args.height})
                page.goto(url + "/")
                _wait(page, "window.coex && window.coex.updates > 0", 30)
                shots = _take(page, args.out, over)
                browser.close()
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
    for name in shots:
        print(args.out / name)
    return 0 if len(shots) == 5 else 1


def _wait(page: Any, expression: str, seconds: float) -> None:
    """Poll ``expression`` until true. Not ``wait_for_function``: it evaluates with ``eval``,
    which the console's Content-Security-Policy forbids (the shots show the page as served)."""
    deadline = time.monotonic() + seconds
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{expression} still false after {seconds:g} s")
        page.wait_for_timeout(100)


def _shot(page: Any, out: Path, name: str, taken: list[str]) -> None:
    page.wait_for_timeout(400)  # the page draws what it just received
    page.screenshot(path=str(out / name), full_page=True)
    taken.append(name)


def _take(page: Any, out: Path, over: threading.Event) -> list[str]:
    taken: list[str] = []
    stage = 0
    regions_seen_at = None
    deadline = time.monotonic() + 900
    while time.monotonic() < deadline and stage < 4:
        st = page.evaluate(PROBE)
        if stage == 0 and st["levels"] >= 1 and (st["dive"] >= 120 or st["requests"]):
            _shot(page, out, "1-survey.png", taken)
            stage = 1
        elif stage == 1 and st["requests"]:
            # a few updates later: the requests show their state (in flight, filled ...)
            regions_seen_at = regions_seen_at or time.monotonic()
            if time.monotonic() - regions_seen_at >= 1.5:
                _shot(page, out, "2-regions.png", taken)
                stage = 2
        elif stage == 2 and ((st["started"] and st["images"]) or st["ended"]):
            _shot(page, out, "3-camera.png", taken)
            stage = 3
        elif stage == 3 and st["images"] and (max(f for _, f in st["images"]) >= 0.5 or st["ended"]):
            best = max(st["images"], key=lambda i: i[1])[0]
            page.click(f'#gallery .card[data-image="{best}"] img')
            page.wait_for_selector("#viewer:not(.hidden)")
            _wait(page, "document.querySelector('#viewer-img').naturalWidth > 0", 20)
            page.wait_for_timeout(400)
            page.screenshot(path=str(out / "4-image.png"))  # the viewer fills the window
            taken.append("4-image.png")
            page.keyboard.press("Escape")
            stage = 4
        else:
            page.wait_for_timeout(500)
    # after the dive: the console says it ended
    over.wait(timeout=max(1.0, deadline - time.monotonic()))
    _wait(page, "document.querySelector('#conn').textContent.startsWith('ended')", 60)
    _shot(page, out, "5-after.png", taken)
    return taken


if __name__ == "__main__":
    sys.exit(main())

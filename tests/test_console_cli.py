"""``coex topside``: the command serves the console over a transport URI; bad options fail cleanly."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.request
from pathlib import Path

from . import _products as typed

COEX = str(Path(sys.executable).with_name("coex"))


def test_coex_topside_serves_the_console() -> None:
    proc = subprocess.Popen([COEX, "topside", "--transport", "loopback://cli-test",
                             "--http", "127.0.0.1:0", "--slot", "5",
                             "--stream-names", "3=map,4=images"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("CoEx console on http://127.0.0.1:"), line + proc.stderr.read()
        url = line.split()[3]
        with urllib.request.urlopen(url, timeout=5) as r:
            assert r.status == 200 and b"CoEx topside" in r.read()
        with urllib.request.urlopen(url + "api/state", timeout=5) as r:
            state = json.loads(r.read())
        (sched,) = state["link"]["schedules"]
        assert [s["owner"] for s in sched["slots"]] == [1, 2, 2, 1, 2, 2]
        assert {s["duration"] for s in sched["slots"]} == {5.0}
        assert state["queues"]["streams"] == []  # nothing from a vehicle yet
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_coex_topside_bad_options() -> None:
    r = subprocess.run([COEX, "topside", "--transport", "nosuch://x", "--http", "127.0.0.1:0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "nosuch" in r.stderr
    r = subprocess.run([COEX, "topside", "--transport", "loopback://x", "--http", "nowhere"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "HOST:PORT" in r.stderr
    r = subprocess.run([COEX, "topside", "--transport", "loopback://y", "--http", "127.0.0.1:0",
                        "--schedule", "{bad json"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--schedule" in r.stderr
    r = subprocess.run([COEX, "topside", "--transport", "loopback://z", "--stream-names", "map"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "ID=NAME" in r.stderr


def test_topside_app_shows_its_own_modem_statistics() -> None:
    from coex_apps.console.cli import build_topside
    from coex_core.messages import LinkStatus
    from coex_core.timefmt import to_stamp

    now = [50_000.0]
    app = build_topside("loopback://cli-stats", "127.0.0.1", 0, modalities=(), clock=lambda: now[0])
    try:
        stats = [LinkStatus(to_stamp(now[0]), 0, 8, 1, 12.5, 0.2)]
        app.transport.link_status = lambda: stats[-1]  # as the Micromodem transport offers
        app.step()
        app.step()  # the same statistics are not counted twice
        now[0] += 10
        stats.append(LinkStatus(to_stamp(now[0]), 0, 8, 3, 7.0, None))
        app.step()
        (lk,) = app.hub.snapshot()["link"]["links"]
        assert (lk["packets"], lk["frames"], lk["bad_frames"], lk["snr"]) == (2, 16, 4, 7.0)
    finally:
        app.close()


def test_topside_with_two_modems() -> None:
    from coex_apps.console.cli import build_topside

    app = build_topside(["loopback://two-a", "loopback://two-b?mtu=128"], "127.0.0.1", 0,
                        modalities=())
    try:
        assert sorted(app.transports) == [0, 1] and app.node.manager.links == [0, 1]
        assert app.node.manager.link(1).fbytes == 128  # frames capped at that transport's MTU
        app.step()
        snap = app.hub.snapshot()["link"]
        assert [lk["link"] for lk in snap["links"]] == [0, 1]
        assert [s["link"] for s in snap["schedules"]] == [0, 1]
        app.hub.act("link_control", {"link": 1, "enabled": False})
        assert app.hub.snapshot()["commands"][0]["summary"] == "link 1 disable"
    finally:
        app.close()


def test_topside_stream_names() -> None:
    from coex_apps.console.cli import build_topside
    from coex_core.messages import QueueStatus, StreamStatus

    app = build_topside("loopback://names", "127.0.0.1", 0, modalities=(),
                        stream_names={3: "map"}, clock=lambda: 100.0)
    try:
        app.hub.messages([QueueStatus(100, (StreamStatus(0, True, 0, 127, 1, 64, 0, 0),
                                            StreamStatus(3, True, 1, 30, 2, 128, 16, 0),
                                            StreamStatus(9, True, 1, 30, 0, 0, 0, 0)))], 100.0)
        names = [s["name"] for s in app.hub.snapshot()["queues"]["streams"]]
        assert names == ["status", "map", "stream 9"]
    finally:
        app.close()


def test_topside_remaps_a_modalitys_third_party_ids() -> None:
    """``--remap-ids pings:100=4100,101=4101``: the console's node takes the pings plugin's
    records under wire id 4100 and hands them to the plugin as its own id 100."""
    import argparse

    import pytest

    from coex_apps.console.cli import build_topside, parse_remap
    from coex_core import wire
    from coex_core.errors import ConfigError
    from coex_core.messages import FrameHeader, Opaque

    assert parse_remap("pings:100=4100,101=4101") == ("pings", {100: 4100, 101: 4101})
    with pytest.raises(argparse.ArgumentTypeError):
        parse_remap("pings:100")
    with pytest.raises(ConfigError, match="not run here: ctd"):
        build_topside("loopback://remap-bad", "127.0.0.1", 0, modalities=("pings",),
                      remap_ids={"ctd": {130: 4130}})
    app = build_topside("loopback://remap", "127.0.0.1", 0, modalities=("pings",),
                        remap_ids={"pings": {100: 4100, 101: 4101}}, clock=lambda: 100.0)
    try:
        record = bytes.fromhex("0000" "00000064" "07d0")  # seq 0, t 100 s, 20.00 m
        for tid, seq in ((4100, 1), (100, 2)):
            app.node.receive(0, wire.pack([Opaque(tid, record)], 256, FrameHeader(src=2, dst=1, seq=seq)), 100.0)
        receiver = app.node.receiver("pings")
        assert receiver.inner.records == {0: (100, 2000)}  # the remapped id only
        (ack,) = [m for m in receiver.poll(101.0) if isinstance(m, Opaque)]
        assert ack.type_id == 4101
    finally:
        app.close()


def test_the_console_keeps_as_many_images_as_the_imagery_receiver(tmp_path: Path) -> None:
    """A topside whose imagery receiver keeps few images (a long dive, its images written out
    with ``out_dir``): the console keeps no more than the receiver, also after a restart from
    its store; with the defaults it keeps MAX_IMAGES."""
    import numpy as np

    from coex_apps.console.cli import build_topside
    from coex_apps.console.state import MAX_IMAGES

    options = {"imagery": {"max_images": 3, "out_dir": str(tmp_path / "images")}}
    db = tmp_path / "topside.sqlite"
    for _ in range(2):  # new, then resumed from its store
        app = build_topside("loopback://cli-images", "127.0.0.1", 0, modalities=("imagery",),
                            receiver_options=options, store=db)
        try:
            assert app.hub.state.max_images == 3
            for i in range(5):  # the newest three stay
                app.hub.state.apply_product("imagery", typed.image(i, np.zeros((8, 8), np.uint8), 100.0 + i),
                                            100.0 + i)
            assert sorted(app.hub.state.images) == [2, 3, 4]
        finally:
            app.close()
    app = build_topside("loopback://cli-images-default", "127.0.0.1", 0, modalities=("imagery",))
    try:
        assert app.hub.state.max_images == MAX_IMAGES
    finally:
        app.close()

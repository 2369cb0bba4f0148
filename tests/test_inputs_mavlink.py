"""The ``mavlink`` input, fed by stock pymavlink senders over UDP on loopback."""

from __future__ import annotations

import logging
import math
import os
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex import Image, InputContext, Item, Nav, Samples, check_options
from coex_core.errors import ConfigError
from coex_plugins.inputs.mavlink import MavlinkInput, pressure_depth
from coex_transports.testing import free_port as free_udp_port

mavutil = pytest.importorskip("pymavlink.mavutil")
from pymavlink.dialects.v20 import ardupilotmega as v20  # noqa: E402

OLD = time.time() - 3600.0


def sender(port: int, system: int = 1, mavlink2: bool = False) -> Any:
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=system, source_component=1)
    if mavlink2:
        conn.mav = v20.MAVLink(conn, srcSystem=system, srcComponent=1)
    return conn


def collect(adapter: MavlinkInput, now: float, want: int, timeout: float = 3.0) -> list[Item]:
    got: list[Item] = []
    deadline = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < deadline:
        got += adapter.poll(now)
        if len(got) < want:
            time.sleep(0.01)
    time.sleep(0.05)
    return got + adapter.poll(now)


def test_options() -> None:
    assert check_options(MavlinkInput, {}) == [
        "input 'mavlink' needs option 'connection' (pymavlink connection: udpin:0.0.0.0:14560, "
        "udpout:host:port, tcp:host:port, /dev/ttyACM0 ...)"]
    problems = check_options(MavlinkInput, {"connection": "udpin:0.0.0.0:1", "source_system": 0,
                                            "pressure_message": "SCALED_PRESSURE9", "water_density": 0})
    assert problems == [
        "source_system: 0 is outside 1..255",
        "pressure_message: one of 'SCALED_PRESSURE', 'SCALED_PRESSURE2', 'SCALED_PRESSURE3', '', "
        "got 'SCALED_PRESSURE9'",
        "water_density: 0 is not above 0 kg/m^3",
    ]
    with pytest.raises(ConfigError, match="'dialect': no pymavlink dialect 'nodialect'"):
        MavlinkInput({"connection": "udpin:127.0.0.1:0", "dialect": "nodialect"}, InputContext()).open()
    assert pressure_depth(1013.25, 1013.25, 1025.0) == 0.0


@pytest.mark.parametrize("mavlink2", [False, True], ids=["mavlink1", "mavlink2"])
def test_navigation_messages(mavlink2: bool) -> None:
    environ = os.environ.get("MAVLINK20")
    port = free_udp_port()
    adapter = MavlinkInput({"connection": f"udpin:127.0.0.1:{port}", "system": 1}, InputContext())
    adapter.open()
    tx = sender(port, mavlink2=mavlink2)
    other = sender(port, system=2, mavlink2=mavlink2)
    m = tx.mav
    assert m.vfr_hud_encode(0, 0, 0, 0, 0, 0).pack(m)[0] == (253 if mavlink2 else 254)  # the magic
    m.global_position_int_send(0, 415000000, -707000000, 0, -12345, 300, -400, 0, 27050)
    other.mav.global_position_int_send(0, 1, 1, 0, -1000, 0, 0, 0, 100)  # another system: ignored
    m.local_position_ned_send(0, 10.0, -5.0, 20.0, 1.0, 0.0, 0.0)
    m.attitude_send(0, 0.0, 0.0, -math.pi / 2, 0.0, 0.0, 0.0)
    m.vfr_hud_send(0.0, 1.5, 45, 0, 0.0, 0.0)
    hpa = 1013.25 + 1025.0 * 9.80665 * 10.0 / 100.0
    m.scaled_pressure2_send(0, hpa, 0.0, 1234)
    m.scaled_pressure2_send(0, 1013.25, 0.0, 1250)
    m.distance_sensor_send(0, 20, 5000, 350, 0, 1, 25, 0)
    m.distance_sensor_send(0, 20, 5000, 200, 0, 2, 0, 0)  # looking forward: not altitude
    m.distance_sensor_send(0, 20, 5000, 6000, 0, 1, 25, 0)  # beyond max: no bottom lock
    m.rangefinder_send(4.25, 0.0)
    m.global_position_int_send(0, 0, 0, 0, 500, 0, 0, 0, 65535)  # no fix, above the surface
    tx.port.sendto(b"\xfe\x05garbage that is no MAVLink at all", ("127.0.0.1", port))
    items = collect(adapter, 77.0, 10)
    navs = [i for i in items if isinstance(i, Nav)]
    assert all(n.time == 77.0 for n in navs)
    gpi, local, att, hud, p1, p2, dist, rng, nofix = navs
    assert (gpi.lat, gpi.lon) == pytest.approx((41.5, -70.7))
    assert gpi.depth == pytest.approx(12.345) and gpi.heading == pytest.approx(270.5)
    assert gpi.speed == pytest.approx(5.0) and gpi.x is None
    assert (local.x, local.y, local.depth, local.speed) == (-5.0, 10.0, 20.0, 1.0)  # east, north
    assert att.heading == pytest.approx(270.0)
    assert (hud.heading, hud.speed) == (45.0, 1.5)
    assert p1.depth == pytest.approx(10.0, abs=1e-3) and p2.depth == pytest.approx(0.0, abs=1e-3)
    assert dist.altitude == 3.5 and dist.depth is None
    assert rng.altitude == 4.25
    assert nofix.lat is None and nofix.depth == 0.0 and nofix.heading is None
    (temps,) = [i for i in items if isinstance(i, Samples)]
    assert temps.channel == "temperature" and temps.values.tolist() == [12.34, 12.5]
    assert temps.times.tolist() == [77.0, 77.0]
    assert adapter.counts["used"] == 9
    assert os.environ.get("MAVLINK20") == environ  # nothing process-wide changed
    # our heartbeat went back to the sender (routers need to hear an endpoint)
    deadline = time.monotonic() + 2.0
    heard = None
    while heard is None and time.monotonic() < deadline:
        heard = tx.recv_match(type="HEARTBEAT", blocking=False)
        time.sleep(0.01)
    assert heard is not None and heard.get_srcSystem() == 255 and heard.get_srcComponent() == 191
    adapter.close()
    tx.close()
    other.close()


def test_captured_images(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from PIL import Image as PILImage

    pixels = np.arange(64, dtype=np.uint8).reshape(8, 8)
    (tmp_path / "cam").mkdir()
    abs_file = tmp_path / "cam" / "img 1.png"
    PILImage.fromarray(pixels).save(abs_file)
    PILImage.fromarray(pixels.T.copy()).save(tmp_path / "cam" / "img2.png")
    for p in (tmp_path / "cam").iterdir():
        os.utime(p, (OLD, OLD))
    port = free_udp_port()
    ctx = InputContext(origin_lat=41.0, origin_lon=-71.0, base_dir=str(tmp_path))
    adapter = MavlinkInput({"connection": f"udpin:127.0.0.1:{port}", "image_dir": "cam",
                            "image_timeout": 10.0, "heartbeat": 0, "settle": 5.0}, ctx)
    adapter.open()
    tx = sender(port, mavlink2=True)
    q = [1.0, 0.0, 0.0, 0.0]
    url = "file://" + str(abs_file).replace(" ", "%20")
    tx.mav.camera_image_captured_send(0, 1_700_000_000_250_000, 0, 410010000, -710000000, 0, 0, q, 1, 1,
                                      url.encode())
    tx.mav.camera_image_captured_send(0, 1_700_000_000_250_000, 0, 410010000, -710000000, 0, 0, q, 1, 1,
                                      url.encode())  # repeated: once
    tx.mav.camera_image_captured_send(0, 0, 0, 0, 0, 0, 0, q, 2, 1, b"img2.png")
    tx.mav.camera_image_captured_send(0, 0, 0, 0, 0, 0, 0, q, 3, 0, b"failed.png")  # capture failed
    tx.mav.camera_image_captured_send(0, 0, 0, 0, 0, 0, 0, q, 4, 1, b"http://camera/img4.jpg")
    tx.mav.camera_image_captured_send(0, 0, 0, 0, 0, 0, 0, q, 5, 1, b"later.png")
    with caplog.at_level(logging.WARNING):
        items = collect(adapter, 10.0, 2)
        assert adapter.next_event(10.0) is not None  # later.png is awaited
        first, second = items
        assert isinstance(first, Image) and first.path == str(abs_file)
        assert first.time == pytest.approx(1_700_000_000.25)
        assert first.x == pytest.approx(0.0, abs=1e-6) and first.y == pytest.approx(111.32, abs=0.01)
        np.testing.assert_array_equal(first.pixels, pixels)
        assert second.path == str(tmp_path / "cam" / "img2.png") and second.time == 10.0 and second.x is None
        np.testing.assert_array_equal(second.pixels, pixels.T)
        # later.png appears, freshly written: read once it has settled for 5 s
        PILImage.fromarray(pixels).save(tmp_path / "cam" / "later.png")
        assert adapter.poll(11.0) == []
        assert adapter.poll(15.9) == []
        (late,) = adapter.poll(16.0)
        np.testing.assert_array_equal(late.pixels, pixels)
        # a file that never appears is given up after image_timeout
        tx.mav.camera_image_captured_send(0, 0, 0, 0, 0, 0, 0, q, 6, 1, b"never.png")
        assert collect(adapter, 20.0, 0, timeout=0.2) == []
        assert adapter.poll(29.0) == [] and adapter.next_event(29.0) is not None
        assert adapter.poll(30.0) == [] and adapter.next_event(30.0) is None
    messages = [r.getMessage() for r in caplog.records]
    assert any("http://camera/img4.jpg is not a local file" in m for m in messages)
    assert any("never.png never appeared" in m for m in messages)
    adapter.close()
    tx.close()


def test_a_connection_that_cannot_open_is_retried(caplog: pytest.LogCaptureFixture) -> None:
    port = free_udp_port()  # reserved for this process: nothing listens on it
    adapter = MavlinkInput({"connection": f"tcp:127.0.0.1:{port}"}, InputContext())
    with caplog.at_level(logging.WARNING):
        adapter.open()  # logged, not raised
        assert adapter.poll(0.0) == [] and adapter.poll(1.0) == []
    assert sum("cannot open" in r.getMessage() for r in caplog.records) == 1
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", port))
        server.listen(1)
        assert adapter.poll(4.0) == []  # not yet: retried every 5 s
        assert adapter._conn is None
        adapter.poll(6.0)
        assert adapter._conn is not None
        peer, _ = server.accept()
        mav = v20.MAVLink(None, srcSystem=1, srcComponent=1)
        peer.sendall(mav.vfr_hud_encode(0.0, 2.0, 90, 0, 0.0, 0.0).pack(mav))
        deadline = time.monotonic() + 2.0
        items: list[Item] = []
        while not items and time.monotonic() < deadline:
            items = adapter.poll(7.0)
        assert [(i.heading, i.speed) for i in items if isinstance(i, Nav)] == [(90.0, 2.0)]
        peer.close()
    adapter.close()

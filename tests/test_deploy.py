"""The deployment, end to end, as processes: `coex vehicle` and `coex topside` started from the
example configurations in examples/deploy/, talking through two simulated Micromodems
(`coex modem-sim`, real time, NMEA over TCP), the vehicle fed by a watched image directory, a
ROS bag, an LCM publisher and a MAVLink navigation stream. A survey command travels up, is
checked against the geofence, and the MAVLink autonomy output uploads it to a mission-protocol
peer built from stock pymavlink, which accepts it and flies it; a command outside the geofence
is rejected with its reason shown topside; killing the vehicle daemon (SIGKILL) and starting it
again loses nothing and sends nothing twice; SIGTERM stops it cleanly."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ._modemsim import free_tcp_base
from ._procs import COEX
from ._procs import act as _act
from ._procs import start as _start
from ._procs import state as _state
from ._procs import wait_for as _wait

pytest.importorskip("lcm")
pytest.importorskip("pymavlink")
pytest.importorskip("rosbags")

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples" / "deploy"
ORIGIN = (41.5245, -70.6712)  # examples/deploy/*.toml

pytestmark = pytest.mark.slow


def _port(kind: int = socket.SOCK_STREAM, n: int = 1) -> int:
    """A base port with ``n`` consecutive free ports."""
    return free_tcp_base(n, kind)


def _write_image(path: Path, seed: int) -> None:
    from PIL import Image

    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:96, 0:128]
    img = (120 + 60 * np.sin(x / 9.0 + seed) * np.cos(y / 7.0) + rng.normal(0, 8, x.shape)).clip(0, 255)
    tmp = path.with_suffix(".part")
    Image.fromarray(img.astype(np.uint8)).save(tmp, format="PNG")
    tmp.rename(path)  # appears whole (the adapter also waits for a file to settle)


def _bag(path: Path) -> Path:
    """A ROS 1 bag with 10 s of multibeam pings over a small patch of seafloor."""
    from coex_plugins.bathymetry.points import write_pointcloud_bag

    rng = np.random.default_rng(5)
    clouds = []
    t0 = 1_700_000_000.0
    for k in range(20):
        x = rng.uniform(-20, 20, 400)
        y = np.full(400, -20.0 + 2.0 * k) + rng.uniform(-1, 1, 400)
        z = -30.0 + 0.05 * x + rng.normal(0, 0.05, 400)
        clouds.append((t0 + 0.5 * k, np.column_stack([x, y, z])))
    return write_pointcloud_bag(path, clouds, topic="/nui/perception/sensors/norbit/points", ros1=True)


class _Feeds:
    """The vehicle's middleware: an LCM publisher of CoEx point clouds and a MAVLink navigation
    stream (GLOBAL_POSITION_INT and a downward DISTANCE_SENSOR from a stock pymavlink sender)."""

    def __init__(self, lcm_url: str, nav_port: int) -> None:
        import lcm
        from pymavlink import mavutil

        from coex_transports.lcm import points_t

        self.lc = lcm.LCM(lcm_url)
        self.points_t = points_t
        self.mav = mavutil.mavlink_connection(f"udpout:127.0.0.1:{nav_port}", source_system=1, source_component=1)
        self.stop = threading.Event()
        self.sent_points = 0
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self) -> None:
        k = 0
        lat0, lon0 = ORIGIN
        while not self.stop.is_set():
            # the vehicle 30 m east, 10 m north of the origin, 25 m deep, 5 m above the seafloor
            lat = lat0 + math.degrees(10.0 / 6378137.0)
            lon = lon0 + math.degrees(30.0 / (6378137.0 * math.cos(math.radians(lat0))))
            self.mav.mav.global_position_int_send(k * 500, int(lat * 1e7), int(lon * 1e7), -25000, -25000,
                                                  50, 0, 0, 9000)
            self.mav.mav.distance_sensor_send(k * 500, 20, 5000, 500, 0, 1, 25, 0)
            if k % 4 == 0 and k < 80:  # a swath of LCM soundings every 2 s, east of the bag's patch
                msg = self.points_t()
                n = 200
                rng = np.random.default_rng(k)
                xs, ys = rng.uniform(25, 45, n), rng.uniform(-20, 20, n)
                msg.utime, msg.n = int(time.time() * 1e6), n
                msg.x, msg.y = xs.tolist(), ys.tolist()
                msg.z = (-31.0 + rng.normal(0, 0.05, n)).tolist()
                self.lc.publish("COEX_POINTS", msg.encode())
                self.sent_points += n
            k += 1
            self.stop.wait(0.5)

    def close(self) -> None:
        self.stop.set()
        self.t.join(timeout=5)
        self.mav.close()


@pytest.fixture
def deployment(tmp_path: Path) -> Iterator[dict[str, Any]]:
    from coex_plugins.autonomy.mavpeer import MissionPeer

    tcp = _port(n=2)
    udp = _port(socket.SOCK_DGRAM, n=2)
    http_port = _port()
    lcm_port = _port(socket.SOCK_DGRAM)
    images = tmp_path / "transmit"
    images.mkdir()
    env = dict(os.environ)
    env.update({
        "COEX_VEHICLE_MODEM": f"micromodem:socket://127.0.0.1:{tcp + 1}?src=2&dest=1&rate=5",
        "COEX_TOPSIDE_MODEM": f"micromodem:socket://127.0.0.1:{tcp}?src=1&dest=2&rate=5",
        "COEX_SLOT_SECONDS": "5", "COEX_GUARD_SECONDS": "0.5",
        "COEX_VEHICLE_STORE": str(tmp_path / "vehicle.sqlite"),
        "COEX_TOPSIDE_STORE": str(tmp_path / "topside.sqlite"),
        "COEX_TOPSIDE_IMAGES": str(tmp_path / "received"),
        "COEX_IMAGE_DIR": str(images),
        "COEX_ROSBAG": str(_bag(tmp_path / "dive.bag")),
        "COEX_LCM_URL": f"udpm://239.255.76.67:{lcm_port}?ttl=0",
        "COEX_MAVLINK_NAV": f"udpin:127.0.0.1:{udp}",
        "COEX_MAVLINK_MISSION": f"udpout:127.0.0.1:{udp + 1}",
        "COEX_HTTP": f"127.0.0.1:{http_port}",
    })
    for f in ("vehicle.toml", "topside.toml"):
        check = subprocess.run([*COEX, "config", "check", str(EXAMPLES / f)], env=env, capture_output=True,
                               text=True, timeout=120, cwd=ROOT)
        assert check.returncode == 0 and ": ok: " in check.stdout, check.stdout + check.stderr
    procs: dict[str, subprocess.Popen[str]] = {}
    sim, _ = _start(["modem-sim", "--nodes", "1,2", "--tcp-base", str(tcp)], env, tmp_path / "modem-sim.log")
    procs["modem-sim"] = sim
    peer = MissionPeer(f"udpin:127.0.0.1:{udp + 1}", fly_interval=1.0)
    feeds: _Feeds | None = None
    try:
        time.sleep(1.5)  # the simulator's TCP ports
        run: dict[str, Any] = {"env": env, "procs": procs, "http": env["COEX_HTTP"], "images": images,
                               "peer": peer, "tmp": tmp_path}
        top, _ = _start(["topside", "--config", str(EXAMPLES / "topside.toml")], env, tmp_path / "topside.log")
        procs["topside"] = top
        run["start_vehicle"] = lambda: _start(["vehicle", "--config", str(EXAMPLES / "vehicle.toml")], env,
                                              tmp_path / "vehicle.log")
        veh, veh_out = run["start_vehicle"]()
        procs["vehicle"] = veh
        run["vehicle_out"] = veh_out
        peer.__enter__()
        feeds = _Feeds(env["COEX_LCM_URL"], udp)
        run["feeds"] = feeds
        yield run
    finally:
        if feeds is not None:
            feeds.close()
        peer.__exit__(None, None, None)
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_a_vehicle_and_topside_pair_from_the_examples(deployment: dict[str, Any]) -> None:
    d = deployment
    http, procs, peer, images = d["http"], d["procs"], d["peer"], d["images"]
    # the vehicle's position (MAVLink) reaches topside; then the camera writes an image
    _wait("the vehicle status topside", lambda: (_state(http).get("vehicle") or {}).get("status"), 300, procs)
    _write_image(images / "img_0001.png", 1)

    # the map (ROS bag and LCM soundings) and the image (placed where the vehicle was) reach topside
    def ready() -> dict[str, Any] | None:
        s = _state(http)
        if not s:
            return None
        levels = (s.get("map") or {}).get("levels") or []
        status = (s.get("vehicle") or {}).get("status")
        imgs = [i for i in (s.get("images") or {}).get("items", []) if i.get("bytes_received")]
        return s if levels and status and imgs else None

    s = _wait("map, image and vehicle status topside", ready, 300, procs)
    status = s["vehicle"]["status"]
    assert abs(status["x"] - 30.0) < 1.0 and abs(status["y"] - 10.0) < 1.0, status  # MAVLink lat/lon -> x/y
    assert abs(status["depth"] - 25.0) < 0.2 and abs(status["altitude"] - 5.0) < 0.2, status
    [img] = [i for i in s["images"]["items"] if i.get("bytes_received")]
    assert (img["width"], img["height"]) == (128, 96) and abs(img["x"] - 30.0) < 1.0, img

    # a lawnmower inside the geofence: accepted, uploaded to the MAVLink peer, flown
    _act(http, "survey", {"kind": "lawnmower", "x": 40.0, "y": -30.0, "heading": 90.0, "length": 60.0,
                          "width": 20.0, "spacing": 10.0, "altitude": 5.0})
    _act(http, "survey", {"kind": "line", "x": 0.0, "y": 0.0, "heading": 0.0, "length": 900.0, "altitude": 5.0,
                          "append": True})

    def surveys() -> list[dict[str, Any]]:
        return list((_state(http).get("surveys") or {}).get("items", []))

    def settled() -> list[dict[str, Any]] | None:
        items = surveys()
        states = [i["state"] for i in items]
        return items if len(items) == 2 and states[0] in ("started", "completed") and states[1] == "rejected" else None

    items = _wait("the survey accepted and flown, the second rejected", settled, 300, procs)
    assert items[1]["text"] == "waypoint 1 is 400 m outside the geofence", items[1]
    assert len(peer.missions) == 1, peer.missions
    wps = [it for it in peer.missions[0] if it.get("command") == 16]
    lat0, lon0 = ORIGIN
    # the lawnmower's first waypoint: the north row's west end (10, -20), as latitude and longitude
    first = wps[1] if len(wps) == 7 else wps[0]
    assert math.isclose(first["y"] / 1e7, lon0 + math.degrees(10.0 / (6378137.0 * math.cos(math.radians(lat0)))),
                        abs_tol=2e-7), first
    assert math.isclose(first["x"] / 1e7, lat0 + math.degrees(-20.0 / 6378137.0), abs_tol=2e-7), first
    _wait("the survey completed", lambda: surveys()[0]["state"] == "completed", 300, procs)

    # kill -9 the vehicle; an image arrives while it is down; it restarts from its store
    veh = procs["vehicle"]
    veh.kill()
    veh.wait(timeout=10)
    _write_image(images / "img_0002.png", 2)
    veh, out = d["start_vehicle"]()
    procs["vehicle"] = veh
    _wait("the vehicle resumed", lambda: out.has("resumed"), 60, procs)

    def both_images() -> list[dict[str, Any]] | None:
        imgs = [i for i in (_state(http).get("images") or {}).get("items", []) if i.get("bytes_received")]
        return imgs if len(imgs) >= 2 else None

    imgs = _wait("the image written while the vehicle was down", both_images, 300, procs)
    time.sleep(20)  # more cycles: nothing is sent twice
    imgs = [i for i in (_state(http).get("images") or {}).get("items", []) if i.get("bytes_received")]
    assert len(imgs) == 2, [(i["image_id"], i["stamp"]) for i in imgs]
    assert len(peer.missions) == 1, "the survey was not uploaded again after the restart"
    assert [i["state"] for i in surveys()] == ["completed", "rejected"]

    # SIGTERM: a clean stop (store saved), exit status 0
    veh.send_signal(signal.SIGTERM)
    assert veh.wait(timeout=30) == 0
    _wait("the summary line", lambda: out.has("coex vehicle: stopped"), 10, {})

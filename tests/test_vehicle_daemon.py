"""`coex vehicle` and `coex topside --config` in one process over a MAVLink (UDP) link: a survey
command goes up signed, is checked against the geofence, flown by the simulated autonomy and
reported back; one outside the fence is rejected with its reason; a restart resumes from the
store without flying the survey again."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from coex_apps.console.cli import topside_from_config
from coex_apps.vehicle.config import load
from coex_apps.vehicle.daemon import VehicleApp
from coex_transports.testing import free_port as _free_udp_port

KEY = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"

COMMON = """
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 1.0
guard = 0.1
"""
VEHICLE = """
[node]
role = "vehicle"
id = 2
command_key_file = "k.key"
store = "vehicle.sqlite"
snapshot_interval = 1
[modalities.bathymetry]
stream = 3
[modalities.survey]
stream = 7
priority = 90
options = {{ geofence = {{ radius = 300.0, min_altitude = 2.0 }} }}
[status]
interval = 1
[[modems]]
uri = "mavlink:udpout:127.0.0.1:{port}?sysid=2&compid=191"
packet_seconds = 0.2
[autonomy]
type = "sim"
speed = 40.0
""" + COMMON
TOPSIDE = """
[node]
role = "topside"
id = 1
command_key_file = "k.key"
store = "topside.sqlite"
[modalities.bathymetry]
stream = 3
[modalities.survey]
stream = 7
[console]
http = "127.0.0.1:0"
[[modems]]
uri = "mavlink:udpin:127.0.0.1:{port}?sysid=1&compid=190"
packet_seconds = 0.2
""" + COMMON


def _wait(cond: Any, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError("timed out")


def test_a_survey_goes_up_is_flown_and_a_restart_resumes(tmp_path: Path) -> None:
    port = _free_udp_port()
    (tmp_path / "k.key").write_text(KEY)
    (tmp_path / "v.toml").write_text(VEHICLE.format(port=port))
    (tmp_path / "t.toml").write_text(TOPSIDE.format(port=port))
    vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
    topside = topside_from_config(str(tmp_path / "t.toml")).start()
    try:
        rx = topside.node.receiver("survey")
        with topside.hub.lock:
            ok = rx.request("line", 0.0, 0.0, time.time(), heading=90.0, length=120.0, altitude=5.0)
            bad = rx.request("line", 0.0, 0.0, time.time(), heading=0.0, length=400.0, altitude=5.0,
                             append=True)
        _wait(lambda: rx.surveys[ok.survey_id].state == "completed"
              and rx.surveys[bad.survey_id].state == "rejected")
        assert rx.surveys[bad.survey_id].text == "waypoint 1 is 100 m outside the geofence"
        states = [h[1] for h in rx.surveys[ok.survey_id].history]
        assert states[0] == "requested" and states[-1] == "completed" and "started" in states
        assert vehicle.counts["plans"] == 1 and vehicle.counts["reports"] >= 2
        # the simulated autonomy's position came up as the vehicle status
        _wait(lambda: topside.hub.state.status is not None and topside.hub.state.status.x > 100.0)
        assert vehicle.node.stats["unauthenticated"] == 0
    finally:
        vehicle.close()
    # the vehicle restarts from its store: the survey's state is there, nothing is flown again
    again = VehicleApp(load(tmp_path / "v.toml", "vehicle"))
    try:
        assert again.resumed
        tx = again.node.sender("survey")
        assert tx.surveys[ok.survey_id].state.name == "COMPLETED"
        assert tx.surveys[bad.survey_id].state.name == "REJECTED"
        again.start()
        time.sleep(1.0)
        assert again.counts["plans"] == 0
    finally:
        again.close()
        topside.close()


SIM_COMMON = """
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 10.0
guard = 1.0
[modalities.timeseries]
stream = 5
{options}
"""


def test_the_daemons_run_on_given_transports_with_an_input_made_in_code(tmp_path: Path) -> None:
    """``VehicleApp(transports=...)`` and ``topside_from_config(transports=...)`` run on links the
    caller opened (here simulated Micromodems on a simulated clock), and ``VehicleApp.add_input``
    polls an input made in code like a configured one: its samples reach the console."""
    import numpy as np
    import pytest

    from coex_core.adapters import Input, Samples
    from coex_core.errors import ConfigError
    from coex_transports.micromodem.simulator import ModemNetwork, SimLoop

    class Thermometer(Input):
        name = "thermometer"
        feeds = ("timeseries",)

        def __init__(self, context: Any) -> None:
            super().__init__({}, context)
            self.next = net.now

        def poll(self, now: float) -> list[Any]:
            out = []
            while self.next + 10.0 <= now:
                t = self.next + np.arange(10.0)
                out.append(Samples("temp", t, 4.0 + 0.01 * (t % 7)))
                self.next += 10.0
            return out

    net = ModemNetwork({1: (0.0, 0.0, 0.0), 2: (500.0, 0.0, 100.0)})
    channel = 'options = { channels = [{ name = "temp", unit = "degC", lo = -2.0, hi = 40.0, resolution = 0.01 }] }'
    (tmp_path / "v.toml").write_text('[node]\nrole = "vehicle"\nid = 2\nstore = false\n'
                                     '[[modems]]\nuri = "micromodem:///dev/sim2?src=2&dest=1&rate=5"\n'
                                     + SIM_COMMON.format(options=channel))
    (tmp_path / "t.toml").write_text('[node]\nrole = "topside"\nid = 1\n[console]\nhttp = "127.0.0.1:0"\n'
                                     '[[modems]]\nuri = "micromodem:///dev/sim1?src=1&dest=2&rate=5"\n'
                                     + SIM_COMMON.format(options=""))
    clock = lambda: net.now  # noqa: E731
    with pytest.raises(ConfigError, match="one per URI"):
        topside_from_config(str(tmp_path / "t.toml"), clock, transports={1: net.transport(1, dest=2)})
    assert not net._hosts  # the refused link was closed
    vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle"), clock=clock, transports={0: net.transport(2, dest=1)})
    topside = topside_from_config(str(tmp_path / "t.toml"), clock, transports={0: net.transport(1, dest=2)})
    try:
        thermometer = vehicle.add_input(Thermometer(vehicle.context))
        assert thermometer.coex_key == "inputs[0] (thermometer)" and thermometer.coex_feeds == ("timeseries",)
        SimLoop(net, [vehicle.runner, topside.runner], max_step=1.0).run(net.now + 1800.0)
        assert vehicle.counts["samples"] >= 1700 and vehicle.runner.error_count == 0
        held = topside.node.receiver("timeseries").series("temp")
        assert len(held.times) > 0 and np.all(np.abs(held.values - 4.03) <= 0.04 + held.bounds)
    finally:
        vehicle.close()
        topside.close()


SKIPPING = """
[node]
role = "vehicle"
id = 2
store = false
[modalities.bathymetry]
stream = 3
[modalities.imagery]
stream = 4
[[modems]]
uri = "loopback://{name}"
packet_seconds = 0.2
[[inputs]]
type = "directory"
path = "camera"
existing = true
settle = 0.0
interval = 0.0
[[inputs]]
type = "lcm"
url = "{url}"
points_channel = "{channel}"
feeds = ["bathymetry"]
""" + COMMON


def test_every_skipped_input_item_is_counted_per_input_in_the_summary(tmp_path: Path) -> None:
    """The field report: "skipped 0" after 4 corrupt images and 2 bad LCM messages. Now every
    item skipped, by an input itself (a file it cannot read, a message that does not decode) or
    by the daemon (an image too small for the image sender), is counted as that input's
    (``Input.counts["skipped"]``) and the shutdown summary gives the total and each input's."""
    import uuid

    import lcm
    import numpy as np
    from PIL import Image

    from coex_apps.vehicle.cli import summary_text
    from coex_transports.lcm import points_t
    from coex_transports.lcm.testing import TEST_UDPM_URL, ensure_multicast_route, unique_channel

    undo = ensure_multicast_route()
    camera = tmp_path / "camera"
    camera.mkdir()
    for k in range(4):  # what a camera leaves when the disk fills: not images at all
        (camera / f"corrupt_{k}.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00garbage" * k)
    rng = np.random.default_rng(1)
    Image.fromarray(rng.integers(0, 255, (48, 64), np.uint8)).save(camera / "good.png")
    Image.fromarray(np.zeros((2, 2), np.uint8)).save(camera / "tiny.png")  # read, but too small to send
    channel = unique_channel("PTS")
    (tmp_path / "v.toml").write_text(SKIPPING.format(name=f"skip-{uuid.uuid4().hex[:8]}", url=TEST_UDPM_URL,
                                                     channel=channel))
    app = VehicleApp(load(tmp_path / "v.toml", "vehicle"))
    directory, lcm_input = app.inputs
    assert (directory.counts, lcm_input.counts) == ({"skipped": 0}, {"skipped": 0, "messages": 0})
    pub = lcm.LCM(TEST_UDPM_URL)
    try:
        app.start()
        good = points_t()
        good.utime, good.n, good.x, good.y, good.z = 0, 2, [1.0, 2.0], [3.0, 4.0], [-30.0, -31.0]
        pub.publish(channel, b"not a points_t")
        pub.publish(channel, good.encode()[:-6])  # cut short
        pub.publish(channel, good.encode())
        _wait(lambda: app.counts["images"] == 1 and app.counts["points"] == 2
              and directory.skipped == 5 and lcm_input.skipped == 2)
    finally:
        app.close()
        undo()
    summary = app.summary()
    assert summary["skipped_by_input"] == {"inputs[0] (directory)": 5, "inputs[1] (lcm)": 2}
    assert summary["skipped"] == 7 and summary["images"] == 1 and summary["points"] == 2
    assert lcm_input.counts == {"skipped": 2, "messages": 1}
    text = summary_text(summary)
    assert "images 1, samples 0, nav 0, skipped 7," in text
    assert text.endswith("; skipped by input: inputs[0] (directory) 5, inputs[1] (lcm) 2"), text


def test_a_vehicle_restarted_mid_survey_follows_it_again_to_its_end(tmp_path: Path) -> None:
    port = _free_udp_port()
    (tmp_path / "k.key").write_text(KEY)
    (tmp_path / "v.toml").write_text(VEHICLE.format(port=port).replace("speed = 40.0", "speed = 12.0"))
    (tmp_path / "t.toml").write_text(TOPSIDE.format(port=port))
    vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
    topside = topside_from_config(str(tmp_path / "t.toml")).start()
    again = None
    try:
        rx = topside.node.receiver("survey")
        with topside.hub.lock:
            cmd = rx.request("line", 0.0, 0.0, time.time(), heading=90.0, length=120.0, altitude=5.0)
        _wait(lambda: rx.surveys[cmd.survey_id].state == "started")
        vehicle.close()  # mid-survey (120 m at 12 m/s)
        again = VehicleApp(load(tmp_path / "v.toml", "vehicle")).start()
        _wait(lambda: rx.surveys[cmd.survey_id].state == "completed", timeout=60.0)
        assert again.lifecycle.counts["resumed"] == 1 and again.counts["plans"] == 0  # followed again, not submitted as new
        assert again.autonomy is not None and again.autonomy._plan.survey_id == cmd.survey_id
    finally:
        vehicle.close()
        if again is not None:
            again.close()
        topside.close()

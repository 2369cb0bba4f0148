"""A vehicle whose dead reckoning drifts, through the daemons end to end (issue 56): ``coex
vehicle`` (its navigation from an input: where it believes it is) and ``coex topside`` with the
ship's USBL on its ``[usbl]`` UDP port, over simulated Micromodems on a simulated clock. Topside's
console shows the drift it estimated, close to the truth, and a survey drawn on the corrected map
reaches the vehicle in its own frame."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from coex import Input, Nav
from coex_apps.console.cli import topside_from_config
from coex_apps.demo.navigation import DeadReckoning, UsblTracker
from coex_apps.demo.world import Leg, Track
from coex_apps.vehicle.config import load
from coex_apps.vehicle.daemon import VehicleApp
from coex_plugins.bathymetry.sim import Seafloor
from coex_plugins.navigation import LocalFrame
from coex_transports.micromodem.simulator import ModemNetwork, SimLoop
from coex_transports.testing import free_port as _free_udp_port

COMMON = """
[tdma]
slots = ["topside", "vehicle"]
slot_seconds = 10.0
guard = 1.0
[modalities.survey]
stream = 7
"""


class DeadReckoned(Input):
    """The vehicle's navigation as its INS gives it: where it believes it is (the truth plus the
    drift of :class:`~coex_apps.demo.navigation.DeadReckoning`), once a second."""

    name = "dead-reckoned"
    feeds = ("status",)

    def __init__(self, context: Any, track: Track, dr: DeadReckoning) -> None:
        super().__init__({}, context)
        self.track, self.dr = track, dr

    def poll(self, now: float) -> list[Any]:
        x, y, depth, alt, heading = self.track.position(now)
        bx, by = self.dr.believed(now, x, y)
        return [Nav(now, x=bx, y=by, depth=depth, altitude=alt, heading=self.dr.heading(heading), speed=1.0)]


def test_a_drifting_vehicle_through_the_daemons_is_corrected_topside(tmp_path: Path) -> None:
    port = _free_udp_port()
    net = ModemNetwork({1: (0.0, -300.0, 0.0), 2: (0.0, 0.0, 400.0)})
    t0 = net.now
    (tmp_path / "v.toml").write_text('[node]\nrole = "vehicle"\nid = 2\nstore = false\n'
                                     '[[modems]]\nuri = "micromodem:///dev/sim2?src=2&dest=1&rate=5"\n'
                                     '[autonomy]\ntype = "log"\n' + COMMON)
    (tmp_path / "t.toml").write_text('[node]\nrole = "topside"\nid = 1\nstore = false\n'
                                     '[console]\nhttp = "127.0.0.1:0"\n'
                                     '[[modems]]\nuri = "micromodem:///dev/sim1?src=1&dest=2&rate=5"\n'
                                     f'[usbl]\nudp = "127.0.0.1:{port}"\n' + COMMON)
    # the truth: east along y = 0 at 1 m/s for 20 min, north for 10 min, then holding
    floor = Seafloor(size=64.0, depth=420.0, seed=0)
    track = Track(floor)
    track.legs += [Leg(t0, t0 + 1200.0, (0.0, 0.0), (1200.0, 0.0), 20.0),
                   Leg(t0 + 1200.0, t0 + 1800.0, (1200.0, 0.0), (1200.0, 600.0), 20.0),
                   Leg(t0 + 1800.0, t0 + 3600.0, (1200.0, 600.0), (1200.0, 600.0), 20.0)]
    dr = DeadReckoning(track, t0, t0, t0 + 3600.0, drift=0.01, heading_bias=1.0, seed_offset=2.0,
                       rng=np.random.default_rng(56))
    clock = lambda: net.now  # noqa: E731
    vehicle = VehicleApp(load(tmp_path / "v.toml", "vehicle"), clock=clock, transports={0: net.transport(2, dest=1)})
    topside = topside_from_config(str(tmp_path / "t.toml"), clock, transports={0: net.transport(1, dest=2)})
    usbl = UsblTracker((0.0, -300.0), LocalFrame(0.0, 0.0), sigma=0.005, outliers=0.03,
                       rng=np.random.default_rng(57), address=("127.0.0.1", port))
    try:
        vehicle.add_input(DeadReckoned(vehicle.context, track, dr))
        loop = SimLoop(net, [vehicle.runner, topside.runner], max_step=1.0)
        t = t0 + 5.0
        while t < t0 + 2400.0:  # the ship's tracking system: a fix every 10 s on its own UDP line
            loop.at(t, lambda now: usbl.send(now, 2, *track.position(now)[:3]))
            t += 10.0
        loop.run(t0 + 2400.0)
        assert topside.usbl is not None and topside.usbl.fixes >= 200, topside.usbl.input.counts
        nav = topside.hub.state.section("navigation")
        got = np.array([nav["correction"]["dx"], nav["correction"]["dy"]])
        truth = dr.error(net.now)
        assert math.hypot(*truth) > 8.0  # the vehicle really drifted ...
        assert math.hypot(*(got - truth)) < 1.5, (got, truth)  # ... and topside knows by how much
        assert nav["outliers"] >= 1 and nav["correction"]["age"] < 30.0
        # a survey drawn on the corrected map goes to the vehicle in its own frame: where it believes
        # the point is, so that it truly gets there
        with topside.hub.lock:
            topside.hub.actions.survey("goto", 1100.0, 500.0, altitude=10.0)
        loop.run(net.now + 120.0)
        plan = vehicle.node.sender("survey").active_plan()
        assert plan is not None
        sent = np.array(plan.waypoints[0])
        aim = sent - dr.error(net.now)  # where a vehicle flying to `sent` in its own frame truly goes
        assert math.hypot(aim[0] - 1100.0, aim[1] - 500.0) < 1.5, (sent, aim)
        assert math.hypot(sent[0] - 1100.0, sent[1] - 500.0) > 5.0  # not the drawn point itself
    finally:
        usbl.close()
        vehicle.close()
        topside.close()

"""The demo's nodes are deployment configurations built by ``build_node`` (issue 53): the
mappings pass the checker of ``coex config check``, and the vehicle's streams and priorities are
the deployment's defaults, not a second copy of them."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from coex import AcousticChannel
from coex_apps.demo.config import CAMERA, EPOCH, LINK_STREAM, TOPSIDE, VEHICLE
from coex_apps.demo.deployment import node_mapping, receiver_modalities, sender_modalities
from coex_apps.demo.scenario import PRESETS, preset
from coex_apps.demo.world import build_fleet, build_nodes, site_geofence
from coex_apps.vehicle.config import STREAM_DEFAULTS, check_problems
from coex_core.loopback import SimClock
from coex_plugins.imagery import ImageryReceiver
from coex_transports.micromodem.simulator import ModemNetwork

NAMES = ("bathymetry", "imagery", "timeseries", "survey", "detections")


@pytest.fixture
def network() -> Iterator[ModemNetwork]:
    net = ModemNetwork({TOPSIDE: (0.0, 0.0, 0.0), VEHICLE: (10.0, 0.0, 0.0), CAMERA: (20.0, 0.0, 0.0)},
                       channel=AcousticChannel(seed=1), clock=SimClock(EPOCH), ptys=False)
    yield net
    net.close()


@pytest.mark.parametrize("quick", [False, True])
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_node_of_a_dive_passes_the_deployment_checker(name: str, quick: bool, tmp_path: Path) -> None:
    """What ``coex config check`` would say of each node's file (every preset, full and
    ``--quick``): nothing but the warning that its modem's device is not there (it is simulated)."""
    scn = preset(name).quick() if quick else preset(name)
    fence = site_geofence(scn)
    raws: list[dict[str, Any]] = [
        node_mapping(scn, "vehicle", VEHICLE, TOPSIDE, sender_modalities(NAMES, [], fence, 4), spare=scn.spare),
        node_mapping(scn, "topside", TOPSIDE, VEHICLE, receiver_modalities(tmp_path, True)),
    ]
    if scn.fleet:
        raws[1:] = [node_mapping(scn, "vehicle", CAMERA, TOPSIDE, sender_modalities(("imagery", "survey"), [],
                                                                                  fence, 4)),
                    node_mapping(scn, "topside", TOPSIDE, VEHICLE, receiver_modalities(tmp_path, True),
                                 vehicles={VEHICLE: ("bathymetry", "survey"), CAMERA: ("imagery", "survey")})]
    for raw in raws:
        cfg, p = check_problems(raw, tmp_path / "node.toml", None)
        assert p.items == [], p.items
        assert all(w.startswith("modems[0].uri: ") for w in p.warnings), p.warnings
        assert cfg.schedule().cycle == scn.cycle


def _streams(node: Any) -> dict[str, tuple[int, int, int | None]]:
    return {s.config.name: (s.id, s.config.priority, s.config.low_priority) for s in node.manager.streams}


def test_the_vehicle_streams_and_priorities_are_the_deployments(tmp_path: Path, network: ModemNetwork) -> None:
    scn = preset("default").quick()
    vehicle, topside, senders, receivers, modems = build_nodes(tmp_path, [], b"k" * 32, scn, network=network)
    streams = _streams(vehicle)
    for name in NAMES:
        stream, priority = STREAM_DEFAULTS[name]
        assert streams[name][:2] == (stream, priority), (name, streams[name])
    assert streams["imagery"][2] == 90  # the demo's own: the operator's answers first on a low link
    assert streams["link"][0] == LINK_STREAM and LINK_STREAM not in {s for s, _ in STREAM_DEFAULTS.values()}
    assert list(senders) == list(NAMES) and list(receivers) == list(NAMES)
    assert senders["bathymetry"] is vehicle.sender("bathymetry")
    # the links as the daemons make them: the scenario's rate and spare share, to the peer
    vlink, tlink = vehicle.manager._link(0).cfg, topside.manager._link(0).cfg
    assert (vlink.rate, vlink.dst, vlink.spare) == (scn.modem_rate, TOPSIDE, scn.spare)
    assert (tlink.rate, tlink.dst) == (scn.modem_rate, VEHICLE)
    assert vehicle.manager.queue_status_interval == scn.cycle
    # the demo topside's file says [tdma] queue_status = true: its own queue status each cycle (as before)
    assert topside.manager.queue_status_interval == scn.cycle
    assert sorted(modems) == [TOPSIDE, VEHICLE]


def test_a_fleets_vehicles_carry_their_own_modalities(tmp_path: Path, network: ModemNetwork) -> None:
    scn = preset("fleet").quick()
    fleet = build_fleet(tmp_path, [], b"k" * 32, scn, network=network)
    mapper, camera = _streams(fleet.mapper), _streams(fleet.camera)
    assert {"bathymetry", "timeseries", "survey", "detections", "link"} <= set(mapper) and "imagery" not in mapper
    assert {"imagery", "survey"} <= set(camera) and "bathymetry" not in camera
    assert camera["imagery"][:2] == STREAM_DEFAULTS["imagery"] and mapper["survey"][:2] == STREAM_DEFAULTS["survey"]
    assert fleet.topside.manager._link(0).cfg.dst == 0  # topside broadcasts to its vehicles
    # topside's receivers: what each vehicle carries, from that vehicle alone
    held = {(r.name, r.peer) for r in fleet.topside._receivers}
    assert held == {("bathymetry", VEHICLE), ("timeseries", VEHICLE), ("detections", VEHICLE), ("survey", VEHICLE),
                    ("imagery", CAMERA), ("survey", CAMERA)}
    assert fleet.receivers["imagery"] is fleet.topside.receiver("imagery", CAMERA)
    imagery = fleet.topside.receiver("imagery", CAMERA)
    assert isinstance(imagery, ImageryReceiver) and imagery.out_dir == str(tmp_path.resolve() / "images")

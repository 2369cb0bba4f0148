"""Console adapter: ConsoleState from real plugin messages/products, ConsoleActions as wire
commands, the HTTP/SSE server, and the topside node glue (commands acked by a vehicle node)."""

from __future__ import annotations

import dataclasses
import io
import json
import threading
import time
import urllib.error
import urllib.request
from typing import Any

import numpy as np
import pytest

from coex_apps.console import ConsoleActions, ConsoleHub, ConsoleState, serve
from coex_apps.console.node import NodeCommands, pump
from coex_apps.console.testing import RecordingSender, feed_sample, survey_points
from coex_core import messages as m
from coex_core import wire
from coex_core.channel.events import BadFrame, CommandResult, LinkChanged
from coex_core.channel.manager import ChannelManager, LinkConfig
from coex_core.channel.queue import StreamConfig
from coex_core.channel.schedule import Schedule
from coex_core.errors import RequestRejected
from coex_core.node import Node
from coex_core.predicted import (
    decode_predicted,
)
from coex_core.timefmt import to_stamp
from coex_plugins.bathymetry import (
    BathymetryModality,
    BathymetryReceiver,
    BathymetrySender,
    decode_subgrid,
)
from coex_plugins.timeseries.synth import dataset

T0 = 36000.0
NUI = Schedule.simple([1, 2, 2, 1, 2, 2], 20.0, 2.0)


@pytest.fixture(scope="module")
def sample() -> tuple[ConsoleState, dict[str, Any]]:
    state = ConsoleState(schedules={0: NUI})
    made = feed_sample(state, t0=T0, seed=0)
    return state, made


@pytest.fixture(scope="module")
def subgrids(sample: tuple[ConsoleState, dict[str, Any]]) -> list[m.Subgrid]:
    return list(sample[1]["subgrids"])


def fresh(subgrids: list[m.Subgrid] | None = None) -> ConsoleState:
    st = ConsoleState(schedules={0: NUI})
    if subgrids:
        st.apply_messages(subgrids, T0)
    return st


def png_size(data: bytes) -> tuple[int, int]:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as img:
        img.load()
        return img.size


# ------------------------------------------------------------------------------ state


def test_snapshot_is_strict_json_with_every_section(sample: tuple[ConsoleState, Any]) -> None:
    state, _ = sample
    snap = json.loads(json.dumps(state.snapshot(), allow_nan=False))
    for name in ("vehicle", "map", "images", "series", "link", "queues", "commands", "log"):
        assert name in snap
    assert snap["vehicle"]["status"]["mode"] == "SURVEY"
    assert len(snap["vehicle"]["track"]) == 63  # 65 statuses, 2 repeat the previous position


def test_map_levels_assembled_from_real_subgrids(subgrids: list[m.Subgrid]) -> None:
    st = fresh(subgrids)
    levels = {lv["level"]: lv for lv in st.snapshot()["map"]["levels"]}
    by_level: dict[int, set[tuple[int, int]]] = {}
    for sg in subgrids:
        by_level.setdefault(sg.level, set()).add((sg.ix, sg.iy))
    assert set(levels) == set(by_level)
    for level, keys in by_level.items():
        assert levels[level]["subgrids"] == len(keys)
        assert levels[level]["cell"] == 2.0**level
    # the assembled grid holds exactly the decoded subgrid values at the right place
    sg = next(s for s in subgrids if s.level == 0)
    z, x0, y0, cell = st.level_grid(0)  # type: ignore[misc]
    r = round((sg.iy * sg.side * cell - y0) / cell)
    c = round((sg.ix * sg.side * cell - x0) / cell)
    cells = decode_subgrid(sg) if isinstance(sg, m.Subgrid) else decode_predicted(sg)  # on its own: NONE
    np.testing.assert_array_equal(z[r:r + sg.side, c:c + sg.side], cells)
    # the level picture is a real PNG of the grid's size
    png = st.map_png(0)
    assert png is not None and png.startswith(b"\x89PNG")
    assert png_size(png) == (z.shape[1], z.shape[0])


def test_subgrid_arrival_changes_only_the_map_and_keeps_newest(subgrids: list[m.Subgrid]) -> None:
    st = fresh()
    v0 = dict(st.versions)
    sg = subgrids[0]
    assert st.apply_message(sg, T0) == {"map"}
    assert st.versions["map"] == v0["map"] + 1
    # an older copy of the same subgrid is ignored; a newer one replaces it
    older = dataclasses.replace(sg, stamp=sg.stamp - 10)
    assert st.apply_message(older, T0) == set()
    newer = dataclasses.replace(sg, stamp=sg.stamp + 10)
    assert st.apply_message(newer, T0 + 20) == {"map"}
    assert st.held_stamps(sg.level, sg.ix, sg.iy, 1, 1) == [sg.stamp + 10]


def test_candidate_targets_found_near_the_cars(subgrids: list[m.Subgrid]) -> None:
    st = fresh(subgrids)
    targets = st.snapshot()["map"]["targets"]
    # Seafloor.default(size=96) puts the cars at (33.6, 40.3) and (60.5, 55.7)
    for cx, cy in ((33.6, 40.3), (60.5, 55.7)):
        assert min(np.hypot(t["x"] - cx, t["y"] - cy) for t in targets) < 4.0


def test_vehicle_status_late_arrival_keeps_newest() -> None:
    st = ConsoleState()
    st.apply_message(m.VehicleStatus(100, 1.0, 2.0, 50.0, 10.0, 90.0, 1.0, 80, m.VehicleMode.SURVEY, 0), 100.0)
    st.apply_message(m.VehicleStatus(90, 9.0, 9.0, 50.0, 10.0, 90.0, 1.0, 80, m.VehicleMode.SURVEY, 0), 101.0)
    snap = st.snapshot()["vehicle"]
    assert (snap["status"]["x"], snap["status"]["t"]) == (1.0, 100.0)


def test_series_products_with_error_bounds(sample: tuple[ConsoleState, Any]) -> None:
    state, made = sample
    chans = {c["name"]: c for c in state.snapshot()["series"]["channels"]}
    rx = made["series_receiver"]
    for name in ("methane", "temperature"):
        s = rx.series(name)
        c = chans[name]
        assert c["samples"] == s.times.size
        assert len(c["t"]) == len(c["v"]) == len(c["err"])
        assert c["max_error"] == pytest.approx(float(s.bounds.max()), rel=1e-3)
        # the displayed band contains every true sample: |value - truth| <= bound
        truth = next(d for d in dataset(duration=1800.0, period=1.0, seed=0, t0=T0 - 1800.0)
                     if d.name == name)
        t, v, err = (np.asarray(c[k]) for k in ("t", "v", "err"))
        assert np.all(err >= 0)
        ref = np.interp(t, truth.times, truth.values)
        assert np.all(np.abs(v - ref) <= err + 1e-3)


def test_image_products_thumbnails_and_bytes(sample: tuple[ConsoleState, Any]) -> None:
    state, made = sample
    items = state.snapshot()["images"]["items"]
    assert len(items) == 3
    rx = made["image_receiver"]
    for it in items:
        p = next(p for p in rx.products() if p.kind == "image" and p.meta["image_id"] == it["image_id"])
        assert it["bytes_received"] == p.meta["held_bytes"] > 0
        assert it["total_bytes"] == p.meta["total_bytes"]
        png = state.image_png(it["image_id"])
        assert png is not None and max(png_size(png)) <= 160


def test_the_console_send_is_a_command_sink() -> None:
    """The console's ``send`` is a declared CommandSink: a plain callable is wrapped with the
    defaults (the console numbers its commands from ``first_command_id``, nothing is queued to
    flush); a sink's own ``next_command_id`` numbers them and ``pump`` calls its ``flush``."""
    from coex_apps.console.actions import CallSink, CommandSink

    st = ConsoleState(schedules={0: NUI})
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: 10.0, first_command_id=7)
    assert isinstance(acts.send, CallSink) and acts.send.next_command_id() is None
    assert acts.send.flush() == 0
    assert [acts.link_control(0, True).command_id, acts.link_control(0, False).command_id] == [7, 8]
    assert len(sent) == 2

    class Queued(CommandSink):
        def __init__(self) -> None:
            self.queue: list[m.Message] = []
            self.flushed: list[m.Message] = []

        def __call__(self, msg: m.Message) -> None:
            self.queue.append(msg)

        def next_command_id(self) -> int:
            return 300  # the console keeps it within 0..255

        def flush(self) -> int:
            n, self.flushed, self.queue = len(self.queue), self.flushed + self.queue, []
            return n

    sink = Queued()
    hub = ConsoleHub(ConsoleState(schedules={0: NUI}), sink, lambda: 10.0)
    assert hub.actions.send is sink
    assert hub.actions.link_control(0, True).command_id == 300 % 256
    top = Node(ChannelManager(1, [LinkConfig(0, NUI)]))
    hub.pump(top, 11.0)
    assert [type(x) for x in sink.flushed] == [m.LinkControl] and not sink.queue


def test_link_queue_and_command_acks() -> None:
    st = ConsoleState(schedules={0: NUI})
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: 10.0)
    q = acts.queue_config(3, priority=90)
    st.apply_message(m.QueueStatus(to_stamp(12.0), (m.StreamStatus(3, True, 1, 90, 5, 640, 32, 1),)), 12.0)
    st.apply_message(m.LinkStatus(to_stamp(12.0), 0, 8, 3, 9.5, None), 12.0)
    st.apply_event(BadFrame(13.0, 0, "crc"))
    st.apply_message(m.CommandAck(q.command_id, m.AckStatus.ACCEPTED), 14.0)
    snap = st.snapshot()
    assert snap["queues"]["streams"] == [dict(stream=3, drops_total=1, enabled=True, tier=1, priority=90,
                                              depth=5, queued_bytes=640, oldest_age=32, drops=1,
                                              name="stream 3")]
    lk = snap["link"]["links"][0]
    assert (lk["frames"], lk["bad_frames"], lk["snr"], lk["local_bad"]) == (8, 3, 9.5, 1)
    assert snap["commands"][0]["status"] == "accepted"
    st.apply_event(LinkChanged(15.0, 0, False, False))
    assert st.snapshot()["link"]["links"][0]["enabled"] is False


# ---------------------------------------------------------------------------- actions


def _region_requests(rx: BathymetryReceiver, now: float, n: int) -> list[m.MapRoiRequest]:
    """What the receiver sends for ``n`` new regions (a few per poll, as on the uplink)."""
    out: list[m.MapRoiRequest] = []
    for _ in range(n):
        out += [x for x in rx.poll(now) if isinstance(x, m.MapRoiRequest)]
        if len(out) >= n:
            break
    return out


def test_request_region_lists_held_stamps(subgrids: list[m.Subgrid]) -> None:
    """A map region asked in the console goes through the bathymetry receiver, which lists
    what topside holds in each request (the console keeps no second map)."""
    st = fresh(subgrids)
    rx = st.map_receiver
    acts = ConsoleActions(st, lambda msg: None, lambda: T0 + 5, map_receiver=rx)
    held = {(s.ix, s.iy): s.stamp for s in subgrids if s.level == 0}
    regions = acts.request_region(0, 20.0, 20.0, 60.0, 100.0)
    assert [r["status"] for r in st.snapshot()["map"]["requests"]] == ["waiting"] * len(regions)
    sent = _region_requests(rx, T0 + 5, len(regions))
    assert len(sent) == len(regions)
    covered = set()
    for req in sent:
        assert req.w <= 8 and req.h <= 8 and req.level == 0
        assert len(req.held) == req.w * req.h
        for k, st_ in enumerate(req.held):
            key = (req.x0 + k % req.w, req.y0 + k // req.w)
            covered.add(key)
            assert st_ == held.get(key)
        wire.encode(req)  # every request fits the wire format
    assert covered == {(ix, iy) for ix in range(2, 8) for iy in range(2, 13)}
    reqs = st.snapshot()["map"]["requests"]
    assert [r["status"] for r in reqs] == ["sent"] * len(sent)
    assert sorted(r["request_id"] for r in reqs) == sorted(x.request_id for x in sent)


def test_region_status_follows_the_vehicle_s_replies(subgrids: list[m.Subgrid]) -> None:
    st = fresh()
    st.apply_message(subgrids[0], T0)
    rx = st.map_receiver
    acts = ConsoleActions(st, lambda msg: None, lambda: T0, map_receiver=rx)
    sg = next(s for s in subgrids if s.level == 0)
    span = sg.side * 1.0
    acts.request_region(0, sg.ix * span + 1, sg.iy * span + 1, sg.ix * span + 2, sg.iy * span + 2)
    (req,) = _region_requests(rx, T0, 1)
    st.apply_message(m.MapRoiReply(req.request_id, 0, 1), T0 + 30)
    assert st.snapshot()["map"]["requests"][-1]["status"] == "queued"
    assert st.snapshot()["map"]["requests"][-1]["queued"] == 1
    acts.request_region(0, 500.0, 500.0, 501.0, 501.0)
    (req2,) = [x for x in _region_requests(rx, T0 + 40, 2) if x.x0 > 10]
    st.apply_message(m.MapRoiReply(req2.request_id, 0, 0), T0 + 50)
    assert st.snapshot()["map"]["requests"][-1]["status"] == "nothing newer"


def test_gap_fill_request_bitmap(subgrids: list[m.Subgrid]) -> None:
    st = fresh(subgrids)
    rx = st.map_receiver
    ConsoleActions(st, lambda msg: None, lambda: T0, map_receiver=rx).request_region(
        1, 0, 0, 63.9, 63.9, fill_gaps=True)
    (req,) = _region_requests(rx, T0, 1)
    assert req.fill_gaps and req.held == () and (req.w, req.h) == (4, 4)
    held = {(s.ix, s.iy) for s in subgrids if s.level == 1}
    for k in range(16):
        bit = (req.have >> (15 - k)) & 1
        assert bit == ((k % 4, k // 4) in held)


def test_a_view_only_console_asks_nothing(subgrids: list[m.Subgrid]) -> None:
    st = fresh(subgrids)
    with pytest.raises(RequestRejected, match="bathymetry receiver"):
        ConsoleActions(st, lambda msg: None, lambda: T0).request_region(0, 0, 0, 10, 10)


@pytest.mark.parametrize("action,args", [
    ("request_region", dict(level=16, x_min=0, y_min=0, x_max=1, y_max=1)),
    ("request_region", dict(level=0, x_min=0, y_min=0, x_max=1e6, y_max=1e6)),
    ("request_region", dict(level=0, x_min="nan", y_min=0, x_max=1, y_max=1)),
    ("set_image_goal", dict(image_id=1, kind="most", value=1)),
    ("set_image_goal", dict(image_id=1, kind="fraction", value=0)),
    ("image_by_time", dict(t=1.0, direction="sideways")),
    ("refine_series", dict(channel=9, start=0, end=1)),
    ("queue_config", dict(stream=40, priority=1)),
    ("queue_config", dict(stream=3, priority=300)),
    ("link_control", dict(link=9, enabled=True)),
    ("spare_config", dict(percent=101)),
    ("spare_config", dict(percent=50, link=0, stream=3)),
    ("spare_config", dict(percent=50, link=8)),
    ("propose_schedule", dict(link=0, slots=[])),
    ("propose_schedule", dict(link=0, slots=[{"owner": 1, "duration": 1.0, "guard": 2.0}])),
    ("no_such_action", {}),
    ("queue_config", dict(stream=3, bogus=1)),
])
def test_bad_actions_rejected_and_nothing_sent(subgrids: list[m.Subgrid], action: str,
                                               args: dict[str, Any]) -> None:
    st = fresh(subgrids)
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: T0, map_receiver=st.map_receiver)
    before = st.snapshot()["commands"]
    with pytest.raises(RequestRejected):
        acts.dispatch(action, args)
    assert sent == [] and st.snapshot()["commands"] == before
    assert not st.map_receiver.regions  # and no map region either


def test_every_action_is_a_wire_command(sample: tuple[ConsoleState, Any]) -> None:
    state, _ = sample
    st = ConsoleState(schedules={0: NUI})
    st.apply_messages(sample[1]["subgrids"], T0)
    for c in state.series.values():  # reuse the reconstructed series
        st.series[c["channel"]] = dict(c)
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: T0 + 100)
    acts.set_image_goal(2, "fraction", 40)
    acts.image_by_time(T0 - 130, "previous")
    acts.refine_series(0, T0 - 600, T0 - 300)
    acts.queue_config(3, enabled=False)
    acts.queue_config(3, flush=True)
    acts.link_control(1, False)
    acts.dispatch("spare_config", {"percent": 0, "link": 0})
    acts.propose_schedule(0, [{"owner": 1, "duration": 10, "guard": 1},
                              {"owner": 2, "duration": 30, "guard": 2}])
    kinds = [type(x) for x in sent]
    assert kinds == [m.ImageGoal, m.ImageByTimeRequest, m.TimeSeriesRequest, m.QueueConfig,
                     m.QueueConfig, m.LinkControl, m.SpareConfig, m.ScheduleUpdate]
    assert sent[6] == m.SpareConfig(sent[6].command_id, 0, None, 0)
    for x in sent:
        assert wire.decode(wire.encode(x)) == x
    assert sent[1].direction == m.TimeDirection.BEFORE and sent[1].stamp == to_stamp(T0 - 130)
    assert sent[2].max_error > 0
    sched = sent[-1]
    assert isinstance(sched, m.ScheduleUpdate)
    assert sched.version == 1 and sched.activate_cycle == int((T0 + 100) // 120) + 2
    assert len({x.command_id for x in sent}) == len(sent)
    snap = st.snapshot()
    assert len(snap["commands"]) == len(sent)
    assert st.images[2].goal == ("FRACTION", 40)
    assert snap["link"]["schedules"][0]["proposed"]["status"] == "sent"


def test_image_region_is_a_wire_command_drawn_with_its_state() -> None:
    """``image_region``: quality in dB from the page, 0.1 dB on the wire; the command says it in
    words; the image lists the region with its command's state, and a refusal's reason."""
    st = ConsoleState(schedules={0: NUI})
    feed_sample(st, t0=T0)
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: T0)
    (msg,) = acts.dispatch("image_region", {"image_id": 1, "x0": 100.4, "y0": 60, "x1": 20,
                                            "y1": 10})  # corners in any order
    assert msg == m.ImageRegionRequest(msg.command_id, 1, 20, 10, 100, 60, m.RegionGoal.QUALITY, 300)
    assert wire.decode(wire.encode(msg)) == msg
    st.images[2].decoded_meta["layers"] = 18  # as an image coded with 18 layers says
    budget = acts.image_region(2, 0, 0, 160, 120, kind="bytes", value=2000)
    assert (budget.kind, budget.value) == (m.RegionGoal.BYTES, 2000)
    layer = acts.image_region(2, 0, 0, 8, 8, kind="layer", value=18)
    assert (layer.kind, layer.value) == (m.RegionGoal.LAYER, 18)
    assert sent == [msg, budget, layer]
    snap = st.snapshot()
    assert snap["commands"][-1]["summary"] == "image 1 region 20..100 x 10..60 to 30 dB"
    assert snap["commands"][-2]["summary"] == "image 2 region 0..160 x 0..120 within 2000 bytes"
    item = next(i for i in snap["images"]["items"] if i["image_id"] == 1)
    assert item["precincts"] and [(r["box"], r["kind"], r["value"], r["state"]) for r in item["regions"]] \
        == [([20, 10, 100, 60], "quality", 30.0, "requested")]
    st.apply_event(CommandResult(T0 + 5, msg.command_id, m.AckStatus.REJECTED, msg))
    (row,) = next(i for i in st.snapshot()["images"]["items"] if i["image_id"] == 1)["regions"]
    assert row["state"] == "rejected" and "coded without precincts" in row["reason"]
    st.apply_event(CommandResult(T0 + 6, budget.command_id, m.AckStatus.ACCEPTED, budget))
    rows = next(i for i in st.snapshot()["images"]["items"] if i["image_id"] == 2)["regions"]
    assert [r["state"] for r in rows] == ["accepted", "requested"]


@pytest.mark.parametrize("args,words", [
    (dict(image_id=1, x0=10, y0=10, x1=10, y1=50), "empty"),
    (dict(image_id=1, x0=0, y0=0, x1=161, y1=50), "outside the 160 x 120 image"),
    (dict(image_id=1, x0=-3, y0=0, x1=16, y1=50), "outside"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1="nan"), "finite"),
    (dict(image_id=9, x0=0, y0=0, x1=16, y1=16), "not announced"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, value=5), "outside 10..60 dB"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, value=61), "outside 10..60 dB"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, kind="bytes", value=0), "1..65535"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, kind="bytes", value=70000), "1..65535"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, kind="layer", value=0), "outside 1..18"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, kind="layer", value=19), "outside 1..18"),
    (dict(image_id=1, x0=0, y0=0, x1=16, y1=16, kind="sharpest"), "unknown region goal"),
    (dict(image_id=0, x0=0, y0=0, x1=16, y1=16), "coded without precincts"),
])
def test_image_region_checks_its_box_and_goal(args: dict[str, Any], words: str) -> None:
    st = ConsoleState(schedules={0: NUI})
    feed_sample(st, t0=T0)
    st.images[0].decoded_meta["precincts"] = 0  # as an image coded without precincts says
    st.images[1].decoded_meta["layers"] = 18  # and one coded with 18 quality layers
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: T0)
    before = st.snapshot()["commands"]
    with pytest.raises(RequestRejected, match=words):
        acts.dispatch("image_region", args)
    assert sent == [] and st.snapshot()["commands"] == before


def test_image_region_through_the_node_s_receiver() -> None:
    """On a node, the imagery receiver sends the region (and retries it): the console records
    it once, and shows the layers complete inside it as the receiver counts them."""
    from coex_apps.console.testing import drain
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput
    from coex_plugins.imagery.synth import seafloor

    mod = ImageryModality()
    tx, rx = mod.sender(), mod.receiver()
    st = ConsoleState(schedules={0: NUI}, receivers={"imagery": rx})
    tx.ingest(ImageInput(seafloor(120, 160, seed=1), T0 - 10, 1.0, 2.0), T0)
    for msg in drain(tx, T0)[:30]:
        for p in rx.receive(msg, T0):
            st.apply_product("imagery", p, T0)
    iid = next(iter(rx.images))
    sent: list[m.Message] = []
    acts = ConsoleActions(st, sent.append, lambda: T0)
    req = acts.image_region(iid, 0, 0, 64, 64)
    assert sent == []  # the receiver sends it at the node's next poll
    assert [x for x in rx.poll(T0) if isinstance(x, m.ImageRegionRequest)] == [req]
    for p in rx.products():
        st.apply_product("imagery", p, T0)
    (row,) = next(i for i in st.snapshot()["images"]["items"] if i["image_id"] == iid)["regions"]
    assert row["box"] == [0, 0, 64, 64] and row["state"] == "requested"
    assert isinstance(row["layers_complete"], int)
    assert [c["kind"] for c in st.snapshot()["commands"]] == ["ImageRegionRequest"]
    for p in rx.receive(m.CommandAck(req.command_id, m.AckStatus.ACCEPTED), T0 + 5):
        st.apply_product("imagery", p, T0 + 5)  # the receiver hears the answer
    (row,) = next(i for i in st.snapshot()["images"]["items"] if i["image_id"] == iid)["regions"]
    assert row["state"] == "accepted"


def test_a_region_served_as_a_crop_is_listed_with_the_crop() -> None:
    """A region the vehicle answered with a crop: the snapshot's region row says ``crop``, its
    bytes and whether it is shown, with a link to the crop's picture (what it shows of the box);
    the crop is not an image of its own in the images section; a console restored from a store
    saved before crops has none."""
    from coex_plugins.imagery.sim import region_transfer
    from coex_plugins.imagery.synth import seafloor

    run = region_transfer(seafloor(240, 320, seed=4), (0, 0, 160, 120), "quality", 35.0, mtu=128, base="layer:1")
    assert run.crop is not None
    st = ConsoleState(schedules={0: NUI}, receivers={"imagery": run.receiver})
    for p in run.receiver.products():
        st.apply_product("imagery", p, T0)
    items = st.snapshot()["images"]["items"]
    assert [i["image_id"] for i in items] == [0]
    (row,) = items[0]["regions"]
    crop = row["crop"]
    assert row["served"] == "crop" and row["state"] == "accepted" and row["bytes"] == len(run.crop.enc.body)
    assert crop["image_id"] == run.crop.image_id and (crop["width"], crop["height"]) == (160, 120)
    assert crop["complete"] and crop["shown"] and crop["held_bytes"] == crop["total_bytes"]
    assert crop["png"].startswith(f"/crop/{run.crop.image_id}.png?v=")
    png = st.crop_png(run.crop.image_id)
    assert png is not None and png.startswith(b"\x89PNG") and st.crop_png(999) is None
    # a console saved before crops (state version 1) is given none on load
    from coex_apps.console.state import _upgrade_state

    assert _upgrade_state({"log": []}, 1)["crops"] == {}


# ----------------------------------------------------------------------------- server


def _get(url: str) -> tuple[int, bytes, str]:
    with urllib.request.urlopen(url, timeout=5) as r:
        return r.status, r.read(), r.headers.get("Content-Type", "")


def _post(url: str, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_server_pages_actions_and_events(subgrids: list[m.Subgrid]) -> None:
    st = fresh(subgrids)
    sent: list[m.Message] = []
    hub = ConsoleHub(st, sent.append, lambda: T0)
    with serve(hub, "127.0.0.1", 0) as srv:
        assert srv.server_address[0] == "127.0.0.1"
        code, body, ctype = _get(srv.url)
        assert code == 200 and b"map-canvas" in body and ctype.startswith("text/html")
        for name in ("app.js", "style.css"):
            assert _get(srv.url + "static/" + name)[0] == 200
        code, png, ctype = _get(srv.url + "map/0.png")
        assert ctype == "image/png" and png == st.map_png(0)
        state = json.loads(_get(srv.url + "api/state")[1])
        assert state["map"]["levels"]
        code, ans = _post(srv.url + "api/action", {"action": "queue_config",
                                                   "args": {"stream": 4, "priority": 70}})
        assert code == 200 and ans["sent"][0]["type"] == "QueueConfig" and ans["sent"][0]["priority"] == 70
        assert sent == [m.QueueConfig(0, 4, False, None, 70, None, None, None)]
        code, ans = _post(srv.url + "api/action", {"action": "queue_config", "args": {"stream": 99}})
        assert code == 400 and "stream" in ans["error"] and len(sent) == 1
        with pytest.raises(urllib.error.HTTPError):
            _get(srv.url + "static/../server.py")
        # another site's page cannot act: not JSON, or another origin
        for headers, code in (({"Content-Type": "text/plain"}, 415),
                              ({"Content-Type": "application/json",
                                "Origin": "http://evil.example"}, 403)):
            req = urllib.request.Request(srv.url + "api/action", method="POST", headers=headers,
                                         data=b'{"action": "queue_config", "args": {"stream": 4, "flush": true}}')
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(req, timeout=5)
            assert err.value.code == code
        assert len(sent) == 1
        # two browsers on the event stream both see a change made after they connected
        streams = [urllib.request.urlopen(srv.url + "api/events", timeout=5) for _ in range(2)]
        try:
            firsts = [_read_event(s) for s in streams]
            assert all(ev == "snapshot" for ev, _ in firsts)
            hub.messages([m.VehicleStatus(to_stamp(T0), 5.0, 6.0, 40.0, 20.0, 10.0, 1.0, 90,
                                          m.VehicleMode.SURVEY, 0)], T0)
            for s in streams:
                _ev, data = _read_event(s, want="update")
                assert data["vehicle"]["status"]["x"] == 5.0
        finally:
            for s in streams:
                s.close()


def _read_event(stream: Any, want: str | None = None) -> tuple[str, Any]:
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        name, data = "", ""
        while True:
            line = stream.readline().decode()
            if line in ("\n", ""):
                break
            if line.startswith("event: "):
                name = line[7:].strip()
            elif line.startswith("data: "):
                data = line[6:]
        if name and (want is None or name == want):
            return name, json.loads(data)
    raise AssertionError(f"no {want} event")


# ---------------------------------------------------------------------- node glue


def _pair(schedule: Schedule) -> tuple[Node, Node, RecordingSender, BathymetryReceiver, ConsoleHub, list[float]]:
    clock = [1000.0]
    top = Node(ChannelManager(1, [LinkConfig(0, schedule, dst=2)]))
    veh = Node(ChannelManager(2, [LinkConfig(0, schedule, dst=1)], queue_status_interval=30.0))
    sender = RecordingSender(BathymetrySender({"send_delay": 0.0, "levels": 4}))
    sender.ingest(survey_points(), 900.0)
    veh.add_sender(BathymetryModality, sender, StreamConfig(3, "map", priority=30))
    rx = BathymetryReceiver()
    top.add_receiver(BathymetryModality, rx)
    state = ConsoleState(schedules={0: schedule}, receivers=dict(top.receivers()))
    hub = ConsoleHub(state, NodeCommands(top, lambda: clock[0]), lambda: clock[0])
    return top, veh, sender, rx, hub, clock


def _run(top: Node, veh: Node, hub: ConsoleHub, clock: list[float], seconds: float) -> None:
    """Both nodes over a perfect in-memory link, 0.5 s steps (frames arrive at once)."""
    end = clock[0] + seconds
    while clock[0] < end:
        now = clock[0]
        for a, b in ((top, veh), (veh, top)):
            for tx in a.poll(now):
                for f in tx.frames:
                    b.receive(0, f, now)
        hub.pump(top, now)
        clock[0] += 0.5


def test_node_commands_are_acked_by_the_vehicle() -> None:
    sched = Schedule.simple([1, 2], 5.0, 0.5)
    top, veh, _sender, _rx, hub, clock = _pair(sched)
    _run(top, veh, hub, clock, 12)
    snap = hub.snapshot()
    assert snap["map"]["levels"], "subgrids from the vehicle reach the console (the receiver's)"
    assert {s["name"] for s in snap["queues"]["streams"]} >= {"stream 3"}
    hub.act("queue_config", {"stream": 3, "priority": 99})
    hub.act("propose_schedule", {"link": 0, "slots": [{"owner": 1, "duration": 4, "guard": 0.5},
                                                      {"owner": 2, "duration": 6, "guard": 0.5}]})
    _run(top, veh, hub, clock, 25)
    assert veh.manager.stream(3).config.priority == 99
    cmds = {c["kind"]: c["status"] for c in hub.snapshot()["commands"]}
    assert cmds["QueueConfig"] == "accepted" and cmds["ScheduleUpdate"] == "accepted"
    _run(top, veh, hub, clock, 25)
    assert veh.manager.schedule(0).version == 1 and top.manager.schedule(0).version == 1
    assert hub.snapshot()["link"]["schedules"][0]["version"] == 1


def test_map_region_through_the_bathymetry_receiver() -> None:
    sched = Schedule.simple([1, 2], 5.0, 0.5)
    top, veh, sender, rx, hub, clock = _pair(sched)
    hub.actions.map_receiver = rx
    _run(top, veh, hub, clock, 12)
    ans = hub.act("request_region", {"level": 0, "x_min": 30, "y_min": 35, "x_max": 40, "y_max": 45})
    assert ans and all(r.level == 0 for r in ans)
    assert hub.snapshot()["map"]["requests"][-1]["status"] == "waiting"
    _run(top, veh, hub, clock, 30)
    got = [x for x in sender.handled if isinstance(x, m.MapRoiRequest)]
    assert got and got[0].level == 0 and (got[0].x0, got[0].y0) == (3, 4)
    req = hub.snapshot()["map"]["requests"][-1]
    assert req["status"] in ("sent", "queued", "nothing newer")
    assert req["request_id"] == got[0].request_id


def test_a_third_party_modality_gets_the_generic_panel() -> None:
    """A modality without a panel of its own (the sample plugin's pings, found through its
    entry point) is shown in the generic panel: its products with the receiver's view of them;
    a view that raises is reported there, never stops the console."""
    from coex_core.registry import load_modality

    pings = load_modality("pings")
    sender = pings().sender(None)
    for t in range(5):
        sender.ingest((float(t), 20.0 + t), float(t))
    st = ConsoleState()
    for msg in sender.fill(400, 10.0):
        st.apply_message(msg, 10.0)
    snap = json.loads(json.dumps(st.snapshot(), allow_nan=False))
    (panel,) = snap["other"]["modalities"]
    assert panel["name"] == "pings" and panel["products"]
    assert all(p["version"] >= 1 and p["fields"] for p in panel["products"])

    def broken(product: Any) -> dict[str, Any]:
        raise RuntimeError("plugin bug")

    st.receivers["pings"].view = broken
    sender.ingest((15.0, 30.0), 15.0)  # a new ping: the receiver's product changes
    for msg in sender.fill(400, 20.0):
        st.apply_message(msg, 20.0)
    fields = [p["fields"] for p in st.snapshot()["other"]["modalities"][0]["products"]]
    assert any("view failed: plugin bug" in str(f.get("error")) for f in fields)


def test_pump_reports_events_and_link_state() -> None:
    sched = Schedule.simple([1, 2], 5.0, 0.5)
    top = Node(ChannelManager(1, [LinkConfig(0, sched, dst=2)]))
    st = ConsoleState()
    top.receive(0, b"\x00garbage", 1.0)
    assert pump(st, top, 2.0) == 1
    snap = st.snapshot()
    assert snap["link"]["bad_frames"] == 1 and snap["link"]["schedules"][0]["cycle"] == 10.0
    assert any("bad frame" in x["text"] for x in snap["log"])
    st.apply_event(CommandResult(3.0, 77, m.AckStatus.REJECTED))
    assert any("command 77: rejected (not sent from this console)" in x["text"]
               for x in st.snapshot()["log"])
    # a command the node sent for someone else (a script) is listed with its outcome
    goal = m.ImageGoal(78, 4, m.GoalKind.FULL, 0)
    st.apply_event(CommandResult(4.0, 78, m.AckStatus.ACCEPTED, goal))
    assert st.snapshot()["commands"][0] == {"command_id": 78, "kind": "ImageGoal",
                                            "summary": "ImageGoal (by the node)", "sent": 4.0,
                                            "status": "accepted", "answered": 4.0, "by": "", "answer": "", "image_id": None,
                                                "reason": ""}


def test_hub_is_safe_from_threads(subgrids: list[m.Subgrid]) -> None:
    st = fresh()
    hub = ConsoleHub(st, lambda msg: None, lambda: T0)
    errors: list[BaseException] = []

    def feed() -> None:
        try:
            for sg in subgrids[:200]:
                hub.messages([sg], T0)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=feed)
    t.start()
    seen: dict[str, int] = {}
    while t.is_alive():
        hub.wait_changes(seen, 0.05)
        json.dumps(hub.snapshot(), allow_nan=False)
    t.join()
    assert not errors
    assert sum(lv["subgrids"] for lv in hub.snapshot()["map"]["levels"]) == len(
        {(s.level, s.ix, s.iy) for s in subgrids[:200]})


def test_serve_a_node_or_a_view_only_state() -> None:
    sched = Schedule.simple([1, 2], 5.0, 0.5)
    top = Node(ChannelManager(1, [LinkConfig(0, sched, dst=2)]))
    rx = BathymetryReceiver()
    top.add_receiver(BathymetryModality, rx)
    with serve(top, "127.0.0.1", 0, stream_names={3: "map"}) as srv:
        hub = srv.hub
        assert hub.state.stream_names[3] == "map" and hub.state.stream_names[2] == "control"
        assert hub.actions.map_receiver is rx  # attach() found the bathymetry receiver
        code, ans = _post(srv.url + "api/action", {"action": "link_control",
                                                   "args": {"link": 0, "enabled": False}})
        assert code == 200 and ans["sent"][0]["type"] == "LinkControl"
        # the page never touches the node from its thread: the command waits for the loop
        assert not any(isinstance(e.message, m.LinkControl) for e in top.manager.stream(2).entries)
        # whoever drains the node's events (here: this test, as the demo's loop does) sends it
        # and feeds the console
        top.receive(0, b"\x00garbage", 5.0)
        events = top.events()
        assert [type(e).__name__ for e in events] == ["BadFrame"]
        assert any(isinstance(e.message, m.LinkControl) for e in top.manager.stream(2).entries)
        assert hub.snapshot()["link"]["bad_frames"] == 1
    st = ConsoleState()
    with serve(st, "127.0.0.1", 0) as srv:
        code, ans = _post(srv.url + "api/action", {"action": "link_control",
                                                   "args": {"link": 0, "enabled": False}})
        assert code == 400 and "view-only" in ans["error"]


def test_drive_simulation_feeds_the_console_and_the_caller() -> None:
    from coex import SimNetwork
    from coex_apps.console import attach, drive_simulation
    from coex_core.acoustic import AcousticChannel

    top = Node(ChannelManager(1, [LinkConfig(0, NUI)]))
    top.add_receiver(BathymetryModality, BathymetryReceiver())
    veh = Node(ChannelManager(2, [LinkConfig(0, NUI)], queue_status_interval=120.0))
    sender = BathymetrySender({"send_delay": 0.0, "levels": 4})
    sender.ingest(survey_points(), 0.0)
    veh.add_sender(BathymetryModality, sender, StreamConfig(3, "map", priority=30))
    net = SimNetwork({0: AcousticChannel(loss=0.2, seed=3)})
    net.add_node(veh, (0.0, 0.0, 100.0))
    net.add_node(top, (50.0, 0.0, 0.0))
    hub = attach(top, clock=lambda: net.now)
    seen: list[Any] = []
    drive_simulation(net, top, hub, 300.0, step=5.0, on_events=seen.extend)
    assert seen and net.now == pytest.approx(300.0)
    snap = hub.snapshot()
    assert snap["map"]["levels"] and snap["queues"]["streams"]
    assert snap["link"]["schedules"][0]["cycle"] == 120.0
    hub.act("queue_config", {"stream": 3, "priority": 64})
    drive_simulation(net, top, hub, 600.0, step=5.0)
    assert veh.manager.stream(3).config.priority == 64
    assert hub.snapshot()["commands"][0]["status"] == "accepted"


def test_the_map_is_the_receiver_s(subgrids: list[m.Subgrid]) -> None:
    """Attached to a node, the console shows the node's bathymetry receiver: the levels it
    holds, with each subgrid's stamp; the console keeps no mosaic of its own."""
    rx = BathymetryReceiver()
    st = ConsoleState(receivers={"bathymetry": rx})
    for sg in subgrids:
        for p in rx.receive(sg, T0):
            st.apply_product("bathymetry", p, T0)
    levels = {lv["level"]: lv for lv in st.snapshot()["map"]["levels"]}
    assert set(levels) == set(rx.levels())
    for k, lv in levels.items():
        assert lv["subgrids"] == len(rx.holdings(k))
        assert sorted((ix, iy) for ix, iy, _ in lv["tiles"]) == sorted(rx.holdings(k))
        z = st.level_grid(k)[0]  # type: ignore[index]
        np.testing.assert_array_equal(z, rx.level_product(k).data)
        assert z is not rx.level_product(k).data  # a copy: drawn outside the node's lock
    sg = subgrids[0]
    assert st.held_stamps(sg.level, sg.ix, sg.iy, 1, 1) == [rx.holdings(sg.level)[(sg.ix, sg.iy)]]
    # messages reach a node's receivers through the node, never through the console
    fresh_rx = BathymetryReceiver()
    st2 = ConsoleState(receivers={"bathymetry": fresh_rx})
    st2.apply_message(sg, T0)
    assert not fresh_rx.levels()


def test_pump_survives_an_event_the_console_cannot_show() -> None:
    from coex_core.channel.events import ProductUpdated, Received
    from coex_core.modality import Product

    class FakeNode:
        manager = ChannelManager(1, [LinkConfig(0, NUI)])

        def __init__(self) -> None:
            self._events = [
                ProductUpdated(1.0, "bathymetry", Product("map-level", "level-0", 1,
                                                          np.zeros((3, 5)), {"level": 0})),
                Received(1.5, 0, 2, m.Subgrid(0, 0, 0, 1, 1.0, 0.1, 8, m.SubgridEncoding.OFFSET,
                                              0, 4, None, (1, 2, 3))),  # 3 values for 64 cells
                Received(2.0, 0, 2, m.VehicleStatus(2, 1.0, 2.0, 3.0, None, 0.0, 0.0, 50,
                                                    m.VehicleMode.IDLE, 0)),
            ]

        def events(self) -> list[Any]:
            out, self._events = self._events, []
            return out

    st = ConsoleState()
    assert pump(st, FakeNode(), 3.0) == 3
    snap = json.loads(json.dumps(st.snapshot(), allow_nan=False))
    assert snap["vehicle"]["status"]["x"] == 1.0  # the good event after the odd ones is shown
    assert snap["map"]["levels"] == []
    assert any("could not show Received" in x["text"] for x in snap["log"])


def test_attached_node_driven_like_the_demo_loop() -> None:
    """The demo drains ``topside.events()`` itself and holds no console lock: the console still
    sees everything, and page commands (a schedule gets a new command id from the manager) are
    sent from the loop's thread and end up accepted."""
    from coex import SimNetwork
    from coex_apps.console import attach
    from coex_core.acoustic import AcousticChannel

    sched = Schedule.simple([1, 2], 10.0, 1.0)
    top = Node(ChannelManager(1, [LinkConfig(0, sched)]))
    top.add_receiver(BathymetryModality, BathymetryReceiver())
    veh = Node(ChannelManager(2, [LinkConfig(0, sched)], queue_status_interval=60.0))
    sender = BathymetrySender({"send_delay": 0.0, "levels": 3})
    sender.ingest(survey_points(), 0.0)
    veh.add_sender(BathymetryModality, sender, StreamConfig(3, "map", priority=30))
    net = SimNetwork({0: AcousticChannel(seed=1)})
    net.add_node(veh, (0.0, 0.0, 100.0))
    net.add_node(top, (50.0, 0.0, 0.0))
    hub = attach(top)
    mine: list[Any] = []

    def demo_loop(until: float) -> None:
        while net.now < until:
            net.run(min(until, net.now + 2.0))
            mine.extend(top.events())

    demo_loop(60.0)
    assert mine and hub.snapshot()["map"]["levels"]
    t = threading.Thread(target=lambda: hub.act("propose_schedule", {
        "link": 0, "slots": [{"owner": 1, "duration": 8, "guard": 1},
                             {"owner": 2, "duration": 12, "guard": 1}]}))
    t.start()
    t.join()
    (cmd,) = hub.snapshot()["commands"]
    demo_loop(200.0)
    snap = hub.snapshot()
    (cmd,) = snap["commands"]
    assert cmd["kind"] == "ScheduleUpdate" and cmd["status"] == "accepted"
    assert veh.manager.schedule(0).version == 1 and top.manager.schedule(0).version == 1
    assert snap["link"]["schedules"][0]["cycle"] == 20.0
    # a region someone else asked of the bathymetry receiver is shown too
    rx = hub.actions.map_receiver
    rx.request_area(0, 30.0, 30.0, 40.0, 40.0)
    demo_loop(260.0)
    reqs = hub.snapshot()["map"]["requests"]
    assert [r["level"] for r in reqs] == [0] and reqs[0]["status"] != "waiting"
    assert any("(by the node)" in c["summary"] for c in hub.snapshot()["commands"])
    assert any(type(e).__name__ == "CommandResult" for e in mine)  # the loop still gets them


def test_images_and_series_through_nodes() -> None:
    """Imagery and time series from a vehicle node: the gallery fills with bytes and
    thumbnails, channels with error bounds; a goal and a refinement from the console are
    accepted by the vehicle's senders."""
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput
    from coex_plugins.imagery.synth import seafloor
    from coex_plugins.timeseries import TimeSeriesModality

    sched = Schedule.simple([1, 2], 5.0, 0.5)
    clock = [2000.0]
    top = Node(ChannelManager(1, [LinkConfig(0, sched, dst=2)]))
    veh = Node(ChannelManager(2, [LinkConfig(0, sched, dst=1)]))
    data = dataset(duration=1200.0, period=1.0, seed=2, t0=700.0)
    img_tx = RecordingSender(ImageryModality().sender())
    ts_tx = RecordingSender(TimeSeriesModality().sender({
        "channels": [s.channel() for s in data], "block_samples": 256, "max_latency": 30.0}))
    for k in range(2):
        img_tx.ingest(ImageInput(seafloor(96, 128, seed=k), 1900.0 + 30 * k, 10.0 * k, 5.0), 1990.0)
    ts_tx.ingest({s.name: (s.times, s.values) for s in data}, 1990.0)
    veh.add_sender(ImageryModality, img_tx, StreamConfig(4, "images", priority=30))
    veh.add_sender(TimeSeriesModality, ts_tx, StreamConfig(5, "series", priority=30))
    top.add_receiver(ImageryModality, ImageryModality().receiver())
    top.add_receiver(TimeSeriesModality, TimeSeriesModality().receiver())
    state = ConsoleState(schedules={0: sched}, receivers=dict(top.receivers()))
    hub = ConsoleHub(state, NodeCommands(top, lambda: clock[0]), lambda: clock[0])
    _run(top, veh, hub, clock, 60)
    snap = hub.snapshot()
    items = {it["image_id"]: it for it in snap["images"]["items"]}
    assert len(items) == 2 and all(it["total_bytes"] for it in items.values())
    assert any(it["bytes_received"] > 0 and it["thumb"] for it in items.values())
    chans = {c["name"]: c for c in snap["series"]["channels"]}
    assert set(chans) == {s.name for s in data} and all(c.get("samples") for c in chans.values())
    first = min(items)
    hub.act("set_image_goal", {"image_id": first, "kind": "full"})
    hub.act("refine_series", {"channel": 0, "start": 1400.0, "end": 1500.0})
    _run(top, veh, hub, clock, 30)
    assert any(isinstance(x, m.ImageGoal) and x.image_id == first for x in img_tx.handled)
    assert any(isinstance(x, m.TimeSeriesRequest) and x.channel == 0 for x in ts_tx.handled)
    status = {c["kind"]: c["status"] for c in hub.snapshot()["commands"]}
    assert status == {"ImageGoal": "accepted", "TimeSeriesRequest": "accepted"}


def test_an_image_region_from_the_console_reaches_the_vehicle_through_nodes() -> None:
    """``image_region`` on a topside node: the node's imagery receiver sends it, the vehicle's
    imagery sender accepts it, and the console shows it accepted with the layers inside it."""
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput
    from coex_plugins.imagery.synth import seafloor

    sched = Schedule.simple([1, 2], 5.0, 0.5)
    clock = [2000.0]
    top = Node(ChannelManager(1, [LinkConfig(0, sched, dst=2)]))
    veh = Node(ChannelManager(2, [LinkConfig(0, sched, dst=1)]))
    img_tx = RecordingSender(ImageryModality().sender())
    img_tx.ingest(ImageInput(seafloor(96, 128, seed=0), 1900.0, 0.0, 5.0), 1990.0)
    veh.add_sender(ImageryModality, img_tx, StreamConfig(4, "images", priority=30))
    top.add_receiver(ImageryModality, ImageryModality().receiver())
    state = ConsoleState(schedules={0: sched}, receivers=dict(top.receivers()))
    hub = ConsoleHub(state, NodeCommands(top, lambda: clock[0]), lambda: clock[0])
    _run(top, veh, hub, clock, 40)
    iid = hub.snapshot()["images"]["items"][0]["image_id"]
    hub.act("image_region", {"image_id": iid, "x0": 0, "y0": 0, "x1": 48, "y1": 48, "value": 35})
    _run(top, veh, hub, clock, 60)
    got = [x for x in img_tx.handled if isinstance(x, m.ImageRegionRequest)]
    assert got and (got[0].x0, got[0].y0, got[0].x1, got[0].y1, got[0].value) == (0, 0, 48, 48, 350)
    (row,) = hub.snapshot()["images"]["items"][0]["regions"]
    assert row["state"] == "accepted" and isinstance(row["layers_complete"], int)
    assert [(c["summary"], c["status"]) for c in hub.snapshot()["commands"]] == [
        (f"image {iid} region 0..48 x 0..48 to 35 dB", "accepted")]


# ------------------------------------------------------------------ one topside, two users

def test_a_console_leaves_the_node_s_receivers_alone() -> None:
    """``coex topside`` and ``demo --gui`` attach the console to the node: its receivers stay
    the node's own objects (no wrapper that could lose a hook, as a wrapper once lost
    ``supersedes``), and a retried region request still replaces the earlier copy."""
    from coex_apps.console import attach
    from coex_core.channel import CONTROL_STREAM

    receiver = BathymetryReceiver({"levels": 3, "request_timeout": 100.0})
    tmgr = ChannelManager(1, [LinkConfig(0, Schedule.simple([1, 2], 5.0, 0.5), dst=2)])
    top = Node(tmgr)
    top.add_receiver(BathymetryModality, receiver)
    hub = attach(top, clock=lambda: 0.0)
    assert top.receiver("bathymetry") is receiver and hub.actions.map_receiver is receiver
    receiver.request_region(0, 0, 0, 1, 1)  # the vehicle never answers: retried every 100 s
    now = 0.0
    while now < 450.0:
        top.poll(now)
        top.events()
        now += 1.0
    (newest,) = [r.request_id for r in receiver.active_regions()]
    queued = [e.message.request_id for e in tmgr.stream(CONTROL_STREAM).entries
              if isinstance(e.message, m.MapRoiRequest)]
    assert queued == [newest]


def test_a_script_and_the_console_never_share_a_command_id() -> None:
    """A script asks the imagery receiver for an image goal while the person at the console sends
    a queue change the vehicle refuses. Each must get its own answer: the person's command shows
    rejected, the script's goal reaches the vehicle's sender and is accepted."""
    from coex import SimNetwork
    from coex_apps.console import attach
    from coex_core.acoustic import AcousticChannel
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput
    from coex_plugins.imagery.synth import seafloor

    sched = Schedule.simple([1, 2], 10.0, 1.0)
    top = Node(ChannelManager(1, [LinkConfig(0, sched, dst=2)]))
    images = ImageryModality().receiver()
    top.add_receiver(ImageryModality, images)
    veh = Node(ChannelManager(2, [LinkConfig(0, sched, dst=1)]))
    img_tx = RecordingSender(ImageryModality().sender())
    img_tx.ingest(ImageInput(seafloor(96, 128, seed=1), 10.0, 0.0, 5.0), 10.0)
    veh.add_sender(ImageryModality, img_tx, StreamConfig(4, "images", priority=30))
    net = SimNetwork({0: AcousticChannel(seed=1, loss=0.0)})
    net.add_node(veh, (0.0, 0.0, 100.0))
    net.add_node(top, (50.0, 0.0, 0.0))
    hub = attach(top, clock=lambda: net.now)

    def run(until: float) -> None:
        while net.now < until:
            net.run(min(until, net.now + 1.0))
            hub.pump(top, net.now)

    run(40.0)
    (image_id,) = [p.key for p in images.products() if p.kind == "image"] or [None]
    assert image_id is not None
    hub.act("queue_config", {"stream": 9, "priority": 5})  # no stream 9 on the vehicle
    run(41.0)  # the console's command is queued in the node before the script's
    goal = images.request_goal(int(image_id), "layer", 3, net.now)
    run(120.0)
    assert any(isinstance(x, m.ImageGoal) and x.command_id == goal.command_id
               for x in img_tx.handled), "the vehicle took the script's goal as a new command"
    assert not images.pending_requests(), "the script's goal was acknowledged"
    person = [c for c in hub.snapshot()["commands"] if c["kind"] == "QueueConfig"]
    assert [c["status"] for c in person] == ["unknown_target"], hub.snapshot()["commands"]


def test_tap_receiver_is_deprecated_and_wraps_nothing() -> None:
    from coex_apps.console import tap_receiver

    rx = BathymetryReceiver()
    with pytest.warns(DeprecationWarning, match="node's receivers"):
        assert tap_receiver(rx, ConsoleState()) is rx


# ------------------------------------------------------------------------------ surveys

FENCE = {"polygon": [[-50, -50], [50, -50], [50, 50], [-50, 50]], "min_altitude": 2.0}


def _survey_pair() -> tuple[Node, Node, Any, ConsoleHub, list[float]]:
    """A topside node with the survey receiver and its console, and a vehicle whose survey
    sender keeps it inside a 100 m square."""
    from coex_plugins.survey import SurveyModality, SurveyReceiver, SurveySender

    clock = [1000.0]
    sched = Schedule.simple([1, 2], 5.0, 0.5)
    top = Node(ChannelManager(1, [LinkConfig(0, sched, dst=2)]))
    veh = Node(ChannelManager(2, [LinkConfig(0, sched, dst=1)]))
    tx = SurveySender({"geofence": FENCE})
    veh.add_sender(SurveyModality, tx, StreamConfig(7, "survey", priority=90))
    top.add_receiver(SurveyModality, SurveyReceiver())
    state = ConsoleState(schedules={0: sched}, receivers=dict(top.receivers()))
    hub = ConsoleHub(state, NodeCommands(top, lambda: clock[0]), lambda: clock[0])
    return top, veh, tx, hub, clock


def test_survey_action_sends_a_survey_command_and_shows_the_vehicle_s_reason() -> None:
    """The page's ``survey`` action goes through the node's survey receiver; the vehicle refuses
    a lawnmower that leaves its geofence, and the page is told "rejected" with the reason in
    words (only the sections that changed)."""
    top, veh, tx, hub, clock = _survey_pair()
    seen = dict(hub.state.versions)
    (cmd,) = hub.act("survey", {"kind": "lawnmower", "x": 40, "y": 0, "heading": 0, "length": 40,
                                "width": 40, "spacing": 10, "altitude": 5, "depth": None,
                                "speed": "", "append": False, "points": []})
    assert isinstance(cmd, m.SurveyCommand) and cmd.kind == m.SurveyKind.LAWNMOWER
    assert (cmd.x, cmd.y, cmd.heading, cmd.length, cmd.width, cmd.spacing, cmd.altitude) == (
        40.0, 0.0, 0.0, 40.0, 40.0, 10.0, 5.0)
    changed = hub.wait_changes(seen, 0.1)
    assert "surveys" in changed and "map" not in changed and "images" not in changed
    (item,) = changed["surveys"]["items"]
    assert (item["survey_id"], item["kind"], item["state"]) == (cmd.survey_id, "lawnmower", "requested")
    assert len(item["waypoints"]) == 10 and item["waypoints"][0] == [20.0, -20.0]  # port row first
    (c,) = changed["commands"]
    assert c["kind"] == "SurveyCommand" and c["status"] == "requested"
    assert "lawnmower 40 x 40 m at (40, 0)" in c["summary"]

    _run(top, veh, hub, clock, 20)
    got = tx.surveys[cmd.survey_id].command  # what the vehicle's survey sender was given
    assert got == cmd
    changed = hub.wait_changes(seen, 0.1)
    (item,) = changed["surveys"]["items"]
    assert item["state"] == "rejected" and item["reason"] == "OUTSIDE_GEOFENCE"
    assert item["text"] == "waypoint 8 is 10 m outside the geofence"  # (60, -20): 10 m east of it
    assert [h[1] for h in item["history"]] == ["requested", "rejected", "rejected"]
    assert changed["commands"][0]["status"] == "rejected"
    assert any("waypoint 8 is 10 m outside" in line["text"] and line["level"] == "warn"
               for line in changed["log"])
    json.dumps(hub.snapshot(), allow_nan=False)

    # a survey inside the fence is accepted, then started (its waypoint) and completed
    (ok,) = hub.act("survey", {"kind": "line", "x": -20, "y": 0, "heading": 90, "length": 40,
                               "altitude": 5})
    _run(top, veh, hub, clock, 20)
    from coex_plugins.survey import SurveyReport

    tx.ingest(SurveyReport(ok.survey_id, m.SurveyState.STARTED, clock[0], index=1), clock[0])
    _run(top, veh, hub, clock, 20)
    items = {s["survey_id"]: s for s in hub.snapshot()["surveys"]["items"]}
    assert (items[ok.survey_id]["state"], items[ok.survey_id]["index"]) == ("started", 1)
    assert items[ok.survey_id]["waypoints"] == [[-20.0, 0.0], [20.0, 0.0]]
    assert items[cmd.survey_id]["state"] == "rejected"  # the other one is still listed

    # the console saved (a store saves it with the node and its receivers) shows the same
    # surveys after a restart
    from coex_core.state import dumps, loads

    state2 = loads(dumps(hub.state))
    assert state2.survey_receiver is not hub.state.survey_receiver
    assert state2.snapshot()["surveys"] == hub.snapshot()["surveys"]


def test_a_survey_that_cannot_be_sent_is_refused_with_a_clear_error() -> None:
    top, _veh, _tx, hub, _clock = _survey_pair()
    for args, match in [({"kind": "spiral", "x": 0, "y": 0}, "unknown survey kind"),
                        ({"kind": "line", "x": 0, "y": 0, "length": 10}, "heading"),
                        ({"kind": "goto", "x": 1e6, "y": 0}, "cannot be sent"),
                        ({"kind": "goto", "x": "nan", "y": 0}, "finite"),
                        ({"kind": "goto", "x": 0, "y": 0, "altitude": 5, "depth": 9}, "not both"),
                        ({"kind": "waypoints", "x": 0, "y": 0, "points": [[1]]}, "pairs"),
                        ({"kind": "goto", "x": 0}, "needs x and y"),
                        ({"kind": "waypoints", "points": []}, "needs x and y"),
                        ({"kind": "waypoints", "points": "12"}, "list of"),
                        ({"kind": "goto", "x": 0, "y": 0, "hdg": 5}, "no argument 'hdg'")]:
        with pytest.raises(RequestRejected, match=match):
            hub.act("survey", args)
    assert hub.snapshot()["surveys"]["items"] == [] and hub.snapshot()["commands"] == []
    assert not top.receiver("survey").pending_requests()
    with serve(hub, "127.0.0.1", 0) as srv:  # the page gets the reason as the error
        code, ans = _post(srv.url + "api/action", {"action": "survey", "args": {
            "kind": "line", "x": 0, "y": 0, "length": 10}})
        assert code == 400 and not ans["ok"] and "heading" in ans["error"]
        # the waypoint form: every waypoint in points (the first becomes x, y)
        code, ans = _post(srv.url + "api/action", {"action": "survey", "args": {
            "kind": "waypoints", "points": [[1, 2], [3, 4], [5, 6]]}})
        assert code == 200, ans
        (cmd,) = ans["sent"]
        assert (cmd["x"], cmd["y"], len(cmd["points"])) == (1.0, 2.0, 2), cmd
    assert hub.snapshot()["surveys"]["available"] is True
    # a console without the survey receiver (view only) says so, and the page disables the tool
    view = ConsoleState()
    with pytest.raises(RequestRejected, match="survey receiver"):
        ConsoleActions(view, lambda msg: None, lambda: T0).survey("goto", 0, 0)
    assert view.snapshot()["surveys"] == {"items": [], "available": False,
                                          "states": ["requested", "accepted", "started", "completed",
                                                     "rejected", "aborted", "given up"]}


def test_topside_runs_the_survey_receiver_by_default() -> None:
    from coex_apps.console.cli import build_topside

    app = build_topside("loopback://survey-default", "127.0.0.1", 0, clock=lambda: 100.0)
    try:
        assert app.node.receiver("survey") is app.hub.state.survey_receiver is not None
        (cmd,) = app.hub.act("survey", {"kind": "goto", "x": 3, "y": 4})
        app.step()
        snap = app.hub.snapshot()
        assert snap["surveys"]["items"][0]["state"] == "requested"
        assert snap["commands"][0]["summary"] == f"survey {cmd.survey_id}: go to (3, 4)"
    finally:
        app.close()


def _merge_map(old: dict[str, Any], upd: dict[str, Any]) -> dict[str, Any]:
    """What the page does with a map delta (app.js mergeMap)."""
    had = {lv["level"]: lv for lv in old["levels"]}
    levels = []
    for lv in upd["levels"]:
        if lv.get("same"):
            levels.append(had[lv["level"]])
        elif "tiles_changed" in lv:
            tiles = {(t[0], t[1]): t for t in had[lv["level"]]["tiles"]}
            tiles.update({(t[0], t[1]): t for t in lv["tiles_changed"]})
            for a, b in lv["tiles_removed"]:
                tiles.pop((a, b), None)
            part = {k: v for k, v in lv.items() if k not in ("tiles_changed", "tiles_removed")}
            levels.append({**part, "tiles": list(tiles.values())})
        else:
            levels.append(lv)
    return {**{k: v for k, v in upd.items() if k != "delta"}, "levels": levels}


def test_an_update_after_one_new_subgrid_sends_only_what_changed(subgrids: list[m.Subgrid]) -> None:
    """A page's update after one new subgrid carries that level's changed block, not the whole
    map section; merged into what the page holds it gives the whole section."""
    import json

    def size(x: Any) -> int:
        return len(json.dumps(x, separators=(",", ":")))

    fine = [sg for sg in subgrids if sg.level == 0]
    last = fine[-1]
    st = fresh([sg for sg in subgrids if sg is not last])
    held_map = st.snapshot()["map"]
    seen: dict[str, Any] = dict(st.versions)
    seen["_map"] = st.map_held(held_map)
    assert st.apply_message(last, T0 + 5) == {"map"}
    whole = st.section("map")
    upd = st.changes(seen)
    assert set(upd) == {"map"} and upd["map"]["delta"] is True
    assert size(upd["map"]) * 5 < size(whole), (size(upd["map"]), size(whole))
    same = [lv["level"] for lv in upd["map"]["levels"] if lv.get("same")]
    assert sorted(same) == [1, 2, 3], upd["map"]["levels"]
    changed = next(lv for lv in upd["map"]["levels"] if lv["level"] == 0)
    assert len(changed["tiles_changed"]) == 1 and changed["tiles_removed"] == []
    merged = _merge_map(held_map, upd["map"])
    key = lambda lv: (lv["level"], sorted(map(tuple, lv["tiles"])))  # noqa: E731
    assert [key(lv) for lv in merged["levels"]] == [key(lv) for lv in whole["levels"]]
    assert {k: v for k, v in merged.items() if k != "levels"} == {
        k: v for k, v in whole.items() if k != "levels"}
    seen.update({k: st.versions[k] for k in upd})
    assert st.changes(seen) == {}  # nothing new: nothing sent
    # without "_map" (an API client, a test): the whole section, as before
    plain = st.changes({k: v for k, v in seen.items() if k != "map" and k != "_map"})
    assert "tiles" in plain["map"]["levels"][0] and "delta" not in plain["map"]


# ------------------------------------------------------------------ a quiet, true event log
def test_repeated_events_are_counted_in_one_entry_not_listed() -> None:
    """The flood seen at sea: 60 of 60 entries "stream 2: 1 dropped (superseded)". Drops of one
    stream and reason within ten minutes of the first are one entry, updated in place (the
    same entry, its total, its last time); the events that matter stay in the list; another
    ten minutes start a new entry; bad frames count the same way."""
    from coex_core.channel.events import Dropped

    st = ConsoleState()
    st.apply_event(LinkChanged(T0, 0, False, False))
    for k in range(400):  # every 3 s for 20 min: 1 message each, sometimes 3 at once
        st.apply_event(Dropped(T0 + 3.0 * k, 2, "superseded", 3 if k % 100 == 0 else 1))
        if k == 50:
            st.apply_event(LinkChanged(T0 + 3.0 * k, 0, True, False))
    log = st.snapshot()["log"]
    texts = [e["text"] for e in log]
    # k = 0..200 (t within 600 s of the first): 201 events, 207 messages (3 at k = 0, 100, 200)
    assert texts[:2] == ["link 0 disabled", "stream 2: 207 dropped (superseded) in 10 min"]
    assert texts[2] == "link 0 enabled"  # still there: a drop does not push it out
    assert texts[3] == "stream 2: 201 dropped (superseded) in 9 min 54 s"  # k = 201..399
    assert len(log) == 4
    first = log[1]
    assert (first["t"], first["last"], first["n"], first["count"], first["level"]) == (T0, T0 + 600.0, 201, 207,
                                                                                     "warn")
    assert "key" not in first and "base" not in first  # the page gets what it shows
    # another kind, another stream, another reason: their own entries
    st.apply_event(Dropped(T0 + 1300.0, 3, "superseded"))
    st.apply_event(Dropped(T0 + 1301.0, 2, "ttl", 4))
    st.apply_event(BadFrame(T0 + 1302.0, 0, "crc"))
    st.apply_event(BadFrame(T0 + 1310.0, 0, "crc"))
    texts = [e["text"] for e in st.snapshot()["log"][-3:]]
    assert texts == ["stream 3: 1 dropped (superseded)", "stream 2: 4 dropped (ttl)",
                     "bad frame on link 0: crc (2 times in 8 s)"]


def test_the_counted_log_is_bounded_and_survives_a_save() -> None:
    from coex_apps.console.state import MAX_REPEATS
    from coex_core.channel.events import Dropped
    from coex_core.state import dumps, loads

    st = ConsoleState(max_log=50)
    for k in range(1000):  # 1000 different streams and reasons: a bounded log, bounded keys
        st.apply_event(Dropped(T0 + k, k % 250, f"reason {k}"))
    assert len(st.log) == 50 and len(st._repeats) <= MAX_REPEATS
    st.apply_event(Dropped(T0 + 2000.0, 7, "superseded"))
    again = loads(dumps(st))
    again.apply_event(Dropped(T0 + 2010.0, 7, "superseded", 2))
    assert again.snapshot()["log"][-1]["text"] == "stream 7: 3 dropped (superseded) in 10 s"
    assert len(again.log) == 50
    # an entry that left the log is not updated out of sight: the next event is a new entry
    small = ConsoleState(max_log=3)
    small.apply_event(Dropped(T0, 1, "superseded"))
    for k in range(3):
        small.apply_event(LinkChanged(T0 + 1 + k, 0, bool(k % 2), False))
    small.apply_event(Dropped(T0 + 10.0, 1, "superseded"))
    assert small.snapshot()["log"][-1]["text"] == "stream 1: 1 dropped (superseded)"


def test_survey_outcomes_come_from_the_receiver_in_words_and_in_the_vehicles_order() -> None:
    """The console shows the survey receiver's records (no tracking of its own): a refusal by
    the autonomy, no answer from it, a pilot's override and a completion read apart, in the
    snapshot and in the event log; a history that arrived out of order is shown in the
    receiver's (vehicle time) order, each state logged once."""
    from coex_plugins.survey import SurveyReceiver

    rx = SurveyReceiver()
    st = ConsoleState(receivers={"survey": rx})
    cmds = [rx.request("goto", 10.0 * k, 0.0, T0) for k in range(4)]
    R, S = m.SurveyReason, m.SurveyState

    def feed(msg: m.Message, now: float) -> None:
        for p in rx.receive(msg, now):
            st.apply_product("survey", p, now)

    for c in cmds:
        feed(m.CommandAck(c.command_id, m.AckStatus.ACCEPTED), T0 + 5)
    feed(m.SurveyStatus(cmds[0].survey_id, S.REJECTED, R.AUTONOMY_REFUSED, to_stamp(T0 + 8), None, 14.0,
                        "MAV_MISSION_DENIED"), T0 + 20)
    feed(m.SurveyStatus(cmds[1].survey_id, S.REJECTED, R.AUTONOMY_NO_ANSWER, to_stamp(T0 + 9), None, 6.0), T0 + 20)
    feed(m.SurveyStatus(cmds[2].survey_id, S.ABORTED, R.MANUAL_OVERRIDE, to_stamp(T0 + 30), None, 2.0,
                        "left AUTO for ALT_HOLD"), T0 + 40)
    feed(m.SurveyStatus(cmds[3].survey_id, S.COMPLETED, R.NONE, to_stamp(T0 + 60)), T0 + 70)
    feed(m.SurveyStatus(cmds[3].survey_id, S.STARTED, R.NONE, to_stamp(T0 + 10), 0), T0 + 80)  # late
    rows = {r["survey_id"]: r for r in st.snapshot()["surveys"]["items"]}
    got = [(rows[c.survey_id]["outcome"], rows[c.survey_id]["text"]) for c in cmds]
    assert got == [
        ("refused by autonomy", "the vehicle's autonomy refused it (code 14): MAV_MISSION_DENIED"),
        ("no answer from autonomy", "no answer from the vehicle's autonomy (after 6 tries)"),
        ("taken over", "taken over on the vehicle (manual override): left AUTO for ALT_HOLD"),
        ("completed", ""),
    ]
    done = rows[cmds[3].survey_id]
    assert [h[1] for h in done["history"]] == ["requested", "accepted", "started", "completed"]
    assert done["history"] == [[t, s, x] for t, s, x in rx.surveys[cmds[3].survey_id].history]  # as is
    log = [(e["t"], e["text"]) for e in st.snapshot()["log"]]
    sid = cmds[3].survey_id
    assert [x for _, x in log if x.startswith(f"survey {sid} ")] == [
        f"survey {sid} accepted", f"survey {sid} completed", f"survey {sid} started: heading for waypoint 0"]
    assert (T0 + 10, f"survey {sid} started: heading for waypoint 0") in log  # at the vehicle's time, once
    assert sum(x.startswith(f"survey {sid} completed") for _, x in log) == 1
    assert any(x == f"survey {cmds[1].survey_id} no answer from autonomy: no answer from the vehicle's "
                    "autonomy (after 6 tries)" for _, x in log)


def test_the_console_keeps_the_newest_images_only() -> None:
    """A dive of several days: the console's images (with their decoded pictures, saved with
    the console) stay at MAX_IMAGES, the newest by time."""
    from coex_apps.console.state import MAX_IMAGES
    from coex_core.modality import Product

    st = ConsoleState(schedules={0: NUI})
    n = MAX_IMAGES + 44
    for i in range(n):
        st.apply_product("imagery", Product("image", f"image-{i}", 1, np.zeros((8, 8), np.uint8),
                                            {"image_id": i, "time": 100.0 + i}), 100.0 + i)
    assert len(st.images) == MAX_IMAGES
    assert sorted(st.images) == list(range(n - MAX_IMAGES, n))
    items = st.snapshot()["images"]["items"]
    assert len(items) <= MAX_IMAGES and {it["image_id"] for it in items} <= set(range(n - MAX_IMAGES, n))

"""Imagery modality: codec (no header sent, whole packets, repair), sender and receiver behaviour."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from coex_core import wire
from coex_core.errors import ConfigError, DecodeError, RequestRejected
from coex_core.messages import (
    AckStatus,
    ByteRange,
    CommandAck,
    GoalKind,
    ImageAck,
    ImageAnnounce,
    ImageByTimeRequest,
    ImageFragment,
    ImageGoal,
    TimeDirection,
    TransferProgress,
)
from coex_plugins.imagery import ImageInput, ImageryModality, ImageryReceiver, ImagerySender, codec
from coex_plugins.imagery.codec import CodingParams
from coex_plugins.imagery.sender import fragment_size
from coex_plugins.imagery.sim import Transfer
from coex_plugins.imagery.synth import seafloor

SMALL = {"layer_bytes": [30, 60, 120, 240, 480, 900, 1600, 3000], "rto": 12.0}


@pytest.fixture(scope="module")
def img() -> np.ndarray:
    return seafloor(96, 128, seed=5)


@pytest.fixture(scope="module")
def enc(img: np.ndarray) -> codec.Encoded:
    return codec.encode_image(img, CodingParams(layer_bytes=(30, 60, 120, 240, 480, 900, 1600, 3000)))


# ------------------------------------------------------------------------------ codec


def test_params_code_roundtrip_and_invalid() -> None:
    for prog in codec.PROGRESSIONS:
        code = codec.params_code(prog, 6, 10, True, False)
        sp = codec.parse_params(code)
        assert (sp.progression, sp.resolutions, sp.layers, sp.irreversible, sp.colour) == (prog, 6, 10, True, False)
        assert code < 2**13
    with pytest.raises(DecodeError):
        codec.parse_params(7 << 10)


def test_packet_order_lrcp_and_rlcp() -> None:
    lrcp = codec.packet_order(codec.parse_params(codec.params_code("LRCP", 3, 2, False, True)))
    assert lrcp.shape == (18, 4)
    assert lrcp[:4].tolist() == [[0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 2, 0], [0, 1, 0, 0]]
    rlcp = codec.packet_order(codec.parse_params(codec.params_code("RLCP", 3, 2, False, False)))
    assert rlcp.tolist() == [[0, 0, 0, 0], [1, 0, 0, 0], [0, 1, 0, 0], [1, 1, 0, 0], [0, 2, 0, 0], [1, 2, 0, 0]]
    # 256-sample precincts on 640 x 480: packets per layer 1 x 5, then 2 x 1, then 3 x 2
    sp = codec.parse_params(codec.params_code("LRCP", 7, 2, True, False, 256))
    pre = codec.packet_order(sp, 640, 480)
    assert len(pre) == sp.n_packets(640, 480) == 2 * 13
    assert pre[5:13, 3].tolist() == [0, 1, 0, 1, 2, 3, 4, 5] and pre[13].tolist() == [1, 0, 0, 0]


def test_header_is_not_sent_and_is_rebuilt(enc: codec.Encoded) -> None:
    hdr = codec.main_header(enc.params, enc.width, enc.height)
    assert hdr[:2] == b"\xff\x4f" and b"\xff\x64" not in hdr  # SOC, no COM
    assert not enc.body.startswith(b"\xff\x4f") and b"\xff\x90" not in enc.body[:2]
    assert len(enc.packet_starts) == enc.stream.n_packets(enc.width, enc.height)
    assert enc.packet_starts[0] == 0 and np.all(np.diff(enc.packet_starts) > 0)
    full = codec.decode_packets(enc.params, enc.width, enc.height, codec.split_packets(enc.body, enc.packet_starts))
    assert full.shape == (96, 128)
    assert codec.psnr(full, enc.image) > 35


@pytest.mark.parametrize("kw", [
    {"irreversible": False}, {"progression": "RLCP"}, {"resolutions": 3}, {"grey": False},
])
def test_configurations_decode(kw: dict, img: np.ndarray) -> None:
    colour = np.stack([img, img // 2 + 40, 255 - img], axis=2).astype(np.uint8)
    cp = CodingParams(layer_bytes=(100, 400, 1600), **kw)
    e = codec.encode_image(colour, cp)
    assert e.grey == kw.get("grey", True)
    out = codec.decode_packets(e.params, e.width, e.height, codec.split_packets(e.body, e.packet_starts))
    ref = e.image
    assert out.shape == ref.shape
    assert codec.psnr(out, ref) > 25
    assert 1000 < len(e.body) <= 1700


def test_prefix_quality_increases(enc: codec.Encoded) -> None:
    q = []
    for k in range(1, enc.stream.layers + 1):
        n = enc.layer_end(k)
        pk = codec.split_packets(enc.body, enc.packet_starts, n)
        q.append(codec.psnr(codec.decode_packets(enc.params, enc.width, enc.height, pk), enc.image))
    assert all(b >= a - 0.05 for a, b in itertools.pairwise(q)), q
    assert q[-1] - q[0] > 8


def test_packet_aware_repair_beats_prefix(enc: codec.Encoded) -> None:
    packets = codec.split_packets(enc.body, enc.packet_starts)
    # lose the largest packet of the second layer
    per_layer = enc.stream.resolutions
    second = list(range(per_layer, 2 * per_layer))
    victim = max(second, key=lambda i: len(packets[i] or b""))
    holed = list(packets)
    holed[victim] = None
    repaired = codec.decode_packets(enc.params, enc.width, enc.height, holed)
    prefix = codec.decode_packets(enc.params, enc.width, enc.height, packets[:victim])
    assert codec.psnr(repaired, enc.image) > codec.psnr(prefix, enc.image) + 1.0
    _cs, used = codec.assemble(enc.params, enc.width, enc.height, holed)
    # later packets of the lost packet's resolution were dropped, the rest kept
    same_res = [i for i in range(victim, len(packets)) if enc.stream.resolutions and
                codec.packet_order(enc.stream)[i, 1] == codec.packet_order(enc.stream)[victim, 1]]
    assert used == len(packets) - len(same_res)


def test_bad_input_is_rejected(img: np.ndarray) -> None:
    with pytest.raises(ConfigError):
        codec.encode_image(np.zeros((4, 4), np.uint8))
    with pytest.raises(ConfigError):
        codec.encode_image(np.zeros((20, 20, 2), np.uint8), CodingParams(grey=False))
    with pytest.raises(ConfigError):
        CodingParams(layer_bytes=(100, 50))
    with pytest.raises(ConfigError):
        CodingParams(progression="XYZ")
    s = ImagerySender(SMALL)
    s.ingest(img, 1.0)
    with pytest.raises(ConfigError):
        s.ingest(np.full((40, 40), np.nan), 2.0)
    with pytest.raises(ConfigError):
        s.ingest(ImageInput(img, x=1e6), 2.0)
    assert list(s.images) == [0]


def test_max_size_reduces(img: np.ndarray) -> None:
    e = codec.encode_image(img, CodingParams(max_size=64, layer_bytes=(100, 300)))
    assert (e.width, e.height) == (64, 48)


# ------------------------------------------------------------------------------ transfer


def _pair(**cfg: object) -> tuple[ImagerySender, ImageryReceiver]:
    m = ImageryModality()
    return m.sender({**SMALL, **cfg}), m.receiver({})


@pytest.mark.parametrize("offset", [0, 4095, 4096, 2**20 - 1])
def test_fragment_size_is_the_encoded_size(offset: int) -> None:
    """The sender's size arithmetic agrees with the codec. Without marks: the type id and a
    4-byte header below 4 KiB (5 bytes beyond), then the data."""
    head = 4 if offset < 4096 else 5
    for n_marks, n_data in [(0, 0), (0, 1), (0, 200), (1, 1), (2, 60), (31, 100)]:
        frag = ImageFragment(3, offset, 9 if n_marks else None, tuple(range(n_marks)), bytes(n_data))
        assert wire.encoded_size(frag) == fragment_size(n_marks, n_data, offset)
        assert wire.decode(wire.encode(frag)) == frag
        if not n_marks:
            assert fragment_size(0, n_data, offset) == 1 + head + n_data
    # two marks: 32 or 40 bits of header, 15 bits (count, first packet), 2 x 8 bits
    assert fragment_size(2, 60, offset) == 1 + (8 if offset < 4096 else 9) + 60


@pytest.mark.parametrize("mtu", [32, 33, 47, 64, 100, 256, 600])
def test_fragments_fit_any_mtu(mtu: int, img: np.ndarray) -> None:
    s, r = _pair(default_goal="full")
    s.ingest(img, 0.0)
    t = Transfer(s, r, mtu=mtu)  # wire.pack raises if a frame exceeds the MTU
    t.run(lambda: not s.order(), 5000)
    frags = [e.message for e in t.events if isinstance(e.message, ImageFragment)]
    assert frags and all(wire.encoded_size(f) <= mtu - 3 for f in frags)
    rx = r.images[0]
    assert rx.have.all() and bytes(rx.buf) == s.images[0].enc.body
    assert rx.image is not None and codec.psnr(rx.image, s.images[0].enc.image) > 35
    # no byte was sent twice on a lossless link
    assert sum(len(f.data) for f in frags) == len(s.images[0].enc.body)


def test_announce_then_default_set_point_in_capture_order() -> None:
    s, r = _pair(default_goal="layer:3")
    for i, t in enumerate([30.0, 10.0, 20.0]):
        s.ingest(ImageInput(seafloor(48, 64, seed=i), time=t, x=float(i), y=None), 40.0)
    out = s.fill(200, 41.0)
    anns = [m for m in out if isinstance(m, ImageAnnounce)]
    assert [a.stamp for a in anns] == [10, 20]  # max_announces=2, oldest first
    frags = [m for m in out if isinstance(m, ImageFragment)]
    assert frags and frags[0].image_id == 1 and {f.image_id for f in frags} <= {1, 2}  # oldest first
    t = Transfer(s, r, mtu=64, now=41.0)
    t.run(lambda: not s.order(), 2000)
    order = [1]
    for e in t.events:
        if isinstance(e.message, ImageFragment) and e.message.image_id not in order:
            order.append(e.message.image_id)
    assert order == [1, 2, 0]
    for image_id, tx in s.images.items():
        assert r.images[image_id].contiguous() >= tx.goal > 0
        assert r.images[image_id].contiguous() < tx.total  # then moved on
        assert r.images[image_id].ann.x == float(image_id)


def test_goals_are_served_first_and_acknowledged() -> None:
    s, r = _pair(default_goal="layer:2")
    for i in range(3):
        s.ingest(seafloor(48, 64, seed=i), 10.0 * i)
    t = Transfer(s, r, mtu=128, now=30.0)
    t.run(lambda: all(i in r.images for i in range(3)), 100)
    goal = r.request_goal(2, "full", now=t.now)
    assert isinstance(goal, ImageGoal) and r.pending_requests() == [goal]
    seen: list[int] = []

    def done() -> bool:
        seen.extend(e.message.image_id for e in t.events[-4:] if isinstance(e.message, ImageFragment))
        return bool(r.images[2].have.all())

    t.run(done, 500)
    assert r.pending_requests() == []  # CommandAck received
    acks = [e.message for e in t.events if isinstance(e.message, CommandAck)]
    assert acks and acks[0].status == AckStatus.ACCEPTED
    assert r.images[2].image is not None
    first_after = [e.message.image_id for e in t.events if isinstance(e.message, ImageFragment)
                   and e.now > t.events[next(i for i, e2 in enumerate(t.events) if e2.message == goal)].now]
    assert first_after[0] == 2


def test_goal_kinds_and_rejections(img: np.ndarray) -> None:
    s, _ = _pair()
    s.ingest(img, 0.0)
    tx = s.images[0]
    s.handle(ImageGoal(1, 0, GoalKind.FRACTION, 50), 1.0)
    assert tx.goal >= tx.total // 2 and tx.goal in set(tx.enc.packet_starts.tolist()) | {tx.total}
    s.handle(ImageGoal(2, 0, GoalKind.LAYER, 3), 1.0)
    assert tx.goal == tx.enc.layer_end(3)
    s.handle(ImageGoal(3, 0, GoalKind.SKIP, 0), 1.0)
    assert tx.goal == 0 and not tx.needs()
    for bad in (ImageGoal(4, 0, GoalKind.FRACTION, 0), ImageGoal(4, 0, GoalKind.LAYER, 99),
                ImageGoal(4, 9, GoalKind.FULL, 0), ImageAck(0, tx.total + 1, ()),
                ImageAck(0, 0, (ByteRange(5, 4),))):
        with pytest.raises(RequestRejected):
            s.handle(bad, 1.0)
    assert tx.goal == 0


def test_image_by_time(img: np.ndarray) -> None:
    s, _ = _pair(default_goal="layer:1", request_goal="layer:5")
    for t in (100.0, 200.0, 300.0):
        s.ingest(ImageInput(seafloor(48, 64, seed=int(t)), time=t), 300.0)
    assert s.find(190, TimeDirection.NEAREST, 400.0).image_id == 1
    assert s.find(200, TimeDirection.BEFORE, 400.0).image_id == 0
    assert s.find(200, TimeDirection.AFTER, 400.0).image_id == 2
    assert s.find(100, TimeDirection.BEFORE, 400.0) is None
    with pytest.raises(RequestRejected):
        s.handle(ImageByTimeRequest(1, 300, TimeDirection.AFTER), 400.0)
    reply = s.handle(ImageByTimeRequest(2, 201, TimeDirection.BEFORE), 400.0)
    assert reply == [CommandAck(2, AckStatus.ACCEPTED)]
    assert s.order()[0].image_id == 1 and s.images[1].goal == s.images[1].enc.layer_end(5)
    # the receiver side builds the request from an absolute time
    r = ImageryReceiver()
    req = r.request_by_time(2**18 + 201.7, "after", now=0.0)
    assert req.stamp == 201 and req.direction == TimeDirection.AFTER


def test_selective_ack_resends_only_missing(img: np.ndarray) -> None:
    s, _ = _pair(default_goal="full")
    s.ingest(img, 0.0)
    sent: list[ImageFragment] = []
    for k in range(6):
        sent += [m for m in s.fill(120, 1.0 + k) if isinstance(m, ImageFragment)]
    hole = sent[2]
    got_end = sent[-1].offset + len(sent[-1].data)
    s.handle(ImageAck(0, hole.offset, (ByteRange(hole.offset + len(hole.data), got_end),)), 8.0)
    assert s.unacked_fragments() == 1
    out = [m for m in s.fill(120, 8.0 + 12.0) if isinstance(m, ImageFragment)]
    assert out[0].offset == hole.offset and out[0].data == hole.data
    assert all(m.offset >= got_end for m in out[1:])  # then new data, nothing else again


def test_receiver_repairs_a_lost_middle_fragment(enc: codec.Encoded, img: np.ndarray) -> None:
    s, r = _pair(default_goal="full")
    s.ingest(img, 0.0)
    msgs: list = []
    while out := s.fill(60, 0.0):  # same time: nothing is due for resending
        msgs += out
    frags = [m for m in msgs if isinstance(m, ImageFragment)]
    ann = next(m for m in msgs if isinstance(m, ImageAnnounce))
    lost = frags[len(frags) // 3]
    r.receive(ann, 0.0)
    q_before = None
    for f in frags:
        if f is lost:
            continue
        r.receive(f, 0.0)
        if f.offset > lost.offset and q_before is None:
            q_before = r.images[0].used
    rx = r.images[0]
    assert not rx.have.all()
    assert rx.used > q_before  # packets after the gap are used
    prefix = codec.decode_packets(enc.params, enc.width, enc.height,
                                  codec.split_packets(s.images[0].enc.body, s.images[0].enc.packet_starts, lost.offset))
    assert codec.psnr(rx.image, s.images[0].enc.image) > codec.psnr(prefix, s.images[0].enc.image) + 0.5
    ack = next(m for m in r.poll(1.0) if isinstance(m, ImageAck))
    assert ack.contiguous == lost.offset and ack.ranges[0].start == lost.offset + len(lost.data)
    r.receive(lost, 2.0)
    assert rx.have.all() and bytes(rx.buf) == s.images[0].enc.body


def test_receiver_tolerates_early_and_bad_fragments(img: np.ndarray) -> None:
    s, r = _pair(default_goal="full")
    s.ingest(img, 0.0)
    msgs = s.fill(250, 1.0) + s.fill(250, 2.0)
    ann = next(m for m in msgs if isinstance(m, ImageAnnounce))
    frags = [m for m in msgs if isinstance(m, ImageFragment)]
    for f in frags:
        assert r.receive(f, 3.0) == []  # before the announcement: kept, not lost
    assert r.poll(3.0) == []  # no ack before the announcement
    products = r.receive(ann, 3.0)
    assert products and products[-1].version >= 1 and r.images[0].contiguous() == sum(len(f.data) for f in frags)
    bad = ImageFragment(0, 0, 0, (5, 3), b"x" * 10)  # marks not increasing
    outside = ImageFragment(0, r.images[0].ann.total_bytes - 2, 0, (), b"abcd")
    wrong = ImageFragment(0, frags[0].offset, 0, (0, 1), frags[0].data)  # contradicts known starts
    for m in (bad, outside, wrong):
        assert r.receive(m, 4.0) == []
    assert r.rejected_fragments == 3
    assert bytes(r.images[0].buf[: len(frags[0].data)]) == frags[0].data


def test_memory_bounds_keep_requested_images() -> None:
    s, _ = _pair(max_images=3)
    for i in range(3):
        s.ingest(ImageInput(seafloor(48, 64, seed=i), time=float(i)), 10.0)
    s.handle(ImageGoal(1, 0, GoalKind.FULL, 0), 10.0)
    s.images[1].acked[:] = True  # image 1 is done
    s.ingest(ImageInput(seafloor(48, 64, seed=9), time=5.0), 10.0)
    assert sorted(s.images) == [0, 2, 3] and s.evicted == 1
    s.ingest(ImageInput(seafloor(48, 64, seed=8), time=6.0), 10.0)
    assert 0 in s.images and len(s.images) == 3  # the requested image stays
    r = ImageryReceiver({"max_images": 2})
    for i in range(3):
        r.receive(ImageAnnounce(i, i, None, None, 64, 48, True, 100, s.images[0].enc.params), 1.0)
    assert sorted(r.images) == [1, 2]


def test_progress_reports(img: np.ndarray) -> None:
    s, r = _pair(default_goal="full", progress_interval=30.0)
    s.ingest(img, 0.0)
    s.ingest(seafloor(48, 64, seed=1), 0.0)
    assert not any(isinstance(m, TransferProgress) for m in s.fill(250, 1.0))
    out = s.fill(250, 40.0)
    prog = [m for m in out if isinstance(m, TransferProgress)]
    assert len(prog) == 1
    p = prog[0]
    assert p.pending == 2 and p.current == 0 and p.next_images == (1,) and p.unacked_fragments >= 1
    products = r.receive(p, 40.0)
    assert products[0].kind == "image-progress" and products[0].meta["next_images"] == [1]
    s.handle(ImageGoal(1, 1, GoalKind.LAYER, 1), 41.0)
    prog2 = [m for m in s.fill(250, 42.0) if isinstance(m, TransferProgress)]
    assert prog2 and prog2[0].current == 1  # a goal change is reported at once


def test_writer_outputs_tiff_and_png_after_each_useful_fragment(tmp_path: Path, img: np.ndarray) -> None:
    import tifffile
    from PIL import Image

    m = ImageryModality()
    s = m.sender({**SMALL, "default_goal": "layer:4"})
    r = m.receiver({"out_dir": str(tmp_path)})
    s.ingest(img, 0.0)
    t = Transfer(s, r, mtu=48)
    t.run(lambda: not s.order(), 500)
    writer = r.listeners[0]
    assert writer.written == r.images[0].version >= 3
    tif = tifffile.imread(tmp_path / "image_0000.tiff")
    png = np.asarray(Image.open(tmp_path / "image_0000.png"))
    assert np.array_equal(tif, r.images[0].image) and np.array_equal(png, tif)


def test_receiver_survives_arbitrary_valid_messages() -> None:
    """Any message that decodes is taken without an exception, and real data still lands."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    e = codec.encode_image(seafloor(48, 64, seed=2), CodingParams(layer_bytes=(50, 200, 600)))
    ann = ImageAnnounce(3, 10, None, None, e.width, e.height, True, len(e.body), e.params)
    frag = st.builds(
        ImageFragment, st.integers(0, 5), st.integers(0, 2000), st.integers(0, 1023),
        st.lists(st.integers(0, 255), max_size=8).map(lambda v: tuple(sorted(v))),
        st.binary(max_size=100),
    )
    bad_ann = st.builds(ImageAnnounce, st.integers(4, 9), st.integers(0, 100), st.none(), st.none(),
                        st.integers(1, 300), st.integers(1, 300), st.booleans(), st.integers(0, 5000),
                        st.integers(0, 2**15 - 1))

    @settings(max_examples=60, deadline=None)
    @given(st.lists(st.one_of(frag, bad_ann), max_size=12))
    def run(noise: list) -> None:
        r = ImageryReceiver()
        r.receive(ann, 11.0)
        for m in noise:
            r.receive(m, 11.0)
        r.poll(12.0)
        r.products()
        good = ImageFragment(3, 0, 0, (0,), e.body[: min(100, len(e.body))])
        r.receive(good, 12.0)
        assert r.images[3].have[: len(good.data)].all() or r.rejected_fragments > 0

    run()


def test_receiver_forgets_images_of_the_previous_id_cycle(img: np.ndarray) -> None:
    e = codec.encode_image(img, CodingParams(layer_bytes=(100, 300)))
    r = ImageryReceiver()
    for i in (5, 6, 700):
        r.receive(ImageAnnounce(i, i, None, None, e.width, e.height, True, len(e.body), e.params), 1.0)
    assert sorted(r.images) == [5, 6, 700]
    # id 1020 is announced: 5 and 6 are 9 and 10 ids ahead, so they belong to the previous cycle
    r.receive(ImageAnnounce(1020, 9, None, None, e.width, e.height, True, len(e.body), e.params), 2.0)
    assert sorted(r.images) == [700, 1020]
    # a re-announced old image (an earlier capture time) never removes newer ones
    r.receive(ImageAnnounce(690, 3, None, None, e.width, e.height, True, len(e.body), e.params), 3.0)
    assert sorted(r.images) == [690, 700, 1020]


def test_codec_threads_change_no_byte(img: np.ndarray) -> None:
    """OpenJPEG's threads (issue 55: a lone demo codes on every core, a sweep's dive on one)
    give the same codestream and the same decoded pixels as coding in the caller's thread."""
    import glymur

    before = glymur.get_option("lib.num_threads")
    cp = CodingParams(layer_psnr=(25.0, 30.0))
    try:
        out = []
        for n in (0, 2):
            codec.set_threads(n)
            codec._TARGETS.clear()
            e = codec.encode_image(img, cp)
            out.append((e.body, codec.decode_packets(e.params, e.width, e.height,
                                                     codec.split_packets(e.body, e.packet_starts)).tobytes()))
        assert out[0] == out[1]
        with pytest.raises(ConfigError):
            codec.set_threads(-1)
    finally:
        glymur.set_option("lib.num_threads", before)

"""Image regions at the imagery level: an ImageRegionRequest brings a rectangle to a goal, over a
simulated link, with the packets of the precincts that cover it or with a crop (the rectangle
coded on its own as the difference to what topside shows of it), whichever the vehicle measures
cheaper."""

from __future__ import annotations

import numpy as np
import pytest

from coex_core.errors import ConfigError, RequestRejected
from coex_core.messages import (
    AckStatus,
    CommandAck,
    ImageAnnounce,
    ImageCrop,
    ImageFragment,
    ImageRegionRequest,
    ImageShortFragment,
    Message,
    RegionGoal,
)
from coex_plugins.imagery import ImageInput, ImageryModality, ImagerySender, codec
from coex_plugins.imagery._regions import decoded
from coex_plugins.imagery.sender import BRIDGE_BYTES, _bridge, packet_layers
from coex_plugins.imagery.sim import Transfer, region_transfer
from coex_plugins.imagery.synth import seafloor

BOX = (0, 0, 320, 240)  # the top-left quarter of a 640 x 480 frame


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    return seafloor(480, 640, seed=11)


def _announced(img: np.ndarray, **cfg: object) -> tuple[Transfer, object, object]:
    m = ImageryModality()
    s = m.sender({"default_goal": "none", "progress_interval": 1e9, **cfg})
    r = m.receiver({})
    s.ingest(ImageInput(img, time=0.0), 0.0)
    t = Transfer(s, r, mtu=128)
    t.run(lambda: 0 in r.images and not s.order(), 100)
    return t, s, r


def _inside_psnr(r: object, img: np.ndarray, box: tuple[int, int, int, int]) -> float:
    x0, y0, x1, y1 = box
    shown = r.image(0)  # type: ignore[attr-defined]
    return 0.0 if shown is None else codec.psnr(shown[y0:y1, x0:x1], img[y0:y1, x0:x1])


def test_a_quality_region_reaches_its_quality_inside_with_only_its_packets(frame: np.ndarray) -> None:
    t, s, r = _announced(frame, crops="never")
    start = len(t.events)
    req = r.request_region(0, BOX, "quality", 33.0, t.now)  # type: ignore[attr-defined]
    assert isinstance(req, ImageRegionRequest) and req.kind == RegionGoal.QUALITY and req.value == 330
    t.run(lambda: s.images[0].region is not None and not s.order(), 1000)  # type: ignore[attr-defined]
    t.step()
    answers = [e.message for e in t.events[start:] if isinstance(e.message, CommandAck)]
    assert [a.status for a in answers] == [AckStatus.ACCEPTED]
    assert _inside_psnr(r, frame, BOX) >= 33.0
    (reg,) = r.images[0].regions  # type: ignore[attr-defined]
    assert reg["state"] == "accepted" and reg["box"] == BOX
    # every byte sent belongs to a packet inside the region, or to a gap of at most BRIDGE_BYTES
    tx = s.images[0]  # type: ignore[attr-defined]
    enc = tx.enc
    inside = codec.region_packets(enc.stream, enc.width, enc.height, BOX)
    sent = np.zeros(len(enc.body), bool)
    for e in t.events[start:]:
        if isinstance(e.message, ImageFragment | ImageShortFragment) and s.image_of(e.message) == 0:  # type: ignore[attr-defined]
            sent[e.message.offset:e.message.offset + len(e.message.data)] = True
    starts = enc.packet_starts
    ends = np.append(starts[1:], len(enc.body))
    outside = [i for i in range(len(starts)) if sent[starts[i]:ends[i]].any() and not inside[i]]
    assert sum(int(ends[i] - starts[i]) for i in outside) <= BRIDGE_BYTES * max(1, len(outside))
    assert sent.sum() < len(enc.body)  # not the whole image


def test_layer_and_byte_goals(frame: np.ndarray) -> None:
    t, s, r = _announced(frame, crops="never")
    r.request_region(0, (400, 300, 560, 420), "layer", 2, t.now)  # type: ignore[attr-defined]
    t.run(lambda: s.images[0].region is not None and not s.order(), 1000)  # type: ignore[attr-defined]
    t.step()
    product = next(p for p in r.products() if p.meta.get("image_id") == 0)  # type: ignore[attr-defined]
    (reg,) = product.meta["regions"]
    assert reg["state"] == "accepted" and reg["layers_complete"] >= 2
    t2, s2, r2 = _announced(frame, crops="never")
    r2.request_region(0, BOX, "bytes", 300, t2.now)  # type: ignore[attr-defined]
    t2.run(lambda: s2.images[0].region is not None and not s2.order(), 1000)  # type: ignore[attr-defined]
    tx = s2.images[0]  # type: ignore[attr-defined]
    # the budget counts the region's own packets; bridged gaps add at most a few bytes each
    assert 0 < int(tx.region.sum()) <= 300 + 4 * BRIDGE_BYTES


def test_absurd_regions_are_refused_by_both_sides(frame: np.ndarray) -> None:
    t, s, r = _announced(frame)
    with pytest.raises(ConfigError):
        r.request_region(0, (10, 10, 10, 50), "quality", 30, t.now)  # type: ignore[attr-defined]
    with pytest.raises(ConfigError):
        r.request_region(0, (0, 0, 641, 50), "quality", 30, t.now)  # type: ignore[attr-defined]
    with pytest.raises(ConfigError):
        r.request_region(0, BOX, "quality", 70, t.now)  # type: ignore[attr-defined]
    with pytest.raises(ConfigError, match="unknown region goal"):
        r.request_region(0, BOX, "sharpest", 1, t.now)  # type: ignore[attr-defined]
    with pytest.raises(RequestRejected):
        s.handle(ImageRegionRequest(9, 0, 0, 0, 700, 50, RegionGoal.QUALITY, 300), t.now)  # type: ignore[attr-defined]
    _t, s0, r0 = _announced(frame, precincts=0)
    with pytest.raises(ConfigError, match="without precincts"):
        r0.request_region(0, BOX, "quality", 30, 0.0)  # type: ignore[attr-defined]
    with pytest.raises(RequestRejected, match="without precincts"):
        s0.handle(ImageRegionRequest(9, 0, 0, 0, 64, 64, RegionGoal.QUALITY, 300), 0.0)  # type: ignore[attr-defined]


def test_small_gaps_between_region_packets_are_bridged() -> None:
    chosen = np.array([1, 0, 1, 0, 0, 1, 0, 1, 0], bool)
    held = np.array([0, 0, 0, 0, 0, 0, 1, 0, 0], bool)
    sizes = np.array([50, 3, 40, 5, 9, 30, 2, 10, 1], np.int64)
    out = _bridge(chosen, held, sizes)
    # 3 B gap bridged; 5 + 9 B gap too big; the gap with a held packet stays; nothing after the last
    assert out.tolist() == [True, True, True, False, False, True, False, True, False]


def test_coex_image_region_writes_before_after_and_the_bytes(tmp_path: object, frame: np.ndarray) -> None:
    import json
    import subprocess
    import sys
    from pathlib import Path

    from coex_plugins.imagery.output import write_png

    src = Path(str(tmp_path)) / "frame.png"
    write_png(src, frame)
    out = Path(str(tmp_path)) / "o"
    proc = subprocess.run([sys.executable, "-m", "coex_core.cli", "image", "region", str(src), "--box", "0,0,320,240",
                           "--quality", "32", "--mtu", "96", "--out", str(out)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["state"] == "accepted" and summary["box"] == [0, 0, 320, 240]
    assert summary["goal"] == {"kind": "quality", "value": 32.0}
    assert summary["psnr_inside_after"] >= 32.0 > summary["psnr_inside_before"]
    assert summary["region_wire_bytes"] > 0 and summary["base_wire_bytes"] > 0
    assert (out / "before.png").stat().st_size > 0 and (out / "after.png").stat().st_size > 0
    assert summary["crops"] == "auto"
    # --crops never: the vehicle sends the region's packets, no crop
    never = Path(str(tmp_path)) / "never"
    proc = subprocess.run([sys.executable, "-m", "coex_core.cli", "image", "region", str(src), "--box", "0,0,320,240",
                           "--layers", "2", "--mtu", "96", "--crops", "never", "--out", str(never)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((never / "summary.json").read_text())
    assert summary["crops"] == "never" and summary["served"] == "packets" and summary["crop"] is None
    assert summary["goal"] == {"kind": "layer", "value": 2} and not (never / "crop.png").exists()
    bad = subprocess.run([sys.executable, "-m", "coex_core.cli", "image", "region", str(src), "--box", "0,0,700,240",
                          "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "outside" in bad.stderr and "Traceback" not in bad.stderr


# ------------------------------------------------------------------ crops


def _plain(sender: ImagerySender, m: Message) -> Message:
    """A short fragment the sender sent as the ImageFragment it stands for (its image named)."""
    if isinstance(m, ImageShortFragment):
        image_id = sender.image_of(m)
        assert image_id is not None
        return ImageFragment(image_id, m.offset, None, (), m.data)
    return m


def _inside(image: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = box
    return image[y0:y1, x0:x1]


def test_a_crop_brings_the_region_to_its_quality_for_fewer_bytes_than_its_packets(frame: np.ndarray) -> None:
    """From an announced image, the quarter to 33 dB: the vehicle codes it on its own (a crop,
    its own image id, announced with ImageCrop) because that costs fewer wire bytes than the
    precincts' packets, measured with both ways; topside pastes it over the image at its box."""
    packets = region_transfer(frame, BOX, "quality", 33.0, mtu=128, sender_config={"crops": "never"})
    crop = region_transfer(frame, BOX, "quality", 33.0, mtu=128)
    assert packets.region["served"] == "packets" and packets.crop is None
    assert crop.region["served"] == "crop" and crop.crop is not None
    assert crop.region["state"] == "accepted" and crop.region["crop"]["complete"] and crop.region["crop"]["shown"]
    assert crop.region_bytes < packets.region_bytes
    assert codec.psnr(_inside(crop.after, BOX), _inside(frame, BOX)) >= 33.0
    # announced as a crop of image 0 at its box, with an id of its own; its bytes travel as fragments
    sent = [e.message for e in crop.transfer.events if e.direction == "down" and not e.lost]
    (ann,) = {m for m in sent if isinstance(m, ImageCrop)}
    assert (ann.parent, (ann.x0, ann.y0, ann.x1, ann.y1), ann.base) == (0, BOX, 0)
    assert ann.image_id == crop.crop.image_id != 0 and ann.command_id == crop.request.command_id
    frags = [_plain(crop.sender, m) for m in sent if isinstance(m, ImageFragment | ImageShortFragment)]
    assert {f.image_id for f in frags} == {ann.image_id}  # nothing of the parent's body
    # the crop is listed as an image-crop product, the parent shows it; outside the box nothing changed
    (cp,) = [p for p in crop.receiver.products() if p.kind == "image-crop"]
    assert cp.meta["parent"] == 0 and cp.meta["box"] == list(BOX) and cp.meta["shown"]
    assert np.array_equal(_inside(crop.after, BOX), cp.data)
    outside = np.ones(frame.shape, bool)
    outside[0:240, 0:320] = False
    assert np.all(crop.after[outside] == 128)


def test_a_crop_resumes_from_what_topside_holds() -> None:
    """With the image at its default goal (layer 2), the crop may code the difference to the
    image decoded from the packets topside acknowledged (``base``): what topside shows inside
    the box is then that decode plus the crop's, and reaches the goal. The vehicle measures this
    and the region coded from nothing, and sends the smaller."""
    frame = seafloor(480, 640, seed=3)  # a frame whose quarter is cheaper resumed
    run = region_transfer(frame, BOX, "quality", 35.0, mtu=128, base="layer:2")
    fresh = region_transfer(frame, BOX, "quality", 35.0, mtu=128, base="none")
    assert run.crop is not None and fresh.crop is not None and fresh.crop.crop.base == 0
    tx = run.sender.images[0]
    base = run.crop.crop.base
    # the base is every packet of the first two layers: what topside acknowledged
    assert base == len(codec.split_packets(tx.enc.body, tx.enc.packet_starts, tx.enc.layer_end(2))) > 0
    parent = codec.decode_packets(tx.enc.params, tx.enc.width, tx.enc.height,
                                  codec.split_packets(tx.enc.body, tx.enc.packet_starts)[:base])
    residual = run.receiver.images[run.crop.image_id].image
    assert np.array_equal(_inside(run.after, BOX), codec.add_residual(_inside(parent, BOX), residual))
    assert codec.psnr(_inside(run.after, BOX), _inside(frame, BOX)) >= 35.0
    assert codec.psnr(_inside(run.before, BOX), _inside(frame, BOX)) < 35.0
    # what topside already held is not paid for again
    assert len(run.crop.enc.body) < len(fresh.crop.enc.body)
    # the image outside the box is the image as topside held it
    outside = np.ones(frame.shape, bool)
    outside[0:240, 0:320] = False
    assert np.array_equal(run.after[outside], run.before[outside])


@pytest.mark.parametrize("seed", [1, 2])
def test_a_crop_arrives_through_loss(frame: np.ndarray, seed: int) -> None:
    """40 % of the frames lost both ways: the crop's announcement, fragments and acks are an
    image's, so lost fragments are sent again until topside holds the whole crop."""
    run = region_transfer(frame, BOX, "quality", 35.0, mtu=96, base="layer:1", loss=0.4, seed=seed)
    assert run.crop is not None and run.region["served"] == "crop"
    lost = [e for e in run.transfer.events if e.lost and isinstance(e.message, ImageFragment | ImageShortFragment)
            and run.sender.image_of(e.message) == run.crop.image_id]
    assert lost, "no crop fragment was lost: the test proves nothing"
    assert run.region["crop"]["complete"] and run.region["crop"]["shown"]
    assert run.sender.images[run.crop.image_id].acked.all()
    assert codec.psnr(_inside(run.after, BOX), _inside(frame, BOX)) >= 35.0


def test_the_parent_is_shown_again_once_it_is_better_than_the_crop(frame: np.ndarray) -> None:
    """A crop covers the parent's layers it is as good as; when the parent later holds more
    layers inside the box (the whole image sent), topside shows the parent there: the better."""
    run = region_transfer(frame, BOX, "quality", 33.0, mtu=128, base="layer:1")
    assert run.crop is not None
    cover = run.crop.crop.cover
    tx = run.sender.images[0]
    assert cover < tx.enc.stream.layers
    layer = packet_layers(tx.enc)
    # the crop is at least as good as the parent at `cover` layers inside the box, not at one more
    at = [codec.psnr(_inside(decoded(tx, layer < k), BOX), _inside(frame, BOX))
          for k in (cover, cover + 1)]
    assert at[0] <= run.crop.crop.psnr < at[1]
    run.receiver.request_goal(0, "full", now=run.transfer.now)
    run.transfer.run(lambda: bool(run.receiver.images[0].have.all()), 2000)
    shown = run.receiver.image(0)
    assert np.array_equal(shown, run.receiver.images[0].image)  # the parent's own decode
    product = next(p for p in run.receiver.products() if p.kind == "image" and p.meta["image_id"] == 0)
    (reg,) = product.meta["regions"]
    assert reg["served"] == "crop" and not reg["crop"]["shown"] and reg["layers_complete"] == tx.enc.stream.layers


def test_a_crop_still_arriving_is_not_shown_over_a_parent_as_good_as_the_whole_crop(frame: np.ndarray) -> None:
    """``cover`` is what the *whole* crop is as good as. While the crop arrives it is shown over a
    parent holding fewer layers inside the box (it sharpens there as it comes), but not over one
    that already holds ``cover`` layers there: that would show less than topside holds (the demo's
    region went back from 33 to 26 dB when the parent's next layer came before the last of the
    crop). Once the crop is complete it is shown again."""
    run = region_transfer(frame, BOX, "quality", 33.0, mtu=128, base="layer:1")
    assert run.crop is not None
    c, tx = run.crop, run.sender.images[0]
    cover, body = c.crop.cover, c.enc.body
    assert 2 <= cover < tx.enc.stream.layers and c.crop.base > 0
    sent = [e.message for e in run.transfer.events if e.direction == "down" and not e.lost]
    ann = next(m for m in sent if isinstance(m, ImageAnnounce) and m.image_id == 0)
    crop_ann = next(m for m in sent if isinstance(m, ImageCrop))
    r = ImageryModality().receiver({})

    def parent_to(layers: int) -> None:
        have = int(np.count_nonzero(r.images[0].have))
        r.receive(ImageFragment(0, have, None, (), tx.enc.body[have:tx.enc.layer_end(layers)]), 1.0)

    def crop_at() -> tuple[bool, np.ndarray]:
        (cp,) = [p for p in r.products() if p.kind == "image-crop"]
        return bool(cp.meta["shown"]), _inside(r.image(0), BOX)

    r.receive(ann, 0.0)
    parent_to(cover - 1)
    r.receive(crop_ann, 1.0)
    half = len(body) // 2
    r.receive(ImageFragment(c.image_id, 0, None, (), body[:half]), 2.0)
    assert not r.images[c.image_id].have.all()
    shown, inside = crop_at()
    assert shown and not np.array_equal(inside, _inside(r.images[0].image, BOX))  # the crop, in part
    parent_to(cover)  # the parent's next layer comes before the rest of the crop
    shown, inside = crop_at()
    assert not shown and np.array_equal(inside, _inside(r.images[0].image, BOX))  # the parent there
    r.receive(ImageFragment(c.image_id, half, None, (), body[half:]), 3.0)
    shown, inside = crop_at()
    parent = codec.psnr(_inside(r.images[0].image, BOX), _inside(frame, BOX))
    assert shown and codec.psnr(inside, _inside(frame, BOX)) >= max(33.0, parent)


def test_layer_and_byte_goals_with_crops(frame: np.ndarray) -> None:
    """A layer goal is the quality the image has inside the box at that many layers: a crop
    reaching it counts as those layers complete. A byte budget is spent the way that brings
    more quality inside the box."""
    run = region_transfer(frame, BOX, "layer", 3, mtu=128, sender_config={"crops": "always"})
    assert run.crop is not None and run.region["layers_complete"] >= 3
    tx = run.sender.images[0]
    want = codec.psnr(_inside(decoded(tx, packet_layers(tx.enc) < 3), BOX), _inside(frame, BOX))
    assert codec.psnr(_inside(run.after, BOX), _inside(frame, BOX)) >= want
    budget = region_transfer(frame, BOX, "bytes", 400, mtu=128)
    packets = region_transfer(frame, BOX, "bytes", 400, mtu=128, sender_config={"crops": "never"})
    q = [codec.psnr(_inside(r.after, BOX), _inside(frame, BOX)) for r in (budget, packets)]
    assert q[0] >= q[1]
    if budget.crop is not None:
        assert len(budget.crop.enc.body) <= 400


def test_crops_never_and_always(frame: np.ndarray) -> None:
    never = region_transfer(frame, (320, 240, 640, 480), "quality", 30.0, mtu=128, sender_config={"crops": "never"})
    always = region_transfer(frame, (320, 240, 640, 480), "quality", 30.0, mtu=128, sender_config={"crops": "always"})
    assert never.crop is None and never.region["served"] == "packets"
    assert always.crop is not None and always.region["served"] == "crop"
    with pytest.raises(ConfigError, match=r"crops: one of .auto., .never., .always., got .sometimes."):
        ImageryModality().sender({"crops": "sometimes"})


def test_a_region_of_a_crop_is_refused_by_both_sides(frame: np.ndarray) -> None:
    run = region_transfer(frame, BOX, "quality", 33.0, mtu=128)
    assert run.crop is not None
    cid = run.crop.image_id
    with pytest.raises(ConfigError, match="is a crop of image 0"):
        run.receiver.request_region(cid, (0, 0, 32, 32), "quality", 30, run.transfer.now)
    with pytest.raises(RequestRejected, match="is a crop of image 0"):
        run.sender.handle(ImageRegionRequest(200, cid, 0, 0, 32, 32, RegionGoal.QUALITY, 300), run.transfer.now)
    # a crop is never the image found by time
    assert run.sender.find(0, 0, run.transfer.now).image_id == 0


def test_a_crop_announced_before_its_fragments_or_after_them(frame: np.ndarray) -> None:
    """Fragments of a crop whose announcement is late wait, then count; the crop of an image id
    that is then reused by a new image is forgotten with it."""
    run = region_transfer(frame, BOX, "quality", 33.0, mtu=128)
    assert run.crop is not None
    sent = [_plain(run.sender, e.message) for e in run.transfer.events if e.direction == "down"]
    ann = next(m for m in sent if isinstance(m, ImageCrop))
    frags = [m for m in sent if isinstance(m, ImageFragment) and m.image_id == ann.image_id]
    m = ImageryModality()
    r = m.receiver({})
    for msg in [m for m in sent if not isinstance(m, ImageCrop | ImageFragment)]:
        r.receive(msg, run.transfer.now)
    parent = [m for m in sent if isinstance(m, ImageFragment) and m.image_id == 0]
    for f in frags + parent:
        r.receive(f, run.transfer.now)
    assert r.image(0) is None or not np.array_equal(r.image(0), run.after)
    r.receive(ann, run.transfer.now)
    assert np.array_equal(r.image(0), run.after)
    # image 0's id reused by a newer image: its crop goes with it
    from coex_core.messages import ImageAnnounce
    from coex_core.timefmt import to_stamp

    old = r.images[0].ann
    r.receive(ImageAnnounce(0, to_stamp(run.transfer.now + 100), None, None, 64, 48, True, 10, old.params),
              run.transfer.now + 100)
    assert ann.image_id not in r.images


def test_crops_survive_a_restart_of_both_sides(frame: np.ndarray) -> None:
    """A vehicle and a topside saved with a crop (as a node store saves them) and restored: the
    crop is still the vehicle's answer to its request, and topside shows the same picture."""
    from coex_core.state import dumps, loads

    run = region_transfer(frame, BOX, "quality", 33.0, mtu=128)
    assert run.crop is not None
    sender, receiver = loads(dumps(run.sender)), loads(dumps(run.receiver))
    assert sender.images[run.crop.image_id].crop == run.crop.crop
    assert np.array_equal(receiver.image(0), run.after)
    assert np.array_equal(receiver.image(run.crop.image_id), run.receiver.image(run.crop.image_id))
    (reg,) = next(p for p in receiver.products() if p.kind == "image").meta["regions"]
    assert reg["served"] == "crop" and reg["crop"]["shown"]


def test_a_colour_image_is_cropped_in_colour() -> None:
    img = seafloor(240, 320, seed=2, colour=True)
    run = region_transfer(img, (0, 0, 160, 120), "quality", 33.0, mtu=128, base="layer:1",
                          sender_config={"grey": False, "crops": "always"})
    assert run.crop is not None and run.crop.enc.stream.colour and not run.crop.enc.grey
    enc = run.sender.images[0].enc
    assert run.after.shape == (240, 320, 3) and run.region["crop"]["shown"]
    assert codec.psnr(run.after[:120, :160], enc.image[:120, :160]) >= 33.0

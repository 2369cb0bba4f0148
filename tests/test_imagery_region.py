"""Image regions at the imagery level: an ImageRegionRequest brings a rectangle to a goal with the
packets of the precincts that cover it, over a simulated link."""

from __future__ import annotations

import numpy as np
import pytest

from coex_core.errors import ConfigError, RequestRejected
from coex_core.messages import AckStatus, CommandAck, ImageFragment, ImageRegionRequest, RegionGoal
from coex_plugins.imagery import ImageInput, ImageryModality, codec
from coex_plugins.imagery.sender import BRIDGE_BYTES, _bridge
from coex_plugins.imagery.sim import Transfer
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
    t, s, r = _announced(frame)
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
        if isinstance(e.message, ImageFragment):
            sent[e.message.offset:e.message.offset + len(e.message.data)] = True
    starts = enc.packet_starts
    ends = np.append(starts[1:], len(enc.body))
    outside = [i for i in range(len(starts)) if sent[starts[i]:ends[i]].any() and not inside[i]]
    assert sum(int(ends[i] - starts[i]) for i in outside) <= BRIDGE_BYTES * max(1, len(outside))
    assert sent.sum() < len(enc.body)  # not the whole image


def test_layer_and_byte_goals(frame: np.ndarray) -> None:
    t, s, r = _announced(frame)
    r.request_region(0, (400, 300, 560, 420), "layer", 2, t.now)  # type: ignore[attr-defined]
    t.run(lambda: s.images[0].region is not None and not s.order(), 1000)  # type: ignore[attr-defined]
    t.step()
    product = next(p for p in r.products() if p.meta.get("image_id") == 0)  # type: ignore[attr-defined]
    (reg,) = product.meta["regions"]
    assert reg["state"] == "accepted" and reg["layers_complete"] >= 2
    t2, s2, r2 = _announced(frame)
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
    bad = subprocess.run([sys.executable, "-m", "coex_core.cli", "image", "region", str(src), "--box", "0,0,700,240",
                          "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "outside" in bad.stderr and "Traceback" not in bad.stderr

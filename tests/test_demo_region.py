"""End to end: a region request in the demo's camera pass.

The scripted operator's eye is made more doubtful than the default (every man-made measure within
its margin of a threshold) so that the first look at the confirming image finds the target "too
unclear to tell": the operator then asks for the region of the frame around it (its own finding,
not the whole image). The request crosses the simulated acoustic link signed,
the vehicle answers with a crop (the region coded on its own as the difference to what topside
holds, measured cheaper than the JPEG 2000 packets of the precincts covering the region), and
the received image sharpens there: topside pastes the crop over it. Judged against the truth:
the vehicle's original frame (what the camera rendered from the simulated seafloor) and the
dive's targets; the report shows the region and its bytes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from coex_apps.demo import DemoConfig
from coex_apps.demo.eye import Eye, EyeParams
from coex_apps.demo.operator import CONFIRM_LAYERS, MORE_LAYERS
from coex_apps.demo.run import DiveRun
from coex_plugins.imagery import codec
from coex_plugins.imagery.sender import BRIDGE_BYTES, packet_layers

from ._dives import codestreams_shared, small

# a whole demo dive with a region request
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def dive(tmp_path_factory: pytest.TempPathFactory) -> tuple[DiveRun, Any]:
    out = tmp_path_factory.mktemp("demo_region")
    # perfect navigation: this test's subject is the region path. With issue 56's default drift
    # seed 1's region reached 26.7 dB inside its box where the whole frame at its goal gives 33.0
    # (after the merge of main into h50; not explained yet: docs/demo.md). The small site
    # (tests/_dives.py): the region path, not the default site, is the subject; its frames up
    # to the first doubt are those of the small site's shared dive (the same seed), coded once
    run = DiveRun(DemoConfig(out=Path(out), seed=1, progress=False, scenario=small(navigation={"drift": 0.0}),
                             codec_threads=0))
    # an eye that doubts every target at the first look, and decides at the sharper one
    run.operator.eye = Eye(EyeParams(margin=1.0))
    # the received image and the vehicle's bookkeeping when each region first reaches its goal
    # (later, idle link capacity brings the whole frame up too)
    run.region_done = {}  # type: ignore[attr-defined]

    def watch(product: Any) -> None:
        for reg in product.meta.get("regions", ()) if product.kind == "image" else ():
            cid = reg["command_id"]
            if reg["layers_complete"] >= MORE_LAYERS and cid not in run.region_done:  # type: ignore[attr-defined]
                tx = run.senders["imagery"].images.get(product.meta["image_id"])
                run.region_done[cid] = (np.array(product.data, copy=True),  # type: ignore[attr-defined]
                                        None if tx is None else int(np.count_nonzero(tx.acked)))

    run.receivers["imagery"].listeners.append(watch)
    with codestreams_shared(tmp_path_factory):
        result = run.run()
    return run, result


def test_the_operator_asks_for_the_region_of_a_blurry_object_and_the_vehicle_serves_it(
        dive: tuple[DiveRun, Any]) -> None:
    """The doubtful eye makes the operator doubt (it may even fail to confirm a target: the point
    here is the region path); whatever it decides is still checked against the truth."""
    run, result = dive
    regions = run.operator.regions
    assert regions, "no region request in the camera pass"
    log = (Path(result.out) / "decisions.csv").read_text()
    assert "image region" in log and "too unclear to tell" in log
    assert not result.metrics["false_confirmations"], result.metrics["false_confirmations"]
    assert all(r["time"] >= result.metrics["survey_end_s"] for r in regions)  # the camera pass
    # every region asked for was accepted by the vehicle and reached the layers asked for
    rx = run.receivers["imagery"]
    for reg in regions:
        meta = next(p.meta for p in rx.products() if p.kind == "image" and p.meta["image_id"] == reg["image_id"])
        mine = [r for r in meta["regions"] if r["command_id"] == reg["command_id"]]
        assert mine and mine[0]["state"] == "accepted"
        assert mine[0]["layers_complete"] >= MORE_LAYERS


def test_the_region_reaches_its_goal_against_the_original_without_the_whole_frame(
        dive: tuple[DiveRun, Any]) -> None:
    run, _ = dive
    tx_images = run.senders["imagery"].images
    rx = run.receivers["imagery"]
    checked = crops = 0
    for reg in run.operator.regions:
        tx = tx_images.get(reg["image_id"])
        done = run.region_done.get(reg["command_id"])  # type: ignore[attr-defined]
        assert done is not None, f"region {reg} never reached {MORE_LAYERS} layers"
        got, held = done
        if tx is None:
            continue
        original = tx.enc.image  # the frame the vehicle encoded (rendered from the seafloor)
        x0, y0, x1, y1 = reg["box"]
        inside = np.zeros(original.shape, bool)
        inside[y0:y1, x0:x1] = True
        enc = tx.enc
        layer = packet_layers(enc)
        pk = codec.split_packets(enc.body, enc.packet_starts)

        def upto(k: int, enc: Any = enc, layer: Any = layer, pk: Any = pk) -> np.ndarray:
            """The whole frame decoded from its first k layers."""
            return codec.decode_packets(enc.params, enc.width, enc.height,
                                        [p if layer[i] < k else None for i, p in enumerate(pk)])

        def psnr(a: np.ndarray, where: np.ndarray, original: np.ndarray = original) -> float:
            err = (a.astype(float) - original.astype(float))[where] ** 2
            return float(10 * np.log10(255.0**2 / max(err.mean(), 1e-9)))

        base, goal = upto(CONFIRM_LAYERS), upto(MORE_LAYERS)
        # inside: as good as the whole frame at the region's goal, better than before the request
        assert psnr(got, inside) >= psnr(goal, inside) - 0.3, (psnr(got, inside), psnr(goal, inside))
        assert psnr(got, inside) > psnr(base, inside) + 0.5, (psnr(got, inside), psnr(base, inside))
        meta = next(p.meta for p in rx.products() if p.kind == "image" and p.meta["image_id"] == reg["image_id"])
        (row,) = [r for r in meta["regions"] if r["command_id"] == reg["command_id"]]
        crop = next((c for c in tx_images.values() if getattr(c, "crop", None) is not None
                     and c.crop.parent == reg["image_id"] and c.crop.command_id == reg["command_id"]), None)
        if crop is not None:
            # a crop of exactly the region, all of it held topside, shown over the image, for
            # fewer bytes than the rest of the whole frame to the same layers
            assert row["served"] == "crop" and row["crop"]["image_id"] == crop.image_id
            assert crop.crop.box == (x0, y0, x1, y1) and crop.acked.all() and row["crop"]["complete"]
            assert row["layers_complete"] >= MORE_LAYERS and crop.crop.cover >= MORE_LAYERS
            # the whole crop is as good as the frame at the goal inside (whichever came first)
            assert crop.crop.psnr >= psnr(goal, inside) - 0.3, (crop.crop.psnr, psnr(goal, inside))
            assert len(crop.enc.body) < enc.layer_end(MORE_LAYERS) - enc.layer_end(CONFIRM_LAYERS)
            assert tx.region is None  # none of the frame's own packets were asked for it
            crops += 1
        else:
            # what the request asked the vehicle for: only packets of the region's precincts,
            # below the goal layer (packets topside held already were not asked again), and small
            # runs of other packets that bridge a gap between two of them
            assert row["served"] == "packets"
            asked = tx.region
            assert asked is not None
            starts = enc.packet_starts
            ends = np.append(starts[1:], len(enc.body))
            in_region = codec.region_packets(enc.stream, enc.width, enc.height, (x0, y0, x1, y1))
            gap = 0  # bytes of the current run of other packets sent to bridge a small gap
            for i in range(len(starts)):
                if not asked[int(starts[i]):int(ends[i])].any():
                    gap = 0
                elif in_region[i]:
                    assert layer[i] < MORE_LAYERS, (i, layer[i])
                    gap = 0
                else:
                    gap += int(ends[i] - starts[i])
                    assert gap <= BRIDGE_BYTES, (i, gap)
        assert held is not None
        checked += 1
    assert checked
    assert crops, "no region of the camera pass was served as a crop"


def test_the_report_shows_the_region_and_its_bytes(dive: tuple[DiveRun, Any]) -> None:
    run, result = dive
    out = Path(result.out)
    rows = result.metrics["regions"]
    assert {r["command_id"] for r in rows} >= {r["command_id"] for r in run.operator.regions}
    html = (out / "report.html").read_text()
    assert 'id="regions"' in html and "Image regions" in html
    for r in rows:
        if r["by"] != "script":
            continue
        assert r["state"] == "accepted" and r["bytes"] > 0 and (out / r["file"]).exists()
        x0, y0, x1, y1 = r["box"]
        assert f"x {x0}..{x1}, y {y0}..{y1}" in html
        if r["served"] == "crop":
            crop = r["crop"]
            assert r["bytes"] == crop["held_bytes"] == crop["total_bytes"] and (out / r["crop_file"]).exists()
            assert f"crop {crop['width']} x {crop['height']} px" in html
            assert f"{crop['total_bytes']:,} of {crop['total_bytes']:,} B" in html

"""``coex image roundtrip``: outputs and the wire-byte budget rule."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from coex_core import wire
from coex_core.cli import main
from coex_core.jsonfmt import from_json
from coex_plugins.imagery.codec import psnr
from coex_plugins.imagery.synth import seafloor


@pytest.fixture(scope="module")
def image_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("img") / "sea.tiff"
    tifffile.imwrite(p, seafloor(96, 128, seed=4, colour=True))
    return p


@pytest.mark.parametrize(("mtu", "loss"), [(32, 0.0), (100, 0.4)])
def test_roundtrip_writes_messages_and_budgeted_reconstructions(
    tmp_path: Path, image_file: Path, mtu: int, loss: float
) -> None:
    budgets = [0, 60, 150, 400, 1200, 100000]
    rc = main(["image", "roundtrip", str(image_file), "--mtu", str(mtu), "--budgets",
               ",".join(map(str, budgets)), "--out", str(tmp_path), "--loss", str(loss), "--seed", "3"])
    assert rc == 0
    lines = [json.loads(x) for x in (tmp_path / "messages.jsonl").read_text().splitlines()]
    assert lines[0]["type"] in ("ImageAnnounce", "TransferProgress")
    total = 0
    frames: set[int] = set()
    for obj in lines:
        data = bytes.fromhex(obj["hex"])
        msg = wire.decode(data)
        assert type(msg).__name__ == obj["type"] and obj["bytes"] == len(data)
        fields = {k: v for k, v in obj.items()
                  if k not in ("hex", "direction", "frame", "bytes", "lost", "wire_total")}
        assert from_json(fields) == msg
        total += len(data) + (0 if obj["frame"] in frames else wire.header_size())
        frames.add(obj["frame"])
        assert obj["wire_total"] == total
    if loss:
        assert any(o["lost"] for o in lines) and any(o["direction"] == "up" for o in lines)
    grey = np.asarray(Image.open(tmp_path / "image_0000.png"))
    original = seafloor(96, 128, seed=4, colour=True)
    ref = np.rint(original.astype(float) @ [0.299, 0.587, 0.114]).astype(np.uint8)
    assert psnr(grey, ref) > 35
    prev = -1.0
    for b in budgets:
        rec = np.asarray(Image.open(tmp_path / f"recon_{b}.png"))
        assert rec.shape == (96, 128)
        q = psnr(rec, ref)
        assert q >= prev - 0.5  # more bytes, no worse (whole packets only)
        prev = q
    summary = json.loads((tmp_path / "summary.json").read_text())
    for b in budgets:
        assert summary["recon"][str(b)]["wire_bytes"] <= b
    assert np.all(np.asarray(Image.open(tmp_path / "recon_0.png")) == 128)
    assert psnr(np.asarray(Image.open(tmp_path / "recon_100000.png")), ref) > 35
    assert psnr(np.asarray(Image.open(tmp_path / "recon_150.png")), ref) > 20 or mtu == 100


def test_roundtrip_bad_arguments(tmp_path: Path, image_file: Path) -> None:
    assert main(["image", "roundtrip", str(image_file), "--mtu", "20", "--budgets", "10",
                 "--out", str(tmp_path)]) != 0
    assert main(["image", "roundtrip", str(tmp_path / "nope.png"), "--mtu", "64", "--budgets", "10",
                 "--out", str(tmp_path)]) != 0
    assert not (tmp_path / "messages.jsonl").exists()
    with pytest.raises(SystemExit):
        main(["image", "roundtrip", str(image_file), "--mtu", "64", "--budgets", "a,b", "--out", str(tmp_path)])

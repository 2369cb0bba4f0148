"""Imagery benchmark: wire bytes to reach 25 / 30 / 35 dB PSNR, ours against the 2022 configuration.

Reads the grey NUI dive-040 images from ``../shared/data/nui040/`` (or ``$COEX_NUI040``) when
present, else generated seafloor images (``coex_plugins.imagery.synth``). For each image:

* **2022**: grey, 6 resolutions, 10 LRCP layers from 640 to 20,480 B (5/3 wavelet), the raw
  codestream (OpenJPEG's headers and COM included) cut at whole packets, decoded with Psot = 0
  plus EOC. Bytes = codestream prefix length.
* **ours**: the default ``CodingParams`` (no header sent), delivered by the real
  ``ImagerySender`` over frames of ``--mtu`` bytes (default 256). Bytes = every vehicle-to-ship
  wire byte: frame headers, the ``ImageAnnounce`` and each ``ImageFragment`` with its header and
  packet marks. The cost of every packet-aligned prefix is taken from a lossless transfer to
  the full image (the sender cuts its last fragment at the goal); the prefixes at the thresholds
  are then checked end to end: a sender with that byte goal, a receiver, and the receiver's
  decoded image must reach the PSNR with exactly that many wire bytes.

Prints both rate-distortion curves and the ratios; writes ``bench/results/imagery.json``.
Run: ``.venv/bin/python bench/imagery.py [--quick] [--mtu N]``.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from coex_core.messages import ImageFragment
from coex_plugins.imagery import ImageInput, ImageryModality, codec
from coex_plugins.imagery.sender import fragment_size
from coex_plugins.imagery.sim import Transfer
from coex_plugins.imagery.synth import seafloor

THRESHOLDS = (25.0, 30.0, 35.0)
TARGET_RATIO = {25.0: 0.5, 30.0: 0.6, 35.0: 0.75}
REFERENCE_2022_MEAN = {25.0: 303, 30.0: 744, 35.0: 3231}  # 18 images, reference/imagery.md
GRID = (150, 200, 300, 400, 600, 1000, 1500, 2000, 3000, 3600, 5000, 8000, 12000, 20000)
DATA = Path(os.environ.get("COEX_NUI040", Path(__file__).resolve().parents[2] / "shared" / "data" / "nui040"))


def load_images(quick: bool) -> tuple[str, list[tuple[str, np.ndarray]]]:
    files = sorted(glob.glob(str(DATA / "*.tif*")))
    if files:
        import tifffile

        files = files[:4] if quick else files
        return "nui040", [(Path(f).stem, codec.to_grey(tifffile.imread(f))) for f in files]
    n = 3 if quick else 8
    return "synthetic", [(f"synth_{i}", seafloor(480, 640, seed=100 + i)) for i in range(n)]


def _decode_cs(cs: bytes) -> np.ndarray:
    return codec.decode_codestream(cs)


def baseline_curve(img: np.ndarray) -> list[tuple[int, float]]:
    """(codestream bytes, PSNR) at every packet boundary of the 2022 configuration."""
    import glymur

    path = os.path.join(codec._scratch(), "base.j2k")
    cratios = [img.size / t for t in np.geomspace(640, 20480, 10)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        glymur.Jp2k(path, data=img, numres=6, cratios=cratios, prog="LRCP", plt=True)
    cs = open(path, "rb").read()
    os.unlink(path)
    _hdr, sot, start, end, lengths = codec._split(cs)
    segs, _ = codec._markers(cs, sot + 12, 0xFF93)
    plt_bytes = sum(e - p for p, e in segs.get(0xFF58, []))
    head = bytearray(cs[:start])
    head[sot + 6:sot + 10] = b"\0\0\0\0"
    body = cs[start:end]
    ends = np.cumsum(lengths)
    pts = [(len(head) - plt_bytes, 17.0)]
    for n in ends:
        q = codec.psnr(_decode_cs(bytes(head) + body[:int(n)] + b"\xff\xd9"), img)
        pts.append((len(head) - plt_bytes + int(n), q))  # bytes as if written without PLT
    return pts


def our_curve(img: np.ndarray, mtu: int) -> tuple[list[tuple[int, float, int]], Any]:
    """(wire bytes, PSNR, body prefix) at every packet boundary, from a lossless transfer."""
    m = ImageryModality()
    s = m.sender({"default_goal": "full", "progress_interval": 1e9})
    r = m.receiver({})
    s.ingest(ImageInput(img, time=0.0), 0.0)
    tx = s.images[0]
    t = Transfer(s, r, mtu=mtu)
    t.run(lambda: not s.order(), 100000)
    # wire bytes before each fragment's frame, and the fragment's fixed parts
    frags = [(e.message, e.down_total - e.size) for e in t.events
             if e.direction == "down" and isinstance(e.message, ImageFragment)]
    enc = tx.enc
    starts = enc.packet_starts
    ends = np.append(starts[1:], len(enc.body))
    pts = []
    for n in ends:
        n = int(n)
        # the fragment that carries byte n - 1
        k = next(i for i, (f, _) in enumerate(frags) if f.offset < n <= f.offset + len(f.data))
        f, base = frags[k]
        # the sender marks every packet start in [offset, n], the one at n too (it tells the
        # receiver that the packet ending at n is complete), except at the end of the body
        top = n if n < len(enc.body) else n - 1
        marks = int(np.count_nonzero((starts >= f.offset) & (starts <= top)))
        cost = base + fragment_size(marks, n - f.offset)
        pk = codec.split_packets(enc.body, starts, n)
        q = codec.psnr(codec.decode_packets(enc.params, enc.width, enc.height, pk), img)
        pts.append((cost, q, n))
    return pts, tx


def verify(img: np.ndarray, mtu: int, goal_bytes: int) -> tuple[int, float]:
    """End to end: wire bytes and receiver PSNR for a sender whose goal is ``goal_bytes``."""
    m = ImageryModality()
    s = m.sender({"default_goal": f"bytes:{goal_bytes}", "progress_interval": 1e9})
    r = m.receiver({})
    s.ingest(ImageInput(img, time=0.0), 0.0)
    t = Transfer(s, r, mtu=mtu)
    t.run(lambda: not s.order(), 100000)
    down = max((e.down_total for e in t.events if e.direction == "down"), default=0)
    image = r.image(0)
    return down, (17.0 if image is None else codec.psnr(image, img))


def need(curve: list[tuple[int, float]], x: float) -> int | None:
    for b, q in curve:
        if q >= x:
            return int(b)
    return None


def at(curve: list[tuple[int, float]], budget: int, img: np.ndarray) -> float:
    best = codec.psnr(np.full(img.shape, 128, np.uint8), img)
    for b, q in curve:
        if b <= budget:
            best = q  # the latest prefix within the budget (what the receiver shows)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 images (3 generated)")
    ap.add_argument("--mtu", type=int, default=256)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "imagery.json"))
    args = ap.parse_args(argv)
    t0 = time.time()
    source, images = load_images(args.quick)
    per_image = []
    for name, img in images:
        base = baseline_curve(img)
        ours_pts, tx = our_curve(img, args.mtu)
        ours = [(c, q) for c, q, _ in ours_pts]
        rec: dict[str, Any] = {"image": name, "body_bytes": len(tx.enc.body), "params": tx.enc.params,
                               "base": {}, "ours": {}, "verified": {}}
        for x in THRESHOLDS:
            rec["base"][str(x)] = need(base, x)
            c = need(ours, x)
            rec["ours"][str(x)] = c
            if c is not None:
                n = next(nb for cb, q, nb in ours_pts if cb == c and q >= x)
                down, q = verify(img, args.mtu, n)
                rec["verified"][str(x)] = {"wire_bytes": down, "psnr": round(q, 3)}
                direct = next(qq for cb, qq, nb in ours_pts if nb == n)
                if down != c or abs(q - direct) > 1e-6:
                    raise AssertionError(f"{name}: end-to-end check {down} B / {q:.2f} dB != {c} B / {direct:.2f} dB")
        rec["curve_base"] = [round(at(base, g, img), 3) for g in GRID]
        rec["curve_ours"] = [round(at(ours, g, img), 3) for g in GRID]
        per_image.append(rec)
        print(f"{name}: base {[rec['base'][str(x)] for x in THRESHOLDS]}  ours "
              f"{[rec['ours'][str(x)] for x in THRESHOLDS]}", flush=True)
    summary: dict[str, Any] = {"source": source, "images": len(images), "mtu": args.mtu, "thresholds": {}}
    ok_all = True
    for x in THRESHOLDS:
        b = np.array([r["base"][str(x)] for r in per_image], float)
        o = np.array([r["ours"][str(x)] for r in per_image], float)
        per = o / b
        entry = {
            "base_mean": float(b.mean()), "base_worst": float(b.max()),
            "ours_mean": float(o.mean()), "ours_worst": float(o.max()),
            "ratio_mean": float(o.mean() / b.mean()),
            "ratio_worst_image": float(o.max() / b.max()),
            "ratio_per_image_max": float(per.max()),
            "ratio_vs_reference_2022_mean": float(o.mean() / REFERENCE_2022_MEAN[x]),
            "target": TARGET_RATIO[x],
        }
        entry["meets_mean"] = entry["ratio_mean"] <= TARGET_RATIO[x]
        entry["meets_worst_image"] = entry["ratio_worst_image"] <= TARGET_RATIO[x]
        entry["meets_every_image"] = entry["ratio_per_image_max"] <= TARGET_RATIO[x]
        ok_all &= entry["meets_mean"] and entry["meets_worst_image"]
        summary["thresholds"][str(x)] = entry
    curves = {"grid_bytes": list(GRID),
              "base_mean_psnr": [float(np.mean([r["curve_base"][i] for r in per_image])) for i in range(len(GRID))],
              "ours_mean_psnr": [float(np.mean([r["curve_ours"][i] for r in per_image])) for i in range(len(GRID))],
              "base_worst_psnr": [float(np.min([r["curve_base"][i] for r in per_image])) for i in range(len(GRID))],
              "ours_worst_psnr": [float(np.min([r["curve_ours"][i] for r in per_image])) for i in range(len(GRID))]}
    summary["curves"] = curves
    summary["meets_target"] = bool(ok_all)
    summary["seconds"] = round(time.time() - t0, 1)
    print(f"\nsource: {source}, {len(images)} images, MTU {args.mtu} B (ours: all wire bytes incl. frame "
          "headers, announce, fragment headers)")
    print(f"{'bytes':>7} | {'2022 mean':>9} {'ours mean':>9} | {'2022 worst':>10} {'ours worst':>10}   (PSNR dB)")
    for i, g in enumerate(GRID):
        print(f"{g:>7} | {curves['base_mean_psnr'][i]:9.2f} {curves['ours_mean_psnr'][i]:9.2f} | "
              f"{curves['base_worst_psnr'][i]:10.2f} {curves['ours_worst_psnr'][i]:10.2f}")
    print(f"\n{'PSNR':>5} | {'2022 mean/worst':>16} | {'ours mean/worst':>16} | ratio mean  worst  per-image-max | target")
    for x in THRESHOLDS:
        e = summary["thresholds"][str(x)]
        print(f"{x:5.0f} | {e['base_mean']:7.0f} / {e['base_worst']:6.0f} | {e['ours_mean']:7.0f} / "
              f"{e['ours_worst']:6.0f} | {e['ratio_mean']:10.3f} {e['ratio_worst_image']:6.3f} "
              f"{e['ratio_per_image_max']:14.3f} | {e['target']}")
    print(f"meets target (mean and worst image): {summary['meets_target']}   ({summary['seconds']} s)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"summary": summary, "per_image": per_image}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

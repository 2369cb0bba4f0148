"""``coex image``: try the imagery modality on one image.

``coex image roundtrip IMAGE --mtu N --budgets B1,B2,... --out DIR [--loss P] [--seed S]``
encodes IMAGE on a simulated vehicle, sends it to the full image over a simulated link (frames
of at most N bytes, each frame lost with probability P in both directions, seeded by S) and
writes:

* ``DIR/messages.jsonl``: one JSON object per wire message in send order, both directions:
  ``type``, ``hex`` (the encoded message), ``direction`` (``down`` = vehicle to ship, ``up``),
  ``frame`` (frame index), ``bytes``, ``lost``, ``wire_total`` (cumulative wire bytes up to
  and including this message: messages plus the frame headers, both directions) and the
  message fields (``coex_core.jsonfmt``);
* ``DIR/recon_<B>.png`` for each budget B: the topside image after the longest prefix of the
  transfer whose wire bytes (``wire_total``) are at most B (mid-grey when nothing decodable
  arrived in that prefix);
* ``DIR/image_<id>.tiff`` / ``.png``: the final topside image, and ``DIR/summary.json``.

``coex image region IMAGE --box X0,Y0,X1,Y1 [--quality DB | --layers N | --bytes B] --mtu N
--out DIR [--base GOAL] [--loss P] [--seed S] [--crops auto|never|always]`` sends IMAGE to its
``--base`` goal (default ``layer:1``, the first quality mark), then asks for the rectangle
(pixels, X1 and Y1 exclusive) with one ``ImageRegionRequest`` at the goal (default ``--quality
30`` dB), the vehicle's option ``crops`` set to ``--crops`` (default ``auto``), and writes
``DIR/before.png`` and ``DIR/after.png`` (what topside shows, the region outlined, a crop pasted
over the image), ``DIR/crop.png`` when the vehicle answered with a crop (what the crop shows of
the box) and ``DIR/summary.json``: ``box``, ``goal`` (kind and value), ``state`` (the vehicle's
answer: accepted / rejected / requested when none arrived), ``served`` (``crop`` or
``packets``), ``crop`` (its image id, size, body bytes, resolutions, layers, the parent packets
it refines, the parent layers it covers, its PSNR inside the box and before it; null for
packets), ``base_wire_bytes`` and ``region_wire_bytes`` (vehicle-to-ship wire bytes for the base and
after the request), ``psnr_inside_before`` / ``psnr_inside_after`` and ``psnr_outside_after``
(dB against the vehicle's image), ``layers_complete`` (quality layers complete inside the box).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from coex import ConfigError, Product, to_json, wire

from .output import outlined, write_png

__all__ = ["register", "run_roundtrip", "load_image"]


def _budgets(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"budgets must be integers separated by commas: {text!r}") from None
    if not values or any(v < 0 for v in values):
        raise argparse.ArgumentTypeError("give at least one non-negative budget")
    return values


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("image", help="progressive imagery (JPEG 2000) tools")
    sub = p.add_subparsers(dest="image_command", required=True)
    r = sub.add_parser("roundtrip", help="send one image over a simulated lossy link; write reconstructions")
    r.add_argument("image", metavar="IMAGE", help="image file (TIFF, PNG, JPEG ...)")
    r.add_argument("--mtu", type=int, required=True, metavar="N", help="frame size in bytes (>= 32)")
    r.add_argument("--budgets", type=_budgets, required=True, metavar="B1,B2,...",
                   help="wire-byte budgets for recon_<B>.png")
    r.add_argument("--out", required=True, metavar="DIR", help="output directory")
    r.add_argument("--loss", type=float, default=0.0, metavar="P", help="frame loss probability (default 0)")
    r.add_argument("--seed", type=int, default=0, metavar="S", help="loss seed (default 0)")
    r.add_argument("--colour", action="store_true", help="send colour instead of grey")
    r.add_argument("--max-rounds", type=int, default=20000, help="give up after this many frames")
    g = sub.add_parser("region", help="send one image to a base goal, then a region of it to a goal; write "
                                      "before/after images and the bytes")
    g.add_argument("image", metavar="IMAGE", help="image file (TIFF, PNG, JPEG ...)")
    g.add_argument("--box", type=_box, required=True, metavar="X0,Y0,X1,Y1",
                   help="the region in pixels (X1, Y1 exclusive)")
    goal = g.add_mutually_exclusive_group()
    goal.add_argument("--quality", type=float, metavar="DB", help="PSNR inside the region (default 30 dB)")
    goal.add_argument("--layers", type=int, metavar="N", help="quality layers of the region's precincts")
    goal.add_argument("--bytes", type=int, metavar="B", help="a budget of codestream bytes")
    g.add_argument("--base", default="layer:1", metavar="GOAL",
                   help="the whole image's goal first: none, full, layer:N, fraction:P, bytes:N (default layer:1)")
    g.add_argument("--mtu", type=int, default=64, metavar="N", help="frame size in bytes (default 64)")
    g.add_argument("--out", required=True, metavar="DIR", help="output directory")
    g.add_argument("--loss", type=float, default=0.0, metavar="P", help="frame loss probability (default 0)")
    g.add_argument("--seed", type=int, default=0, metavar="S", help="loss seed (default 0)")
    g.add_argument("--max-rounds", type=int, default=20000, help="give up after this many frames")
    g.add_argument("--crops", choices=("auto", "never", "always"), default="auto",
                   help="how the vehicle may serve the region (its option crops): auto (the cheapest way it "
                        "measures), never (the region's packets only) or always (a crop)")
    p.set_defaults(func=lambda a: p.print_help() or 2)
    r.set_defaults(func=run_roundtrip)
    g.set_defaults(func=run_region)


def _box(text: str) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a box is four integers X0,Y0,X1,Y1: {text!r}") from None
    return x0, y0, x1, y1


def run_region(args: argparse.Namespace) -> int:
    from .codec import psnr
    from .sim import region_transfer

    if args.mtu < 32:
        raise ConfigError("--mtu must be at least 32")
    if not 0.0 <= args.loss < 1.0:
        raise ConfigError("--loss must be in [0, 1)")
    kind, value = (("layer", args.layers) if args.layers is not None else ("bytes", args.bytes)
                   if args.bytes is not None else ("quality", 30.0 if args.quality is None else args.quality))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    run = region_transfer(load_image(args.image), args.box, kind, value, mtu=args.mtu, base=args.base,
                          loss=args.loss, seed=args.seed, max_rounds=args.max_rounds,
                          sender_config={"crops": args.crops})
    enc = run.sender.images[run.image_id].enc
    x0, y0, x1, y1 = args.box

    def inside(img: Any) -> float | None:
        return None if img is None else round(psnr(img[y0:y1, x0:x1], enc.image[y0:y1, x0:x1]), 3)

    outside = None
    if run.after is not None:
        mask = np.ones(run.after.shape[:2], bool)
        mask[y0:y1, x0:x1] = False
        outside = round(psnr(run.after[mask], enc.image[mask]), 3) if mask.any() else None
    blank = np.full(enc.image.shape, 128, np.uint8)
    write_png(out / "before.png", outlined(blank if run.before is None else run.before, args.box))
    write_png(out / "after.png", outlined(blank if run.after is None else run.after, args.box))
    crop = None
    if run.crop is not None:
        shown = run.receiver.image(run.crop.image_id)
        if shown is not None:
            write_png(out / "crop.png", shown)
        c = run.crop.crop
        crop = {"image_id": run.crop.image_id, "width": run.crop.enc.width, "height": run.crop.enc.height,
                "body_bytes": len(run.crop.enc.body), "resolutions": run.crop.enc.stream.resolutions,
                "layers": run.crop.enc.stream.layers, "base_packets": c.base, "cover": c.cover,
                "psnr": c.psnr, "base_psnr": c.base_psnr, "shown": run.region.get("crop", {}).get("shown")}
    summary = {
        "image": str(args.image), "width": enc.width, "height": enc.height, "box": list(args.box),
        "goal": {"kind": kind, "value": value}, "base": args.base, "state": run.region["state"],
        "crops": args.crops, "served": run.region.get("served"), "crop": crop,
        "base_wire_bytes": run.base_bytes, "region_wire_bytes": run.region_bytes,
        "psnr_inside_before": inside(run.before), "psnr_inside_after": inside(run.after),
        "psnr_outside_after": outside,
        "layers_complete": int(run.region.get("layers_complete", 0)), "layers": enc.stream.layers,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary))
    return 0 if run.region["state"] == "accepted" else 1


def load_image(path: str | Path) -> Any:
    """Read an image file with tifffile (TIFF) or Pillow (anything else)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"no such image file: {p}")
    try:
        if p.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            return tifffile.imread(p)
        from PIL import Image

        with Image.open(p) as im:
            return np.asarray(im.convert("RGB") if im.mode not in ("L", "RGB") else im)
    except Exception as exc:
        raise ConfigError(f"cannot read image {p}: {exc}") from exc


def run_roundtrip(args: argparse.Namespace) -> int:
    from . import ImageInput, ImageryModality
    from .sim import Bernoulli, Transfer, WireEvent

    if args.mtu < 32:
        raise ConfigError("--mtu must be at least 32")
    if not 0.0 <= args.loss < 1.0:
        raise ConfigError("--loss must be in [0, 1)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    image = load_image(args.image)
    modality = ImageryModality()
    sender = modality.sender({"default_goal": "full", "grey": not args.colour})
    receiver = modality.receiver({"max_ack_bytes": min(81, args.mtu - wire.header_size())})
    sender.ingest(ImageInput(image), 0.0)
    (image_id, tx), = sender.images.items()
    shape = (tx.enc.height, tx.enc.width) if tx.enc.grey else (tx.enc.height, tx.enc.width, 3)
    blank = np.full(shape, 128, np.uint8)
    snapshots: list[tuple[int, Any]] = [(0, blank)]
    lines: list[str] = []
    current: dict[str, Any] = {"image": blank}

    def record(ev: WireEvent, products: list[Product]) -> None:
        for pr in products:
            if pr.kind == "image" and pr.data is not None:
                current["image"] = pr.data
        obj = {"type": type(ev.message).__name__, "hex": wire.encode(ev.message).hex(),
               "direction": ev.direction, "frame": ev.frame, "bytes": ev.size, "lost": ev.lost,
               "wire_total": ev.wire_total}
        fields = to_json(ev.message)
        fields.pop("type", None)
        obj.update({k: v for k, v in fields.items() if k not in obj})
        lines.append(json.dumps(obj))
        snapshots.append((ev.wire_total, current["image"]))

    transfer = Transfer(sender, receiver, mtu=args.mtu, down=Bernoulli(args.loss, args.seed),
                        up=Bernoulli(args.loss, args.seed + 1), on_message=record)

    def done() -> bool:
        rx = receiver.images.get(image_id)
        return rx is not None and bool(rx.have.all()) and not sender.order()

    rounds = transfer.run(done, args.max_rounds)
    (out / "messages.jsonl").write_text("\n".join(lines) + "\n")
    totals = np.array([s[0] for s in snapshots])
    recon = {}
    for b in args.budgets:
        k = int(np.searchsorted(totals, b, side="right")) - 1
        write_png(out / f"recon_{b}.png", snapshots[k][1])
        recon[str(b)] = {"wire_bytes": int(totals[k]), "messages": k}
    final = receiver.image(image_id)
    from .output import write_tiff

    if final is not None:
        write_tiff(out / f"image_{image_id:04d}.tiff", final)
        write_png(out / f"image_{image_id:04d}.png", final)
    from .codec import psnr

    summary = {
        "image": str(args.image), "width": tx.enc.width, "height": tx.enc.height, "grey": tx.enc.grey,
        "body_bytes": len(tx.enc.body), "packets": len(tx.enc.packet_starts), "rounds": rounds,
        "messages": len(lines), "wire_bytes": int(totals[-1]),
        "down_bytes": transfer.events[-1].down_total if transfer.events else 0,
        "psnr_final": None if final is None else round(psnr(final, tx.enc.image), 3),
        "recon": recon,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary))
    return 0

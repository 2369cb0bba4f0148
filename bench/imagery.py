"""Imagery benchmark: wire bytes to reach 25 / 30 / 35 dB PSNR against the 2022 configuration and
the single-layer bound, at several MTUs and at every MTU from 64, and the bytes of region
requests (quarter- and eighth-frame regions, served as the vehicle chooses: packets or a crop).

Reads the grey NUI dive-040 images from ``../shared/data/nui040/`` (or ``$COEX_NUI040``) when
present, else generated seafloor images (``coex_plugins.imagery.synth``). For each image:

* **2022**: grey, 6 resolutions, 10 LRCP layers from 640 to 20,480 B (5/3 wavelet), the raw
  codestream (OpenJPEG's headers and COM included) cut at whole packets, decoded with Psot = 0
  plus EOC. Bytes = codestream prefix length, at every packet boundary.
* **bound**: the best single-layer OpenJPEG 9/7 encode (5, 6 or 7 resolutions) that reaches the
  quality, found by bisection on its rate: its packet data (body) bytes.
* **ours**, at each MTU (``--mtus``, default 64, 128, 256): the default ``CodingParams`` (quality
  layers, 256-sample precincts; no header sent), delivered by the real ``ImagerySender`` over
  frames of that many bytes. Bytes = every vehicle-to-ship wire byte: frame headers, the
  ``ImageAnnounce`` and each ``ImageFragment`` with its header. The cost of every
  packet-aligned prefix (every packet boundary: the finest grid there is) is taken from a
  lossless transfer of the whole image (the sender cuts its last fragment at the goal); the
  prefix at each threshold is then checked end to end: a sender with that byte goal, a receiver,
  and the receiver's decoded image must reach the PSNR with exactly that many wire bytes.
  ``body`` is the packet data of that prefix.
* **every MTU** (``--every-mtu``, default 64-256, each one): the worst ours / 2022 per threshold
  over those MTUs (``every_mtu``), and the same on generated images unlike the development set
  (``stress``: each image reduced to 213 x 160 and 160 x 120, with noise, with doubled contrast,
  and synthetic frames; ``--stress-mtus``, default every 8th MTU from 64; ``--no-stress``).
* **layout**: body bytes to each threshold with the default coding against the default before
  issue 25 (22 byte layers, one precinct per resolution): the layout that makes regions possible
  must keep the whole image within 3 % (ratio of the means).
* **regions**: for each quarter and each eighth (4 x 2) of the frame, from an announced image with
  nothing else held and from the image at the sender's default goal, one ``ImageRegionRequest``
  at 30 dB and at 35 dB (``coex image region``'s run: the vehicle serves it with the region's
  packets, the image's next packets or a crop), at each MTU: its wire bytes (the request's
  ``CommandAck`` and the ``TransferProgress`` it prompts left out: asking for more of the whole
  image costs them too), the PSNR inside the box, against the wire bytes of the whole image sent
  on from the same start (new frames) until the shortest prefix whose decode reaches the quality
  inside the box (``whole_until_region_wire``), and until the whole image reaches it
  (``whole_to_quality_wire``). The quarters again at ``--packets-mtu`` (256) with ``crops =
  never``: the region's packets alone, as before issue 42.

Targets (issue 42; ``targets``): the region requests' bytes over the whole image's until the
region is there, at every MTU: a quarter to 30 dB from nothing at most 0.35, an eighth at most
0.25, a quarter from the default goal to 35 dB at most 0.4, every request accepted and reaching
its quality; and no dive image above 2022 at any threshold and any MTU from 64 to 256. The
issue's "on average" is judged on all bytes: ``met`` takes all bytes of a group over all bytes
(the mean bytes over the mean bytes; ``meets_targets``), the measure of the study the issue
quotes (a crop at "about 0.24x"). ``met_by_mean_of_ratios`` reports the mean of the per-request
ratios beside it (``meets_targets_by_mean_of_ratios``, not a target): on the softest images the
whole image brings a region to 30 dB in a few tens of bytes, less than a crop's announcement
and first fragment, so the mean of the ratios stays high there (docs/imagery.md).
Issue 25's figures (bound, layout) are printed as before.

Prints the tables; writes ``bench/results/imagery.json``.
Run: ``.venv/bin/python bench/imagery.py [--quick] [--mtus 64,128,256] [--every-mtu 64-256]
[--no-stress] [--packets-mtu 256]`` (6 to 25 minutes for the 13 images on 2 cores, with what else runs).
``--issue54`` runs only the issue 54 table (every frame at MTU 64, 128, 256; about 4 minutes) and
writes ``bench/results/imagery-issue54.json``; ``--option KEY=JSON`` (repeatable, e.g.
``tighten=false``, ``short_fragments=false``) runs every sender with that option, coding options
coding the measured images too.
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

from coex_core import wire
from coex_core.messages import ImageFragment, ImageShortFragment
from coex_plugins.imagery import ImageInput, ImageryModality, codec
from coex_plugins.imagery.goals import parse_goal
from coex_plugins.imagery.sender import (
    CODING_KEYS,
    MAX_FRAGMENT_DATA,
    SENDER_DEFAULTS,
    SHORT_HEAD,
    SHORT_MAX_DATA,
    SHORT_OFFSETS,
    fragment_size,
)
from coex_plugins.imagery.sim import Transfer, region_transfer
from coex_plugins.imagery.synth import seafloor

THRESHOLDS = (25.0, 30.0, 35.0)
BOUND_SLACK = 1.10  # issue 25: the mean at 30 dB within 10 % of the single-layer bound
LAYOUT_SLACK = 1.03  # issue 25: the default layout within 3 % of the previous default's bytes
#: the default before issue 25: 22 byte layers, one precinct per resolution
PREVIOUS_DEFAULT = {"layer_bytes": (40, 60, 85, 120, 170, 240, 330, 450, 600, 800, 1050, 1400, 1850, 2400,
                                    3100, 4000, 5200, 6700, 8700, 11300, 14700, 20480),
                    "precincts": 0, "layer_psnr": ()}
DATA = Path(os.environ.get("COEX_NUI040", Path(__file__).resolve().parents[2] / "shared" / "data" / "nui040"))


#: sender options every run of the benchmark uses (``--option KEY=VALUE``; coding options among
#: them code the images the curves are measured on too): empty = the defaults
OPTIONS: dict[str, Any] = {}


def encode(img: np.ndarray) -> codec.Encoded:
    """``img`` encoded as the benchmark's sender encodes it (the default coding and OPTIONS)."""
    return codec.encode_image(img, codec.CodingParams.from_config({k: v for k, v in OPTIONS.items()
                                                                   if k in CODING_KEYS}))


def load_images(quick: bool) -> tuple[str, list[tuple[str, np.ndarray]]]:
    files = sorted(glob.glob(str(DATA / "*.tif*")))
    if files:
        import tifffile

        files = files[:4] if quick else files
        return "nui040", [(Path(f).stem.removeprefix("image_"), codec.to_grey(tifffile.imread(f))) for f in files]
    n = 3 if quick else 8
    return "synthetic", [(f"synth_{i}", seafloor(480, 640, seed=100 + i)) for i in range(n)]


def _single_layer(img: np.ndarray, rate: int, numres: int) -> tuple[int, float]:
    """(body bytes, PSNR) of a single-layer 9/7 encode with this codestream byte target."""
    import glymur

    path = os.path.join(codec._scratch(), "bound.j2k")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        glymur.Jp2k(path, data=img, numres=numres, cratios=[img.size / rate], irreversible=True)
    cs = open(path, "rb").read()
    os.unlink(path)
    _hdr, sot, start, end, _ = codec._split(cs)
    head = bytearray(cs[:start])
    head[sot + 6:sot + 10] = b"\0\0\0\0"
    return end - start, codec.psnr(codec.decode_codestream(bytes(head) + cs[start:end] + b"\xff\xd9"), img)


def bound(img: np.ndarray, x: float) -> int | None:
    """The fewest packet-data bytes of a single-layer 9/7 encode (5, 6 or 7 resolutions) reaching
    ``x`` dB: bisection on the rate to 0.5 %."""
    best: int | None = None
    for numres in (5, 6, 7):
        lo, hi = 30, 200_000
        found = None
        while hi - lo > max(2, lo * 0.005):
            mid = int((lo * hi) ** 0.5)
            n, q = _single_layer(img, mid, numres)
            if q >= x:
                hi, found = mid, n
            else:
                lo = mid
        if found is not None and (best is None or found < best):
            best = found
    return best


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
        q = codec.psnr(codec.decode_codestream(bytes(head) + body[:int(n)] + b"\xff\xd9"), img)
        pts.append((len(head) - plt_bytes + int(n), q))  # bytes as if written without PLT
    return pts


def quarters(img: np.ndarray) -> list[tuple[int, int, int, int]]:
    h, w = img.shape[:2]
    return [(0, 0, w // 2, h // 2), (w // 2, 0, w, h // 2), (0, h // 2, w // 2, h), (w // 2, h // 2, w, h)]


def eighths(img: np.ndarray) -> list[tuple[int, int, int, int]]:
    """The frame cut in 4 x 2: each quarter halved side by side (160 x 240 px of a 640 x 480 frame)."""
    h, w = img.shape[:2]
    xs, ys = [w * i // 4 for i in range(5)], [0, h // 2, h]
    return [(xs[i], ys[j], xs[i + 1], ys[j + 1]) for j in range(2) for i in range(4)]


def packet_curve(enc: codec.Encoded, img: np.ndarray,
                 boxes: list[tuple[int, int, int, int]] = ()) -> list[Any]:  # type: ignore[assignment]
    """(body prefix, PSNR) at every packet boundary of an encoded image; with ``boxes``, (body
    prefix, PSNR, [PSNR inside each box])."""
    ends = np.append(enc.packet_starts[1:], len(enc.body))
    pts: list[Any] = []
    for n in ends:
        pk = codec.split_packets(enc.body, enc.packet_starts, int(n))
        shown = codec.decode_packets(enc.params, enc.width, enc.height, pk)
        q = codec.psnr(shown, img)
        if boxes:
            pts.append((int(n), q, [codec.psnr(shown[y0:y1, x0:x1], img[y0:y1, x0:x1]) for x0, y0, x1, y1 in boxes]))
        else:
            pts.append((int(n), q))
    return pts


def body_needs(enc: codec.Encoded, img: np.ndarray) -> dict[str, int | None]:
    curve = packet_curve(enc, img)
    return {str(x): next((n for n, q in curve if q >= x), None) for x in THRESHOLDS}


def transfer(img: np.ndarray, mtu: int, goal: str) -> tuple[Transfer, Any, Any]:
    m = ImageryModality()
    s = m.sender({**OPTIONS, "default_goal": goal, "progress_interval": 1e9})
    r = m.receiver({})
    s.ingest(ImageInput(img, time=0.0), 0.0)
    t = Transfer(s, r, mtu=mtu)
    t.run(lambda: not s.order(), 100000)
    return t, s, r


Fragment = ImageFragment | ImageShortFragment


def sender_fragments(img: np.ndarray, mtu: int, upto: int | None = None) -> tuple[codec.Encoded,
                                                                                 list[tuple[Fragment, int, bool]]]:
    """A lossless transfer of the whole image as the vehicle makes it, frames of at most ``mtu``
    bytes, the channel reporting each delivered (no receiver: fast enough for every MTU): each
    fragment with the vehicle-to-ship wire bytes before it (frame headers, the announcement,
    earlier fragments; a fragment first in its frame pays the frame header), until the body
    prefix ``upto`` is sent (default: all of it), and whether the image could go in short
    fragments then (a last fragment cut short at a goal may be one). ``transfer`` and ``verify``
    check the same figures end to end with a receiver."""
    s = ImageryModality().sender({**OPTIONS, "default_goal": "full", "progress_interval": 1e9})
    s.ingest(ImageInput(img, time=0.0), 0.0)
    down, now = 0, 0.0
    frags: list[tuple[Fragment, int, bool]] = []
    while upto is None or not frags or frags[-1][0].offset + len(frags[-1][0].data) < upto:
        now += 5.0
        short_ok = s._short_ok(s.images[0])
        out = s.fill(mtu - wire.header_size(), now)
        if not out:
            break
        for i, msg in enumerate(out):
            head = wire.header_size() if i == 0 else 0
            if isinstance(msg, ImageFragment | ImageShortFragment):
                if isinstance(msg, ImageFragment) and msg.packet is not None:
                    raise AssertionError("a lossless transfer sent packet marks")
                frags.append((msg, down + head, short_ok))
            down += head + wire.encoded_size(msg)
            s.acked(msg, now)
    return s.images[0].enc, frags


def our_curve(img: np.ndarray, mtu: int, pcurve: list[Any] | None = None,
              boxes: list[tuple[int, int, int, int]] = ()) -> tuple[list[tuple[int, float, int, list[float]]],  # type: ignore[assignment]
                                                                codec.Encoded]:
    """(wire bytes, PSNR, body prefix, PSNR inside each box) at every packet boundary of a
    lossless transfer of the whole image: every vehicle-to-ship byte before the fragment that
    ends the prefix, plus that fragment cut at the prefix (the sender cuts its last fragment at a
    goal; no packet marks). ``pcurve``: :func:`packet_curve` with ``boxes``, when known."""
    pc = pcurve if pcurve is not None else packet_curve(encode(img), img, boxes or quarters(img))
    upto = max(n for n, _q, _ in pc)
    enc, frags = sender_fragments(img, mtu, upto)
    pts = []
    for n, q, inq in pc:
        f, base, short_ok = next((f, b, ok) for f, b, ok in frags if f.offset < n <= f.offset + len(f.data))
        # the sender cuts its last fragment at the goal: a short one where it can
        short = short_ok and f.offset < SHORT_OFFSETS and n - f.offset <= SHORT_MAX_DATA
        head = SHORT_HEAD if short else fragment_size(0, 0, f.offset)
        pts.append((base + head + n - f.offset, q, n, inq))
    return pts, enc


Wire = dict[int, dict[str, int | None]]


def wire_at(img: np.ndarray, mtus: list[int], pcurve: list[Any] | None = None) -> tuple[Wire, dict[int, dict[str, int]]]:
    """Our wire bytes to each threshold at each MTU (``{mtu: {threshold: bytes or None}}``) and
    the body prefix each of those ends at (``{mtu: {threshold: bytes}}``, thresholds reached)."""
    pc = pcurve if pcurve is not None else [(n, q, []) for n, q in packet_curve(encode(img), img)]
    # only the prefixes up to the highest threshold matter: the transfer stops there
    last = next((i for i, (_n, q, _) in enumerate(pc) if q >= max(THRESHOLDS)), len(pc) - 1)
    pc = pc[:last + 1]
    out: Wire = {}
    bodies: dict[int, dict[str, int]] = {}
    for mtu in mtus:
        pts = our_curve(img, mtu, pc)[0]
        out[mtu] = {str(x): need([(c, q) for c, q, _, _ in pts], x) for x in THRESHOLDS}
        bodies[mtu] = {str(x): next(n for c, q, n, _ in pts if c == out[mtu][str(x)] and q >= x)
                       for x in THRESHOLDS if out[mtu][str(x)] is not None}
    return out, bodies


def worst_of(wire: dict[int, dict[str, int | None]], base: list[tuple[int, float]],
             mtus: list[int] | None = None) -> dict[str, Any]:
    """Ours / 2022 at each threshold, the worst over ``mtus`` (default: every MTU of ``wire``),
    with the MTU and both byte counts: ``{threshold: [ratio, mtu, ours, 2022]}``."""
    worst: dict[str, Any] = {}
    for mtu in mtus if mtus is not None else sorted(wire):
        for x in THRESHOLDS:
            ours, old = wire[mtu][str(x)], need(base, x)
            if ours is None or old is None:
                continue
            if str(x) not in worst or ours / old > worst[str(x)][0]:
                worst[str(x)] = [round(ours / old, 4), mtu, ours, old]
    return worst


def worst_every_mtu(img: np.ndarray, base: list[tuple[int, float]], mtus: list[int],
                    pcurve: list[Any] | None = None) -> dict[str, Any]:
    """Ours / 2022 at each threshold, the worst over ``mtus`` (every MTU from 64 up), with the
    MTU and both byte counts: ``{threshold: [ratio, mtu, ours, 2022]}``."""
    return worst_of(wire_at(img, mtus, pcurve)[0], base)


def stress_images(images: list[tuple[str, np.ndarray]]) -> list[tuple[str, np.ndarray]]:
    """Generated images unlike the development set, for the 2022 comparison: each dive image
    reduced to 213 x 160 and to 160 x 120, with and without sensor noise (small images: the
    case that comes nearest 2022), and with doubled contrast (the most detailed); and synthetic
    seafloor frames. (Blurred, noisier and 320 x 240 variants were measured while this was
    written and stay further below 2022: docs/imagery.md.)"""
    rng = np.random.default_rng(42)
    out = []

    def u8(a: np.ndarray) -> np.ndarray:
        out_: np.ndarray = np.clip(np.rint(a), 0, 255).astype(np.uint8)
        return out_

    def down(a: np.ndarray, f: int) -> np.ndarray:
        h, w = a.shape
        return u8(a[:h // f * f, :w // f * f].reshape(h // f, f, w // f, f).mean(axis=(1, 3)))

    for name, img in images:
        h, w = img.shape
        m = float(img.mean())
        out += [(f"{name}/down3", down(img, 3)), (f"{name}/down4", down(img, 4)),
                (f"{name}/down4+noise", u8(down(img, 4) + rng.normal(0, 2, (h // 4, w // 4)))),
                (f"{name}/contrast", u8((img - m) * 2 + m))]
    out += [(f"synth_{i}", seafloor(480, 640, seed=200 + i)) for i in range(4)]
    return out


#: issue 54: every frame at most this times the 2022 configuration's bytes, at TARGET_MTUS, at
#: every threshold
TARGET_2022 = 0.95
TARGET_MTUS = (64, 128, 256)
#: seeds of the held-out sand-ripple frames (issue 54): no coding choice was tuned on them
HELD_OUT_RIPPLES = tuple(range(54001, 54007))


def held_out_images(images: list[tuple[str, np.ndarray]]) -> list[tuple[str, np.ndarray]]:
    """Frames held out of development (issue 54; measured only once the coding was chosen):
    textured sand ripples (``synth.sand_ripples``, seeds HELD_OUT_RIPPLES, 640 x 480), and from
    each dive image other crops and rescales than the bench's own (which are whole frames
    box-reduced by 3 and 4): its central 360 x 270 window at full resolution, the whole frame
    resized to 400 x 300 (Lanczos) and its lower-left 480 x 360 window resized to 240 x 180
    (bilinear)."""
    from PIL import Image

    from coex_plugins.imagery.synth import sand_ripples

    out = [(f"ripples_{seed}", sand_ripples(480, 640, seed=seed)) for seed in HELD_OUT_RIPPLES]
    for name, img in images:
        h, w = img.shape
        cy, cx = (h - 270) // 2, (w - 360) // 2
        out.append((f"{name}/centre", np.ascontiguousarray(img[cy:cy + 270, cx:cx + 360])))
        out.append((f"{name}/400x300", np.asarray(Image.fromarray(img).resize((400, 300), Image.Resampling.LANCZOS))))
        out.append((f"{name}/corner", np.asarray(Image.fromarray(np.ascontiguousarray(img[h - 360:, :480])).resize(
            (240, 180), Image.Resampling.BILINEAR))))
    return out


def target_rows(name: str, group: str, img: np.ndarray, base: list[tuple[int, float]],
                wire: dict[int, dict[str, int | None]]) -> dict[str, Any]:
    """One frame's row of the issue 54 table: ours / 2022 at each TARGET_MTUS and threshold (None
    where either never reaches it), the worst and whether it is at most TARGET_2022."""
    old = {str(x): need(base, x) for x in THRESHOLDS}
    ratio = {str(m): {x: _ratio(wire[m][x], old[x]) for x in old} for m in TARGET_MTUS}
    vals = [(v, int(m), x) for m, row in ratio.items() for x, v in row.items() if v is not None]
    worst = max(vals, default=None)
    return {"frame": name, "set": group, "shape": list(img.shape), "2022": old,
            "ours": {str(m): wire[m] for m in TARGET_MTUS}, "ratio": ratio,
            "worst": None if worst is None else list(worst), "met": worst is None or worst[0] <= TARGET_2022}


def table_frames(dive: list[tuple[str, np.ndarray]], stress: bool, held_out: bool) -> list[tuple[str, str, np.ndarray]]:
    """The issue 54 table's frames beside the dive images (``dive``: empty on generated data):
    the bench's generated images (``stress``) and the held-out frames (``held_out``), each with
    its set's name."""
    return ([(n, "bench", i) for n, i in stress_images(dive)] if stress else []) + \
        ([(n, "held-out", i) for n, i in held_out_images(dive)] if held_out else [])


def table_row(name: str, group: str, img: np.ndarray, base: list[tuple[int, float]], mtus: list[int],
              pcurve: list[Any] | None = None, enc: codec.Encoded | None = None) -> tuple[dict[str, Any], Wire]:
    """One frame's row of the issue 54 table (:func:`target_rows`, with the body prefix at each
    point and the layers), its worst point checked end to end (a sender with that byte goal, a
    receiver: its decoded image must reach the threshold with exactly those wire bytes); and
    our wire bytes at ``mtus`` and TARGET_MTUS (:func:`wire_at`; ``pcurve`` when known, of
    ``enc`` when given)."""
    enc = enc if enc is not None else encode(img)
    if pcurve is None:
        pcurve = [(n, q, []) for n, q in packet_curve(enc, img)]
    wire, bodies = wire_at(img, sorted({*mtus, *TARGET_MTUS}), pcurve)
    row = target_rows(name, group, img, base, wire)
    row["layers"] = enc.stream.layers
    row["body"] = {str(m): bodies[m] for m in TARGET_MTUS}
    if row["worst"] is not None:
        _, mtu, x = row["worst"]
        down, q = verify(img, mtu, bodies[mtu][x])
        row["verified"] = {"mtu": mtu, "threshold": x, "wire_bytes": down, "psnr": round(q, 3)}
        if down != wire[mtu][x] or q < float(x):
            raise AssertionError(f"{name} MTU {mtu}: end to end {down} B / {q:.2f} dB, expected "
                                 f"{wire[mtu][x]} B / at least {x} dB")
    return row, wire


def table_sets(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue 54 table by set: frames, the worst point, the worst and the mean ratio per MTU
    and threshold, whether every frame is within TARGET_2022 and which are not."""
    def cells(mine: list[dict[str, Any]]) -> dict[str, list[float]]:
        out: dict[str, list[float]] = {}
        for m in TARGET_MTUS:
            for x in THRESHOLDS:
                vals = [r["ratio"][str(m)][str(x)] for r in mine if r["ratio"][str(m)][str(x)] is not None]
                if vals:
                    out[f"{m}/{x}"] = vals
        return out

    sets: dict[str, Any] = {}
    for group in dict.fromkeys(r["set"] for r in rows):
        mine = [r for r in rows if r["set"] == group]
        worst = max(([*r["worst"], r["frame"]] for r in mine if r["worst"]), default=None)
        per_cell = cells(mine)
        sets[group] = {"frames": len(mine), "worst": worst,
                       "worst_per_mtu_threshold": {k: max(v) for k, v in per_cell.items()},
                       "mean_per_mtu_threshold": {k: round(float(np.mean(v)), 4) for k, v in per_cell.items()},
                       "met": all(r["met"] for r in mine), "not_met": [r["frame"] for r in mine if not r["met"]]}
    return sets


def print_table(rows: list[dict[str, Any]], sets: dict[str, Any]) -> None:
    """The issue 54 table: each frame's ratios at TARGET_MTUS and thresholds, then each set."""
    print(f"\nissue 54: ours / 2022 per frame at MTU {', '.join(map(str, TARGET_MTUS))} and "
          f"{' / '.join(f'{x:g}' for x in THRESHOLDS)} dB (- : 2022 or ours never reaches it); at most {TARGET_2022}")
    print(f"{'frame':24} {'set':9} " + " ".join(f"{'MTU ' + str(m):^17}" for m in TARGET_MTUS) + "  worst")
    for r in rows:
        cells = " ".join(" ".join(f"{v:5.3f}" if v is not None else "    -" for v in r["ratio"][str(m)].values())
                         for m in TARGET_MTUS)
        w = r["worst"]
        print(f"{r['frame']:24} {r['set']:9} {cells}  {w[0] if w else '-'} {'MET' if r['met'] else 'NOT MET'}")
    for group, v in sets.items():
        w = v["worst"]
        print(f"  {group}: {v['frames']} frames, worst {w[0]} ({w[3]}, MTU {w[1]}, {w[2]} dB)" if w
              else f"  {group}: {v['frames']} frames", f"-> {'MET' if v['met'] else 'NOT MET'}"
              + (f" ({len(v['not_met'])} above: {', '.join(v['not_met'])})" if v["not_met"] else ""))
        print("    worst per MTU/dB: " + ", ".join(f"{k} {val:.3f}" for k, val in v["worst_per_mtu_threshold"].items()))
        print("    mean per MTU/dB:  " + ", ".join(f"{k} {val:.3f}" for k, val in v["mean_per_mtu_threshold"].items()))


def verify(img: np.ndarray, mtu: int, goal_bytes: int) -> tuple[int, float]:
    """End to end: wire bytes and receiver PSNR for a sender whose goal is ``goal_bytes``."""
    t, _s, r = transfer(img, mtu, f"bytes:{goal_bytes}")
    down = max((e.down_total for e in t.events if e.direction == "down"), default=0)
    image = r.image(0)
    return down, (17.0 if image is None else codec.psnr(image, img))


def continuation(start: int, end: int, mtu: int) -> int:
    """Wire bytes of sending body bytes ``start .. end`` of an announced image afresh, as the
    sender does: one fragment per frame of at most ``mtu`` bytes (a short one where it carries as
    much: topside heard the image), each frame with its header."""
    total, off = 0, start
    while off < end:
        room = mtu - wire.header_size()
        k = min(end - off, MAX_FRAGMENT_DATA, room - fragment_size(0, 0, off))
        head = fragment_size(0, 0, off)
        # bytes sent the first time of an image topside heard: a short fragment where it carries as much
        short = min(end - off, SHORT_MAX_DATA, room - SHORT_HEAD) if off < SHORT_OFFSETS else 0
        if short >= k:
            k, head = short, SHORT_HEAD
        total += wire.header_size() + head + k
        off += k
    return total


def need(curve: list[tuple[int, float]], x: float) -> int | None:
    return next((int(b) for b, q in curve if q >= x), None)


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else round(a / b, 4)


#: region targets (issue 42): mean region wire bytes / the whole image's wire bytes until the
#: region is there, at every MTU
REGION_TARGETS = {("quarter", "none", 30.0): 0.35, ("eighth", "none", 30.0): 0.25,
                  ("quarter", "default", 35.0): 0.40}
#: (where the image starts, the quality asked inside the region): from an announced image with
#: nothing held, and from the image at the sender's default goal
CONDITIONS = (("none", 30.0), ("none", 35.0), ("default", 30.0), ("default", 35.0))


def region_runs(name: str, img: np.ndarray, enc: codec.Encoded, curves: dict[int, list[Any]],
                kinds: dict[str, list[tuple[int, int, int, int]]], mtus: list[int],
                packets_mtu: int | None) -> list[dict[str, Any]]:
    """Every region request of the benchmark on one image: for each box of each kind, each
    condition and MTU, one ``coex image region`` run (the vehicle chooses packets or a crop),
    against the whole image sent on from the same start until the region is there (the
    shortest whole-packet prefix of the image whose decode reaches the quality inside the box).
    With ``packets_mtu``, the quarters again at that MTU with ``crops = never`` (the packets of
    the region only, as before crops)."""
    default = str(SENDER_DEFAULTS["default_goal"])
    out = []
    offset = 0
    for kind, boxes in kinds.items():
        for j, box in enumerate(boxes):
            jj = offset + j
            x0, y0, x1, y1 = box
            for start, q in CONDITIONS:
                goal = "none" if start == "none" else default
                n0 = 0 if goal == "none" else parse_goal(goal).bytes_for(enc)
                ways: list[tuple[int, str | None]] = [(m, None) for m in mtus]
                if packets_mtu is not None and kind == "quarter":
                    ways.append((packets_mtu, "never"))
                for mtu, crops in ways:
                    pts = curves[mtu]
                    # the whole image sent on from where it is (new frames and fragments), until
                    # the prefix whose decode reaches the quality inside the box
                    until_n = next((n for _c, _q, n, inq in pts if n >= n0 and inq[jj] >= q), None)
                    already = n0 > 0 and any(n == n0 and inq[jj] >= q for _c, _q, n, inq in pts)
                    whole_n = next((n for _c, wq, n, _ in pts if n >= n0 and wq >= q), None)
                    until = None if until_n is None else continuation(n0, until_n, mtu)
                    whole_q = None if whole_n is None else continuation(n0, whole_n, mtu)
                    run = region_transfer(img, box, "quality", q, mtu=mtu, base=goal,
                                          sender_config=None if crops is None else {"crops": crops})
                    # the request's answer (a CommandAck) and the progress report it prompts are
                    # left out: asking for more of the whole image costs them too
                    data = run.region_bytes - run.answer_bytes - run.progress_bytes
                    got = 0.0 if run.after is None else codec.psnr(run.after[y0:y1, x0:x1], img[y0:y1, x0:x1])
                    whole_until = None if until is None or already else until
                    out.append({
                        "image": name, "kind": kind, "box": list(box), "start": start, "quality": q, "mtu": mtu,
                        "crops": crops or "auto", "served": run.region.get("served"), "state": run.region["state"],
                        "wire_bytes": data, "answer_bytes": run.answer_bytes, "progress_bytes": run.progress_bytes, "base_wire_bytes": run.base_bytes,
                        "psnr": round(got, 3), "reached": got >= q,
                        "already": already, "whole_until_region_wire": whole_until,
                        "ratio_to_whole_until_region": None if already else _ratio(data, whole_until),
                        "whole_to_quality_wire": whole_q,
                        "ratio_to_whole_to_quality": _ratio(data, whole_q),
                        "crop": None if run.crop is None else {
                            "body_bytes": len(run.crop.enc.body), "base": run.crop.crop.base,
                            "cover": run.crop.crop.cover, "psnr": run.crop.crop.psnr},
                    })
        offset += len(boxes)
    return out


def region_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per kind, start, quality, MTU (and ``packets`` for the crops = never runs): the number
    of requests, how many were already there at the start, the mean, worst and all-bytes ratio
    of region wire bytes to the whole image's until the region is there (over the others), the
    share served by crops, whether every one reached its quality inside."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in runs:
        key = f"{r['kind']}/{r['start']}/{r['quality']:g}/{r['mtu']}" + ("/packets" if r["crops"] == "never" else "")
        groups.setdefault(key, []).append(r)
    out = {}
    for key, rs in groups.items():
        rated = [r for r in rs if r["ratio_to_whole_until_region"] is not None]
        ratios = [r["ratio_to_whole_until_region"] for r in rated]
        out[key] = {
            "count": len(rs), "already": sum(r["already"] for r in rs), "rated": len(rated),
            "mean_ratio": round(float(np.mean(ratios)), 4) if ratios else None,
            "worst_ratio": round(float(np.max(ratios)), 4) if ratios else None,
            "sum_ratio": round(sum(r["wire_bytes"] for r in rated) / max(1, sum(r["whole_until_region_wire"]
                                                                                  for r in rated)), 4),
            "mean_wire_bytes": round(float(np.mean([r["wire_bytes"] for r in rs])), 1),
            "mean_whole_until_wire": round(float(np.mean([r["whole_until_region_wire"] for r in rated])), 1)
            if rated else None,
            "crops": sum(r["served"] == "crop" for r in rs),
            "all_reached": all(r["reached"] for r in rs), "all_accepted": all(r["state"] == "accepted" for r in rs),
        }
    return out


def issue54(args: argparse.Namespace) -> int:
    """``--issue54``: only the issue 54 table (every frame: the dive images, the bench's generated
    images and the held-out frames, at TARGET_MTUS to each threshold against 2022), each frame's
    worst point checked end to end (a sender with that byte goal, a receiver, its decoded image
    must reach the threshold with exactly those wire bytes). Prints the table and writes
    ``bench/results/imagery-issue54.json`` (``--out`` overrides)."""
    t0 = time.time()
    source, images = load_images(False)
    dive = images if source == "nui040" else []
    frames = [(n, "dive" if source == "nui040" else "synthetic", i) for n, i in images]
    frames += table_frames(dive, not args.no_stress, not args.no_held_out)
    rows: list[dict[str, Any]] = []
    for name, group, img in frames:
        row, wire = table_row(name, group, img, baseline_curve(img), list(TARGET_MTUS))
        rows.append(row)
        print(f"{name:24} {group:9} 2022 {list(row['2022'].values())}  MTU 64 {list(wire[64].values())}  "
              f"worst {row['worst']} {'MET' if row['met'] else 'NOT MET'}  ({time.time() - t0:.0f} s)", flush=True)
    sets = table_sets(rows)
    summary = {"source": source, "options": OPTIONS, "limit": TARGET_2022, "mtus": list(TARGET_MTUS),
               "thresholds": [str(x) for x in THRESHOLDS], "sets": sets,
               "met": all(v["met"] for v in sets.values()), "seconds": round(time.time() - t0, 1)}
    print_table(rows, sets)
    print(f"every frame at most {TARGET_2022}x 2022: {'MET' if summary['met'] else 'NOT MET'}   ({summary['seconds']} s)")
    out = Path(args.out if args.out else Path(__file__).parent / "results" / "imagery-issue54.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"summary": summary, "frames_2022": rows}, indent=1) + "\n")
    return 0


def _mtu_range(text: str) -> list[int]:
    lo, _, rest = text.partition("-")
    hi, _, step = rest.partition(":")
    return list(range(int(lo), int(hi or lo) + 1, int(step or 1)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="4 images (3 generated), MTU 64 and 256, every 16th MTU, no layout, stress or packets-only runs")
    ap.add_argument("--mtus", default="64,128,256", help="comma-separated MTUs (default 64,128,256)")
    ap.add_argument("--every-mtu", default=None, metavar="LO-HI[:STEP]",
                    help="MTUs of the 2022 check on every image (default 64-256, every one)")
    ap.add_argument("--no-stress", action="store_true", help="leave out the generated images of the 2022 check")
    ap.add_argument("--no-held-out", action="store_true",
                    help="leave out the held-out frames of the issue 54 check (sand ripples, crops and rescales)")
    ap.add_argument("--stress-mtus", default="64-256:8", metavar="LO-HI[:STEP]",
                    help="MTUs of the 2022 check on the generated images (default 64-256:8)")
    ap.add_argument("--packets-mtu", type=int, default=256,
                    help="MTU of the quarter-frame requests with crops = never, for comparison (0: none)")
    ap.add_argument("--issue54", action="store_true",
                    help="only the issue 54 table (every frame at MTU 64, 128, 256 against 0.95x 2022), each "
                         "frame's worst point checked end to end; writes bench/results/imagery-issue54.json")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=JSON",
                    help="a sender option for every run (e.g. tighten=false, short_fragments=false): what a "
                         "change buys, measured by turning it off")
    ap.add_argument("--out", default=None, help="JSON output (default bench/results/imagery.json, "
                                                 "imagery-issue54.json with --issue54)")
    args = ap.parse_args(argv)
    for item in args.option:
        key, _, value = item.partition("=")
        OPTIONS[key] = json.loads(value)
    if args.issue54:
        return issue54(args)
    if args.out is None:
        args.out = str(Path(__file__).parent / "results" / "imagery.json")
    mtus = [int(v) for v in args.mtus.split(",")]
    if args.quick and args.mtus == "64,128,256":
        mtus = [64, 256]
    every = _mtu_range(args.every_mtu or ("64-256:16" if args.quick else "64-256"))
    packets_mtu = None if args.quick or not args.packets_mtu else args.packets_mtu
    t0 = time.time()
    source, images = load_images(args.quick)
    per_image: list[dict[str, Any]] = []
    runs: list[dict[str, Any]] = []
    rows: list[dict[str, Any]] = []  # the issue 54 table: every frame at TARGET_MTUS
    for name, img in images:
        rec: dict[str, Any] = {"image": name, "base": {}, "bound": {}, "ours": {}, "body": {}, "verified": {},
                               "layout": {}}
        base = baseline_curve(img)
        for x in THRESHOLDS:
            rec["base"][str(x)] = need(base, x)
            rec["bound"][str(x)] = bound(img, x)
        enc = encode(img)
        kinds = {"quarter": quarters(img), "eighth": eighths(img)}
        if args.quick:
            kinds = {"quarter": quarters(img)[:2], "eighth": eighths(img)[:2]}
        pcurve = packet_curve(enc, img, [b for bs in kinds.values() for b in bs])
        curves: dict[int, list[Any]] = {}
        for mtu in sorted({*mtus, *([packets_mtu] if packets_mtu else [])}):
            pts, enc = our_curve(img, mtu, pcurve)
            curves[mtu] = pts
            if mtu not in mtus:
                continue
            rec["layers"] = enc.stream.layers
            ours = [(c, q) for c, q, _, _ in pts]
            rec["ours"][str(mtu)] = {}
            rec["verified"][str(mtu)] = {}
            for x in THRESHOLDS:
                c = need(ours, x)
                rec["ours"][str(mtu)][str(x)] = c
                if c is None:
                    continue
                n, direct = next((nb, q) for cb, q, nb, _ in pts if cb == c and q >= x)
                rec["body"][str(x)] = n
                down, q = verify(img, mtu, n)
                rec["verified"][str(mtu)][str(x)] = {"wire_bytes": down, "psnr": round(q, 3)}
                if down != c or abs(q - direct) > 1e-6:
                    raise AssertionError(f"{name} MTU {mtu}: end to end {down} B / {q:.2f} dB, "
                                         f"expected {c} B / {direct:.2f} dB")
        row, wire54 = table_row(name, "dive" if source == "nui040" else "synthetic", img, base, every, pcurve, enc)
        rec["every_mtu"] = worst_of(wire54, base, every)
        rows.append(row)
        if not args.quick:
            prev = codec.encode_image(img, codec.CodingParams.from_config(PREVIOUS_DEFAULT))
            pn = body_needs(prev, img)
            for x in THRESHOLDS:
                rec["layout"][str(x)] = {"previous": pn[str(x)], "now": rec["body"].get(str(x))}
        mine = region_runs(name, img, enc, curves, kinds, mtus, packets_mtu)
        runs += mine
        per_image.append(rec)
        q30 = [r for r in mine if r["kind"] == "quarter" and r["start"] == "none" and r["quality"] == 30.0
               and r["crops"] == "auto" and r["ratio_to_whole_until_region"] is not None]
        print(f"{name}: 2022 {[rec['base'][str(x)] for x in THRESHOLDS]}  bound {[rec['bound'][str(x)] for x in THRESHOLDS]}"
              f"  body {[rec['body'].get(str(x)) for x in THRESHOLDS]}  "
              + "  ".join(f"MTU {m} {[rec['ours'][str(m)][str(x)] for x in THRESHOLDS]}" for m in mtus)
              + f"  worst/2022 over MTUs {every[0]}..{every[-1]} "
              + str({x: v[:2] for x, v in rec["every_mtu"].items()})
              + f"  quarters to 30 dB: {[round(r['ratio_to_whole_until_region'], 2) for r in q30]}"
              + f"  ({time.time() - t0:.0f} s)", flush=True)

    summary: dict[str, Any] = {"source": source, "images": len(images), "mtus": mtus,
                               "every_mtu": [every[0], every[-1], every[1] - every[0] if len(every) > 1 else 1],
                               "thresholds": [str(x) for x in THRESHOLDS], "per_mtu": {}}
    bound30 = float(np.mean([r["bound"]["30.0"] for r in per_image]))
    body30 = float(np.mean([r["body"]["30.0"] for r in per_image]))
    summary["bound_mean"] = {str(x): float(np.mean([r["bound"][str(x)] for r in per_image])) for x in THRESHOLDS}
    summary["body_mean"] = {str(x): float(np.mean([r["body"][str(x)] for r in per_image])) for x in THRESHOLDS}
    summary["ratio_body_to_bound_30"] = round(body30 / bound30, 4)
    summary["meets_bound_body"] = body30 <= BOUND_SLACK * bound30
    for mtu in mtus:
        e: dict[str, Any] = {"ratio_to_2022": {}, "worst_ratio_to_2022": {}, "worst_image": {}}
        for x in THRESHOLDS:
            ratios = [(r["ours"][str(mtu)][str(x)] / r["base"][str(x)], r["image"]) for r in per_image]
            e["ratio_to_2022"][str(x)] = round(float(np.mean([v for v, _ in ratios])), 4)
            worst = max(ratios)
            e["worst_ratio_to_2022"][str(x)] = round(worst[0], 4)
            e["worst_image"][str(x)] = worst[1]
        wire30 = float(np.mean([r["ours"][str(mtu)]["30.0"] for r in per_image]))
        e["wire_mean_30"] = wire30
        e["ratio_wire_to_bound_30"] = round(wire30 / bound30, 4)
        e["meets_bound_wire"] = wire30 <= BOUND_SLACK * bound30
        summary["per_mtu"][str(mtu)] = e
    worst_all = {x: max(([r["every_mtu"][str(x)][0], r["every_mtu"][str(x)][1], r["image"]] for r in per_image
                         if str(x) in r["every_mtu"]), default=None) for x in THRESHOLDS}
    summary["worst_every_mtu"] = {str(x): v for x, v in worst_all.items()}
    summary["meets_2022_every_image_every_mtu"] = all(v is None or v[0] <= 1.0 for v in worst_all.values())
    if not args.quick:
        lay: dict[str, dict[str, float]] = {}
        for x in THRESHOLDS:
            prev_mean = float(np.mean([r["layout"][str(x)]["previous"] for r in per_image]))
            now_mean = float(np.mean([r["layout"][str(x)]["now"] for r in per_image]))
            lay[str(x)] = {"previous_mean": prev_mean, "now_mean": now_mean, "ratio": round(now_mean / prev_mean, 4)}
        summary["layout"] = lay
        summary["meets_layout"] = all(v["ratio"] <= LAYOUT_SLACK for v in lay.values())
    stress: list[dict[str, Any]] = []
    stress_mtus = _mtu_range(args.stress_mtus)
    extra = [] if args.quick else table_frames(images if source == "nui040" else [], not args.no_stress,
                                               not args.no_held_out)
    for name, group, img in extra:
        base = baseline_curve(img)
        row, wire54 = table_row(name, group, img, base, stress_mtus if group == "bench" else list(TARGET_MTUS))
        rows.append(row)
        if group == "bench":
            stress.append({"image": name, "shape": list(img.shape), "2022": row["2022"],
                           "worst": worst_of(wire54, base, stress_mtus)})
    if stress:
        summary["stress"] = {"images": len(stress), "mtus": [stress_mtus[0], stress_mtus[-1]], "worst": {
            str(x): max(([s["worst"][str(x)][0], s["worst"][str(x)][1], s["image"]] for s in stress
                         if str(x) in s["worst"]), default=None) for x in THRESHOLDS}}
    sets = table_sets(rows)
    summary["target_2022"] = {"limit": TARGET_2022, "mtus": list(TARGET_MTUS), "thresholds": [str(x) for x in THRESHOLDS],
                              "sets": sets, "met": all(v["met"] for v in sets.values())}
    regions = region_summary(runs)
    summary["regions"] = regions
    targets = {}
    for (kind, start, q), limit in REGION_TARGETS.items():
        cells = {m: regions.get(f"{kind}/{start}/{q:g}/{m}") for m in mtus}
        ok = all(c["all_reached"] and c["all_accepted"] for c in cells.values() if c) and all(cells.values())
        sums = {m: c["sum_ratio"] for m, c in cells.items() if c}
        means = {m: c["mean_ratio"] for m, c in cells.items() if c}
        # "on average": the region requests' mean bytes over the whole image's mean bytes (all
        # bytes), at every MTU; the mean of the per-request ratios is reported beside it
        targets[f"{kind} from {start} to {q:g} dB"] = {
            "limit": limit, "all_bytes_ratio_per_mtu": sums, "mean_ratio_per_mtu": means,
            "met": ok and all(v <= limit for v in sums.values()),
            "met_by_mean_of_ratios": ok and all(v is not None and v <= limit for v in means.values())}
    targets["every image <= 2022 at every MTU"] = {"limit": 1.0, "worst": summary["worst_every_mtu"],
                                                   "met": summary["meets_2022_every_image_every_mtu"]}
    targets[f"every frame <= {TARGET_2022} x 2022 at MTU {', '.join(map(str, TARGET_MTUS))} (issue 54)"] = {
        "limit": TARGET_2022, "worst": {k: v["worst"] for k, v in sets.items()}, "met": summary["target_2022"]["met"]}
    summary["targets"] = targets
    summary["meets_targets"] = all(t["met"] for t in targets.values())
    # the issue's "on average" read as the mean of the per-request ratios instead
    summary["meets_targets_by_mean_of_ratios"] = all(t.get("met_by_mean_of_ratios", t["met"])
                                                      for t in targets.values())
    summary["seconds"] = round(time.time() - t0, 1)

    print(f"\nsource: {source}, {len(images)} images; wire = every vehicle-to-ship byte (frame headers, "
          "announce, fragment headers); body = packet data")
    print("mean bytes   " + "  ".join(f"{x:>5.0f} dB" for x in THRESHOLDS))
    print("  2022       " + "  ".join(f"{np.mean([r['base'][str(x)] for r in per_image]):8.0f}" for x in THRESHOLDS))
    print("  bound      " + "  ".join(f"{summary['bound_mean'][str(x)]:8.0f}" for x in THRESHOLDS))
    print("  ours body  " + "  ".join(f"{summary['body_mean'][str(x)]:8.0f}" for x in THRESHOLDS))
    for mtu in mtus:
        print(f"  ours {mtu:>3} B " + "  ".join(
            f"{np.mean([r['ours'][str(mtu)][str(x)] for r in per_image]):8.0f}" for x in THRESHOLDS))
    print(f"\n{'MTU':>4} | ours/2022 mean, worst image (25 / 30 / 35 dB)            | wire/bound 30")
    for mtu in mtus:
        e = summary["per_mtu"][str(mtu)]
        line = "  ".join(f"{e['ratio_to_2022'][str(x)]:.2f} {e['worst_ratio_to_2022'][str(x)]:.2f} "
                         f"({e['worst_image'][str(x)]})" for x in THRESHOLDS)
        print(f"{mtu:>4} | {line} | {e['ratio_wire_to_bound_30']:13.3f}")
    print(f"worst ours/2022 over every MTU {every[0]}..{every[-1]}" + (f" (step {every[1] - every[0]})"
                                                                        if len(every) > 1 and every[1] - every[0] > 1 else "")
          + ": " + ", ".join(f"{x:g} dB {v[0]:.3f} ({v[2]}, MTU {v[1]})" for x, v in worst_all.items() if v))
    if "stress" in summary:
        print(f"generated images ({len(stress)}: small, small with noise, high contrast, synthetic), worst "
              f"ours/2022 over MTUs {args.stress_mtus}: " + ", ".join(f"{x} dB {v[0]:.3f} ({v[2]}, MTU {v[1]})"
                                                        for x, v in summary["stress"]["worst"].items() if v))
    print(f"body / bound at 30 dB (means): {summary['ratio_body_to_bound_30']:.3f}")
    if "layout" in summary:
        print("layout, body now / previous default (means): " + ", ".join(
            f"{x} dB {v['ratio']:.3f}" for x, v in summary["layout"].items()))
    print_table(rows, sets)
    print("\nregions: wire bytes of one region request / the whole image's wire bytes from the same start until "
          "the region is there (mean over requests not there at the start; worst; all bytes)")
    print(f"{'region':8} {'start':8} {'dB':>3} {'MTU':>4} {'way':7} {'n':>3} {'there':>5} {'mean':>6} {'worst':>6} "
          f"{'bytes':>6} {'crops':>5} {'region B':>8} {'whole B':>8} reached")
    for key, c in sorted(regions.items(), key=lambda kv: (kv[0].split("/")[0] != "quarter", kv[0].split("/")[1:3],
                                                          int(kv[0].split("/")[3]), len(kv[0].split("/")))):
        kind, start, qs, mtu_s, *way = key.split("/")
        print(f"{kind:8} {start:8} {qs:>3} {mtu_s:>4} {'packets' if way else 'chosen':7} {c['count']:>3} "
              f"{c['already']:>5} {c['mean_ratio'] if c['mean_ratio'] is not None else '-':>6} "
              f"{c['worst_ratio'] if c['worst_ratio'] is not None else '-':>6} {c['sum_ratio']:>6} {c['crops']:>5} "
              f"{c['mean_wire_bytes']:>8} {c['mean_whole_until_wire'] or '-':>8} {c['all_reached']}")
    print("\ntargets (issue 42):")
    for label, t in targets.items():
        if "worst" in t:
            print(f"  {label}: worst {t['worst']}: {'MET' if t['met'] else 'NOT MET'}")
            continue
        print(f"  {label}: at most {t['limit']}x: all bytes {t['all_bytes_ratio_per_mtu']}: "
              f"{'MET' if t['met'] else 'NOT MET'}; reported, not judged: mean of the requests' ratios "
              f"{t['mean_ratio_per_mtu']} ({'within' if t['met_by_mean_of_ratios'] else 'above'} the limit)")
    print(f"meets every target (regions judged on all bytes): {summary['meets_targets']}; "
          f"the mean of the requests' ratios within every limit: {summary['meets_targets_by_mean_of_ratios']}"
          f"   ({summary['seconds']} s)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"summary": summary, "per_image": per_image, "regions": runs,
                               "stress": stress, "frames_2022": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

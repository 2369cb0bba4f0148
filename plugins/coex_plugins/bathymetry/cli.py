"""``coex bathy``: run the bathymetry modality end to end.

``coex bathy roundtrip POINTS --out DIR [--loss P] [--seed S]`` ingests POINTS (``.npy``,
``.csv`` or a ROS bag), runs the subsea sender and the topside receiver over an in-memory lossy
link with the default policy (plus the receiver's automatic gap filling, and frame acks that
tell the sender what arrived, so subgrids are predicted from what topside holds) until everything has
been sent and every gap repaired, and writes ``DIR/messages.jsonl``, ``DIR/level_<k>.tif`` (and a
``.png`` preview) per level, and ``DIR/summary.json``.

``coex bathy simulate OUT.npy [--size M] [--seed S]`` writes a simulated survey to try it on.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from coex import (
    Bernoulli,
    CoexError,
    ConfigError,
    RoundTrip,
    to_json,
    wire,
)
from coex.messages import (
    MapMetadata,
    MapRoiReply,
    MapRoiRequest,
    Message,
    PredictedSubgrid,
    Subgrid,
    SubgridMessage,
)

from .baseline import size_2022
from .export import find_targets, write_level_geotiff, write_png
from .points import iter_points
from .receiver import BathymetryReceiver
from .sender import BathymetrySender

__all__ = ["register", "roundtrip"]

FRAME_BYTES = 256
LINK_RATE = 100.0


def _level_of(m: Message) -> int | None:
    if isinstance(m, SubgridMessage | MapRoiRequest | MapRoiReply):
        return int(m.level)
    return None


def _record(m: Message, t: float, direction: str) -> dict[str, Any]:
    data = wire.encode(m)
    rec: dict[str, Any] = {"t": t, "dir": direction, "type": type(m).__name__, "level": _level_of(m),
                           "bytes": len(data), "hex": data.hex()}
    if isinstance(m, Subgrid):
        rec.update(ix=m.ix, iy=m.iy, stamp=m.stamp, encoding=m.encoding.name)
    elif isinstance(m, PredictedSubgrid):
        rec.update(ix=m.ix, iy=m.iy, stamp=m.stamp, context=m.context.name, predictor=m.predictor)
    else:
        rec["message"] = {k: v for k, v in to_json(m).items() if k != "type"}
    return rec


def roundtrip(
    points: str | Path,
    out: str | Path,
    *,
    loss: float = 0.0,
    seed: int = 0,
    sender_config: dict[str, Any] | None = None,
    receiver_config: dict[str, Any] | None = None,
    round_seconds: float = 5.0,
    max_rounds: int = 200_000,
) -> dict[str, Any]:
    """Run the round trip and write the outputs; return the summary."""
    if not 0.0 <= loss < 1.0:
        raise ConfigError("--loss must be in [0, 1)")
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    sender = BathymetrySender(sender_config)
    receiver = BathymetryReceiver(receiver_config)
    n_points = 0
    t_data = 0.0
    for t, xyz in iter_points(points, topic=sender.config["topic"]):
        t_data = max(t_data, t or 0.0)
        sender.map.add_points(xyz, t or 0.0)
        n_points += len(xyz)
    sender.map.flush(force=True)
    link = RoundTrip(sender, receiver, mtu=FRAME_BYTES, down=Bernoulli(loss, seed), up=Bernoulli(loss, seed + 1),
                     round_seconds=round_seconds, now=t_data + sender.send_delay, decode=True, rejects=(CoexError,),
                     acks=True)
    rounds = _run(link, sender, receiver, loss, max_rounds)
    records = [_record(e.message, e.now, e.direction) for e in link.events]
    bytes_down = link.events[-1].down_total if link.events else 0
    bytes_up = link.events[-1].wire_total - bytes_down if link.events else 0
    subgrid_bytes, bytes_2022 = _subgrid_sizes(link, sender)
    with (out_dir / "messages.jsonl").open("w") as fh:
        for rec in records:
            fh.write(json.dumps(rec) + "\n")
    levels, candidates = _levels(out_dir, sender, receiver, subgrid_bytes, bytes_2022)
    lat, lon = sender.origin
    sent_all = [b for v in subgrid_bytes.values() for b in v]
    old_all = [b for v in bytes_2022.values() for b in v]
    summary: dict[str, Any] = {
        "points": n_points,
        "accepted": sender.map.accepted,
        "rejected_outliers": sender.map.rejected,
        "dropped": sender.map.dropped,
        "loss": loss,
        "seed": seed,
        "rounds": rounds,
        "simulated_seconds": rounds * round_seconds,
        "messages": len(records),
        "bytes_down": bytes_down,
        "bytes_up": bytes_up,
        "link_seconds_at_100Bps": (bytes_down + bytes_up) / LINK_RATE,
        "subgrids_sent": len(sent_all),
        "mean_subgrid_bytes": float(np.mean(sent_all)) if sent_all else None,
        "mean_subgrid_bytes_2022": float(np.mean(old_all)) if old_all else None,
        "ratio_vs_2022": float(np.sum(sent_all) / np.sum(old_all)) if old_all else None,
        "complete": all(lv["received"] == lv["subgrids"] for lv in levels),
        "levels": levels,
        "candidates": candidates,
        "origin_lat": lat,
        "origin_lon": lon,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    return summary


def _run(link: RoundTrip, sender: BathymetrySender, receiver: BathymetryReceiver, loss: float,
         max_rounds: int) -> int:
    """Step the link until it has been idle three rounds (and topside has the map's metadata,
    when frames may be lost) or ``max_rounds``; return the rounds run."""
    rounds = 0
    idle = 0
    while rounds < max_rounds:
        rounds += 1
        link.step()
        # a region standing for ground not surveyed yet (queued 0, waiting > 0) waits for soundings
        # that never come here (every sounding was in before the first fill): it is not work
        busy = (bool(link.last_fill) or bool(link.last_requests) or sender.pending_bytes() > 0
                or any(not (r.queued == 0 and r.waiting > 0) for r in receiver.active_regions()))
        idle = 0 if busy else idle + 1
        if idle >= 3 and (receiver.metadata is not None or loss == 0.0):
            break
    return rounds


def _subgrid_sizes(link: RoundTrip, sender: BathymetrySender) -> tuple[dict[int, list[int]], dict[int, list[int]]]:
    """Per level, the bytes of each subgrid sent and of the same subgrid in the 2022 coding."""
    subgrid_bytes: dict[int, list[int]] = {}
    bytes_2022: dict[int, list[int]] = {}
    for m in link.sent:
        if isinstance(m, SubgridMessage):
            subgrid_bytes.setdefault(m.level, []).append(wire.encoded_size(m))
            blk = sender.map.block(m.level, m.ix, m.iy)  # every sounding was in before the first fill
            assert blk is not None
            present = blk.count > 0
            q = np.rint(np.where(present, blk.mean, 0.0) / sender.map.vertical_resolution).astype(np.int64)
            bytes_2022.setdefault(m.level, []).append(size_2022(present, q))
    return subgrid_bytes, bytes_2022


def _levels(out_dir: Path, sender: BathymetrySender, receiver: BathymetryReceiver,
            subgrid_bytes: dict[int, list[int]], bytes_2022: dict[int, list[int]],
            ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Each level's summary (writing its GeoTIFF and PNG) and the target candidates of level 0."""
    inventory = sender.inventory()
    levels: list[dict[str, Any]] = []
    lat, lon = sender.origin
    candidates: list[dict[str, Any]] = []
    for k in range(sender.map.levels):
        held = receiver.holdings(k)
        want = {(ix, iy): st for (lv, ix, iy), st in inventory.items() if lv == k}
        info: dict[str, Any] = {
            "level": k, "cell_size": sender.map.resolution * (1 << k), "subgrids": len(want),
            "received": sum(1 for key, st in want.items() if held.get(key) == st),
            "sent": len(subgrid_bytes.get(k, [])),
            "mean_bytes": float(np.mean(subgrid_bytes[k])) if subgrid_bytes.get(k) else None,
            "mean_bytes_2022": float(np.mean(bytes_2022[k])) if bytes_2022.get(k) else None,
        }
        if k in receiver.levels():
            # the GeoTIFF at full resolution, streamed from the receiver's tiles; the PNG and
            # the candidates from its drawn overview (the level itself while it is small)
            write_level_geotiff(out_dir / f"level_{k}.tif", receiver, k, origin_lat=lat, origin_lon=lon)
            prod = receiver.level_product(k)
            cell = float(prod.cell_size)
            write_png(out_dir / f"level_{k}.png", prod.data, cell)
            info["tif"] = f"level_{k}.tif"
            if k == 0:
                candidates = [c.to_dict() for c in find_targets(prod.data, cell=cell, x0=prod.x0,
                                                                y0=prod.y0)[:20]]
        levels.append(info)
    return levels, candidates


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, float) and math.isnan(o):
        return None
    raise TypeError(type(o).__name__)


def _cmd_roundtrip(args: argparse.Namespace) -> int:
    cfg: dict[str, Any] = {}
    if args.topic:
        cfg["topic"] = args.topic
    if args.origin:
        cfg["origin_lat"], cfg["origin_lon"] = args.origin
    if args.no_outlier_rejection:
        cfg["outlier_rejection"] = False
    summary = roundtrip(args.points, args.out, loss=args.loss, seed=args.seed, sender_config=cfg)
    print(f"{summary['points']} points ({summary['rejected_outliers']} outliers rejected), "
          f"{summary['subgrids_sent']} subgrids sent, mean {summary['mean_subgrid_bytes'] or 0:.1f} B "
          f"(2022: {summary['mean_subgrid_bytes_2022'] or 0:.1f} B), "
          f"{summary['link_seconds_at_100Bps']:.0f} s of link at 100 B/s, complete: {summary['complete']}")
    for c in summary["candidates"][:5]:
        print(f"  candidate target at ({c['x']:.1f}, {c['y']:.1f}) m, {c['height']:.1f} m high, {c['cells']} cells")
    print(f"wrote {args.out}/messages.jsonl, level_<k>.tif, summary.json")
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .sim import Seafloor, simulate_survey

    floor = Seafloor.default(size=args.size, seed=args.seed)
    survey = simulate_survey(floor, seed=args.seed + 1, beams=args.beams)
    np.save(args.out, survey.points.astype(np.float32))
    print(f"wrote {len(survey)} soundings to {args.out}")
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("bathy", help="bathymetry: quadtree map, subgrids, round trip")
    sub = p.add_subparsers(dest="bathy_command", metavar="ACTION", required=True)
    r = sub.add_parser("roundtrip", help="send a point cloud through sender, lossy link and receiver")
    r.add_argument("points", metavar="POINTS", help=".npy / .csv (x, y, z) or a ROS 1/2 bag with PointCloud2")
    r.add_argument("--out", required=True, metavar="DIR", help="output directory")
    r.add_argument("--loss", type=float, default=0.0, metavar="P", help="frame loss probability (0..1)")
    r.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the link's loss")
    r.add_argument("--topic", default=None, help="PointCloud2 topic in a bag (default: all)")
    r.add_argument("--origin", type=float, nargs=2, metavar=("LAT", "LON"), help="origin of the local frame")
    r.add_argument("--no-outlier-rejection", action="store_true", help="keep every sounding")
    r.set_defaults(func=_cmd_roundtrip)
    s = sub.add_parser("simulate", help="write a simulated multibeam survey (.npy)")
    s.add_argument("out", metavar="OUT.npy")
    s.add_argument("--size", type=float, default=256.0, help="side of the surveyed square (m)")
    s.add_argument("--beams", type=int, default=256)
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=_cmd_simulate)


_ = MapMetadata

"""``coex replay --lcm-log FILE [--out DIR] [--channel REGEX] [--json]``: re-analyse a recorded dive.

Reads an ``lcm-logger`` log, routes every CoEx message to the topside receiver of its modality
and prints a summary; with ``--out`` also writes ``summary.json``, exportable products and
``decoded.lcmlog`` (see :mod:`coex_transports.lcm.replay`). Exit code 0 when the log held at
least one CoEx frame, 1 when it held none, 2 on an error (missing or unreadable log).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

__all__ = ["register", "run_replay"]


def register(sub: Any) -> None:
    p = sub.add_parser(
        "replay",
        help="replay an lcm-logger log of a CoEx session into the topside receivers",
        description=(
            "Read an lcm-logger log, give every CoEx message to the topside receiver of its "
            "modality and print a summary; with --out also write summary.json, exportable "
            "products (products/<modality>/...) and decoded.lcmlog (coex.vehicle_status_t and "
            "coex.map_level_t events). Exit code 0 when the log held at least one CoEx frame, "
            "1 when it held none, 2 on an error."
        ),
    )
    p.add_argument("--lcm-log", required=True, metavar="FILE", help="log written by lcm-logger")
    p.add_argument("--out", metavar="DIR", help="write summary.json, products and decoded.lcmlog here")
    p.add_argument("--channel", metavar="REGEX",
                   help="only channels matching this regular expression (default: every coex.frame_t)")
    p.add_argument("--json", action="store_true", help="print the whole summary as JSON")
    p.set_defaults(func=run_replay)


def _text(summary: dict[str, Any]) -> str:
    lines = [
        f"log {summary['log']}: {summary['events']} events, {summary['frames']} CoEx frames "
        f"({summary['frame_bytes']} B), {summary['messages']} messages, "
        f"{summary['bad_events']} bad, {summary['duration_s']:.1f} s",
    ]
    if summary["channels"]:
        lines.append("channels: " + ", ".join(f"{k} ({v})" for k, v in summary["channels"].items()))
    if summary["messages_by_type"]:
        lines.append("messages: " + ", ".join(f"{k} {v}" for k, v in summary["messages_by_type"].items()))
    for name in summary["modalities"]:
        products = summary["products"].get(name, [])
        lines.append(f"modality {name}: {summary['routed'].get(name, 0)} messages, {len(products)} products")
    for name, why in summary["unavailable"].items():
        lines.append(f"modality {name}: unavailable ({why})")
    if summary["unrouted"]:
        lines.append("not routed: " + ", ".join(f"{k} {v}" for k, v in summary["unrouted"].items()))
    status = summary["vehicle_status"]
    if status:
        lines.append(
            f"last vehicle status: stamp {status['stamp']} x {status['x']} y {status['y']} "
            f"depth {status['depth']} mode {status['mode']}"
        )
    for level in summary["map_levels"]:
        lines.append(
            f"map level {level['level']}: {level['subgrids']} subgrids, {level['cells']} cells, "
            f"x {level['x_min']}..{level['x_max']} y {level['y_min']}..{level['y_max']}"
        )
    if summary["files"]:
        lines.append("wrote: " + ", ".join(summary["files"]))
    return "\n".join(lines)


def run_replay(args: argparse.Namespace) -> int:
    from .replay import replay_log

    summary = replay_log(args.lcm_log, args.out, channel=args.channel)
    print(json.dumps(summary, indent=2, default=str) if args.json else _text(summary))
    return 0 if summary["frames"] else 1

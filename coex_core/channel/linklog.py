"""The link log: one JSON object per line per packet and receiver.

Fields: ``time`` (transmission start), ``link``, ``slot``, ``src``, ``dst``, ``rate``, ``frames``,
``capacity_bytes`` (frames x frame size), ``used_bytes`` (bytes of the frames as sent),
``delivered`` (per frame), ``delivered_bytes``, ``lost`` (frames lost) and ``cause``. A
runner's own ``sent`` record adds ``spare_bytes`` and ``redundant_bytes`` (of ``used_bytes``:
spare-tier messages and extra copies of urgent ones) and ``backlog_bytes`` (work left after the
packet, see ``Transmission``). The
simulated channel (:meth:`coex_core.acoustic.AcousticChannel.log`) produces the records; the
runner writes them. Nothing here touches a file: callers pass text in and out.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

__all__ = ["LINK_LOG_FIELDS", "link_record", "read_link_log", "to_json_line"]

LINK_LOG_FIELDS = ("time", "link", "slot", "src", "dst", "rate", "frames", "capacity_bytes",
                   "used_bytes", "delivered", "delivered_bytes", "lost", "cause")


def link_record(**fields: Any) -> dict[str, Any]:
    """A record with every field of :data:`LINK_LOG_FIELDS` (missing ones ``None``)."""
    rec: dict[str, Any] = {k: fields.get(k) for k in LINK_LOG_FIELDS}
    rec.update(fields)
    return rec


def to_json_line(record: dict[str, Any]) -> str:
    """One record as a JSON line (with the trailing newline)."""
    return json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n"


def read_link_log(lines: Iterable[str]) -> list[dict[str, Any]]:
    """Parse JSON lines (blank lines skipped)."""
    return [json.loads(line) for line in lines if line.strip()]

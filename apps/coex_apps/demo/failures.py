"""What went wrong in a dive, counted (``metrics.json`` ``failures``), and the judging radius of
an object (the referee's, from the truth)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from coex import Runner

from .config import IDENTIFY_RADIUS

__all__ = ["failure_counts", "identify_radius"]


def failure_counts(runners: Mapping[int, Runner]) -> dict[str, Any]:
    """Per node and in total: the frames a node rejected (``rejected_frames``: undecodable, or
    failing authentication), the messages it refused (``rejected_messages``: a request out of
    bounds, a failing handler), its senders' failures (``sender_failures``: a sender that raised
    or overran its deadline while filling a packet, or whose hooks raised) and its runner's
    errors (``runner_errors``: a transport or store error the loop went on from). A clean dive
    has none (the demo's tests hold it); ``sender_failures_by_stream`` names each failing
    sender's stream."""
    per: dict[str, dict[str, Any]] = {}
    for node_id, runner in sorted(runners.items()):
        node = runner.node
        stats = node.stats
        mgr = node.manager.stats
        per[str(node_id)] = {
            "rejected_frames": int(stats.get("bad_frames", 0)) + int(stats.get("unauthenticated", 0)),
            "rejected_messages": int(stats.get("rejected", 0)),
            "sender_failures": int(mgr.get("sender_failures", 0)),
            "sender_failures_by_stream": dict(getattr(node.manager, "sender_failures_by_stream", {}) or {}),
            "runner_errors": int(getattr(runner, "error_count", 0)),
        }
    total = {k: sum(v[k] for v in per.values())
             for k in ("rejected_frames", "rejected_messages", "sender_failures", "runner_errors")}
    return {**total, "nodes": per}


def identify_radius(obj: Any) -> float:
    """How close (m) a candidate of the received map must lie to an object to be of it: the
    demo's :data:`~coex_apps.demo.config.IDENTIFY_RADIUS`, or half the object's length for one
    longer than twice that (a container, a hull)."""
    return max(IDENTIFY_RADIUS, float(getattr(obj, "length", 0.0)) / 2.0)

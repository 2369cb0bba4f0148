"""What the dive achieved, judged against the simulation's truth: metrics.json, the report, the
map exports and decisions.csv."""

from __future__ import annotations

import contextlib
import csv
import json
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from coex import ConfigError, Runner
from coex_plugins.bathymetry import (
    BathymetryReceiver,
    write_geotiff,
    write_level_geotiff,
    write_png,
)
from coex_plugins.bathymetry.sender import BathymetrySender
from coex_plugins.bathymetry.sim import Seafloor, Target
from coex_plugins.detections import DetectionsSender
from coex_plugins.imagery import ImageryReceiver
from coex_plugins.timeseries import TimeSeriesReceiver

from .config import EPOCH, TOPSIDE, VEHICLE, Decision, DemoConfig, DemoResult
from .failures import identify_radius
from .operator import MIN_SCORE, NEAR, Operator
from .scenario import Scenario
from .truth import FrameTruth, judge


@dataclass
class World:
    """What the simulation knows, handed to the judging."""

    scenario: Scenario
    floor: Seafloor
    cars: tuple[Target, ...]
    rocks: tuple[Target, ...]
    survey_end: float
    frames: dict[float, FrameTruth]
    received_track: list[tuple[float, float]]
    camera_times: list[float]
    operator: str
    #: the legs the vehicle really flew with its camera on (``Leg``: t0, t1, p0, p1)
    camera_legs: list[Any] = field(default_factory=list)
    #: the vehicle's side of every survey command, by survey id (``Autonomy.summary``)
    surveys: dict[int, dict[str, Any]] = field(default_factory=dict)
    #: one entry per vehicle (node id, role, what it did: :func:`vehicle_summary`); one in a
    #: single-vehicle dive, two in a fleet dive
    vehicles: list[dict[str, Any]] = field(default_factory=list)

    def visited(self, x: float, y: float) -> bool:
        """Whether the camera really flew within :data:`~.operator.NEAR` metres of (x, y)."""
        for leg in self.camera_legs:
            (ax, ay), (bx, by) = leg.p0, leg.p1
            dx, dy = bx - ax, by - ay
            seg = dx * dx + dy * dy
            f = 0.0 if seg == 0 else min(max(((x - ax) * dx + (y - ay) * dy) / seg, 0.0), 1.0)
            if math.hypot(ax + f * dx - x, ay + f * dy - y) <= NEAR:
                return True
        return False


def _judge(world: World, operator: Operator, bytes_of: Callable[[int], int | None],
           cycle: float) -> tuple[list[dict[str, Any] | None], list[dict[str, Any]]]:
    """Every confirmation the operator made, judged against the truth by the referee
    (:func:`~coex_apps.demo.truth.judge`: the object the eye pointed at, a real target, shown
    faithfully): per true target the first confirmation that shows it, and the confirmations
    that show no target."""
    per_target: list[dict[str, Any] | None] = [None] * len(world.cars)
    false: list[dict[str, Any]] = []
    confirmed = sorted((c for c in operator.candidates if c.confirmed), key=lambda c: c.confirmed_at or 0.0)
    for c in confirmed:
        truth = world.frames.get(c.evidence_time) if c.evidence_time is not None else None
        shown = judge(c.evidence, truth, c.evidence_box) if (c.evidence is not None and truth is not None) else []
        hit = [k for kind, k in shown if kind == "target"]
        assert c.confirmed_at is not None and c.verdict_image is not None
        record = {"image_id": c.verdict_image,
                  "image_time_s": None if c.evidence_time is None else round(c.evidence_time - EPOCH, 1),
                  "image_x": c.evidence_xy[0] if c.evidence_xy else None,
                  "image_y": c.evidence_xy[1] if c.evidence_xy else None,
                  "confirmed_at_s": round(c.confirmed_at - EPOCH, 1),
                  "bytes": c.evidence_bytes,
                  "requested_at_s": None if c.request_at is None else round(c.request_at - EPOCH, 1),
                  "first_requested_at_s": None if c.first_request_at is None else round(c.first_request_at - EPOCH, 1),
                  "tdma_cycles": None if c.request_at is None else round((c.confirmed_at - c.request_at) / cycle, 2),
                  "tdma_cycles_from_first_request": None if c.first_request_at is None
                  else round((c.confirmed_at - c.first_request_at) / cycle, 2),
                  "candidate": {"x": c.x, "y": c.y}, "verdict": c.verdict, "sight": c.evidence_sight}
        if hit:
            for k in hit:
                if per_target[k] is None:
                    per_target[k] = record
        else:
            others = [f"decoy {k + 1} ({world.rocks[k].kind})" for kind, k in shown if kind == "decoy"]
            false.append({"x": c.x, "y": c.y, "image_id": c.verdict_image, "verdict": c.verdict,
                          "confirmed_at_s": record["confirmed_at_s"],
                          "shows": ", ".join(others) or "no target (sand, or too little of one, or not faithfully "
                                                        "enough, or not where the eye pointed)"})
    return per_target, false


def _detections(receivers: dict[str, Any], runners: dict[int, Runner],
                truth_near: Callable[[float, float], str]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """What the vehicle's detectors suggested, as topside received it and judged against the
    truth (what really lies within the identify radius of each), and what it cost on the link: the
    Detection messages the vehicle sent (every version and re-send) and the 1 m subgrids it sent
    around them."""
    rx = receivers.get("detections")
    rows = rx.rows() if rx is not None else []
    out = []
    for r in rows:
        out.append({"id": r["id"], "source": r["source"], "x": r["x"], "y": r["y"], "score": r["score"],
                    "height": r["height"], "length": r["length"], "width": r["width"],
                    "orientation": r["orientation"], "footprint": r["footprint"], "image_id": r["image_id"],
                    "first_at_s": round(r["first_at"] - EPOCH, 1), "updated_at_s": round(r["updated_at"] - EPOCH, 1),
                    "bytes_received": r["bytes"], "truth": truth_near(r["x"], r["y"])})
    vehicle = runners[VEHICLE].node
    cost: dict[str, Any] = {"received": len(out),
                            "true": sum(1 for d in out if d["truth"].startswith("target")),
                            "decoys": sum(1 for d in out if d["truth"].startswith("decoy")),
                            "false": sum(1 for d in out if d["truth"] == "none"),
                            "bytes_received": sum(d["bytes_received"] for d in out)}
    with contextlib.suppress(ConfigError):
        det = vehicle.sender("detections")
        cost["bytes_sent"] = int(det.bytes_sent) if isinstance(det, DetectionsSender) else 0
    with contextlib.suppress(ConfigError):
        bathy = vehicle.sender("bathymetry")
        cost["neighbourhood_bytes_sent"] = int(bathy.focus_bytes) if isinstance(bathy, BathymetrySender) else 0
    return out, cost


def _why_not(i: int, world: World, operator: Operator, visible: float | None) -> str:
    """Why target ``i`` was not confirmed, from the truth."""
    car = world.cars[i]
    near = [c for c in operator.candidates if math.hypot(c.x - car.x, c.y - car.y) <= identify_radius(car)]
    shown = sorted(ft.time for ft in world.frames.values() if ft.visible.get(i + 1, 0.0) >= 0.15)
    if shown:
        return (f"photographed ({len(shown)} frames from {shown[0] - EPOCH:.0f} s), but no received image of it "
                "was confirmed")
    if visible is None:
        return "never photographed: never identifiable in the received 1 m map"
    if world.operator == "none":
        return "never photographed: never visited with the camera (no operator retargeted the vehicle)"
    refused = [c.refused for c in near if c.refused]
    if refused and not any(c.planned for c in near):
        return f"never photographed: the vehicle did not fly the camera line over it ({refused[0]})"
    if not any(c.planned for c in near):
        return ("never photographed: identifiable at 1 m but never visited with the camera (ranked too low, "
                "or no camera time left)")
    return "never photographed: visited, but no camera frame showed enough of it"


#: ``map_coverage_after_survey`` is the map this long after the last survey ping (the issue's
#: "every level at least 99.5 % complete within ten minutes of the end of the survey")
AFTER_SURVEY_S = 600.0


def _regions(out: Path, rx: ImageryReceiver, operator: Operator, metas: dict[int, dict[str, Any]]
             ) -> list[dict[str, Any]]:
    """Every image region asked during the dive, as topside knows it: the image, the box, the
    goal, the vehicle's answer and how it served it (a crop, or the image's packets), the bytes
    that brought it (a crop's body held, or the region's packets) and the layers complete inside
    it; ``file``: the image as shown topside with the box outlined (``images/region_<image>_<command>.png``),
    ``crop_file``: what the crop shows (``images/crop_<id>.png``, written by the receiver)."""
    from coex_plugins.imagery.output import outlined, write_png

    script = {r["command_id"]: r for r in operator.regions}
    rows = []
    for image_id, meta in sorted(metas.items()):
        for reg in meta.get("regions") or ():
            cid = int(reg["command_id"])
            crop = reg.get("crop")
            row: dict[str, Any] = {
                "image_id": image_id, "command_id": cid, "box": [int(v) for v in reg["box"]],
                "goal": {"kind": reg["kind"], "value": reg["value"]}, "state": reg["state"],
                "served": reg.get("served"), "bytes": reg.get("bytes"),
                "layers_complete": reg.get("layers_complete"), "layers": meta.get("layers"),
                "asked_s": round(float(reg["time"]) - EPOCH, 1), "by": "script" if cid in script else "console",
                "candidate": list(script[cid]["candidate"]) if cid in script else None,
                "image_bytes": int(meta["bytes_used"]), "image_total_bytes": int(meta["total_bytes"]),
                "crop": None if not crop else {k: crop[k] for k in ("image_id", "width", "height", "total_bytes",
                                                                    "held_bytes", "complete", "shown", "base",
                                                                    "cover")},
            }
            shown = rx.image(image_id)
            if shown is not None:
                name = f"images/region_{image_id:04d}_{cid:03d}.png"
                write_png(out / name, outlined(shown, row["box"]))
                row["file"] = name
            if crop and (out / "images" / f"crop_{int(crop['image_id']):04d}.png").exists():
                row["crop_file"] = f"images/crop_{int(crop['image_id']):04d}.png"
            rows.append(row)
    return sorted(rows, key=lambda r: r["asked_s"])


def finish(out: Path, cfg: DemoConfig, world: World, operator: Operator, receivers: dict[str, Any],
            coverage: dict[int, list[tuple[float, float]]], visible_at: dict[int, float],
            decisions: list[Decision], wall: float, runners: dict[int, Runner],
            responses: dict[str, Any] | None = None, navigation: dict[str, Any] | None = None) -> dict[str, Any]:
    """The dive judged against the truth: the map exports and figures, truth.json, the time
    series, metrics.json, the report and decisions.csv in ``out``; returns the metrics.
    ``navigation``: the navigation's metrics (issue 56), in metrics.json and the report."""
    scn = world.scenario
    names = _truth_names(world)

    def truth_near(x: float, y: float) -> str:
        return _truth_near(world, names, x, y)

    candidates = _candidate_rows(operator, world, truth_near)
    det_rx = receivers.get("detections")
    det_rows = det_rx.rows() if det_rx is not None else []
    map_svgs = _map_exports(out, receivers["bathymetry"], world, candidates, det_rows)
    _write_truth(out, world)
    ts: TimeSeriesReceiver = receivers["timeseries"]
    ts.to_csv(out / "timeseries.csv")
    img: ImageryReceiver = receivers["imagery"]
    metas = {int(p.meta["image_id"]): dict(p.meta) for p in img.products() if p.kind == "image"}

    def bytes_of(image_id: int) -> int | None:
        m = metas.get(image_id)
        return None if m is None else int(m["bytes_used"])

    per_target, false = _judge(world, operator, bytes_of, scn.cycle)
    link = _link_summary(out / "link.jsonl")
    detections, detection_cost = _detections(receivers, runners, truth_near)
    targets = _target_rows(world, operator, names, per_target, detections, visible_at)
    images = _image_rows(out, metas, targets, operator)
    regions = _regions(out, img, operator, metas)
    success, goals = _goals(targets, false, world)
    metrics: dict[str, Any] = {
        "scenario": scn.to_dict(),
        # the key itself never goes into the outputs
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()
                   if k not in ("command_key", "scenario")},
        "operator": world.operator,
        "summary": _summary(targets, false, world.operator, goals),
        "success": success,
        "wall_seconds": round(wall, 1),
        "dive_seconds": scn.duration,
        "survey_end_s": round(world.survey_end - EPOCH, 1),
        "tdma_cycle_s": scn.cycle,
        "targets": targets,
        "false_confirmations": false,
        "false_confirmation_count": len(false),
        "verdicts": _verdicts(operator, truth_near, world),
        "decoys": [{"name": f"decoy {i + 1}", "kind": t.kind, "x": t.x, "y": t.y,
                    "visited": world.visited(t.x, t.y)}
                   for i, t in enumerate(world.rocks)],
        "surveys": _surveys(receivers["survey"], operator, world.surveys),
        "candidates": candidates,
        "detections": detections,
        "detection_cost": detection_cost,
        "images_received": len(metas),
        "regions": regions,
        "images_captured": len(world.camera_times),
        "link": link,
        "map_coverage": {str(k): v[-1][1] if v else 0.0 for k, v in coverage.items()},
        "map_coverage_after_survey": {
            str(k): max((f for t, f in v if t <= world.survey_end - EPOCH + AFTER_SURVEY_S), default=0.0)
            for k, v in coverage.items()},
        "responses": responses,
        "decision_time_s": _decision_summary(targets),
        "vehicles": world.vehicles,
        "bad_frames": {"topside": runners[TOPSIDE].node.stats.get("bad_frames", 0),
                       "vehicle": runners[VEHICLE].node.stats.get("bad_frames", 0)},
        "goals": goals,
    }
    charts = _charts(world, coverage, visible_at, link, decisions)
    for k in ("capacity_series", "used_series", "delivered_series"):
        link.pop(k, None)
    if navigation is not None:
        metrics["navigation"] = navigation
    _write_outputs(out, metrics, charts, map_svgs, images, decisions, regions)
    return metrics


def _truth_names(world: World) -> dict[tuple[str, int], str]:
    """Each true object's name in the outputs: ``target 1``, ``decoy 2 (boulder)``."""
    names = {("target", i): f"target {i + 1}" for i in range(len(world.cars))}
    names.update({("decoy", k): f"decoy {k + 1} ({o.kind})" for k, o in enumerate(world.rocks)})
    return names


def _truth_near(world: World, names: dict[tuple[str, int], str], x: float, y: float) -> str:
    """The true object at (x, y) (within its identification radius), or ``none``."""
    for key, objs in (("target", world.cars), ("decoy", world.rocks)):
        for k, o in enumerate(objs):
            if math.hypot(o.x - x, o.y - y) <= identify_radius(o):
                return names[(key, k)]
    return "none"


def _candidate_rows(operator: Operator, world: World, truth_near: Callable[[float, float], str],
                    ) -> list[dict[str, Any]]:
    """The operator's candidates worth a look (best first), each with its rank, whether the
    camera flew over it and what is really there."""
    ranked = operator.ranked()
    rank_of = {id(c): r for r, c in enumerate(ranked, 1)}
    return [{"x": c.x, "y": c.y, "height": c.height, "cells": c.cells, "length": c.length, "width": c.width,
             "score": c.score, "detection": c.detection, "measured_topside": c.measured,
             "rank": rank_of.get(id(c)), "visited": world.visited(c.x, c.y),
             "survey_id": c.survey_id, "refused": c.refused, "verdict": c.verdict or None,
             "truth": truth_near(c.x, c.y)}
            for c in sorted(operator.candidates, key=lambda c: -c.score) if c.score >= MIN_SCORE]


def _map_exports(out: Path, bathy: BathymetryReceiver, world: World, candidates: list[dict[str, Any]],
                 det_rows: list[dict[str, Any]]) -> list[str]:
    """Each received map level as a GeoTIFF (full resolution) and a PNG in ``out/map``; the
    figures of levels 0 to 3 over the survey box (level 0 with the candidates and detections)."""
    from .figures import map_figure

    floor = world.floor
    map_svgs: list[str] = []
    for level in range(0, 6):
        try:
            p = bathy.level_product(level)
        except Exception:
            continue
        if p.data is None or not np.isfinite(np.asarray(p.data, float)).any():
            continue
        meta = dict(p.meta)
        cell, x0, y0 = float(meta["cell_size"]), float(meta["x0"]), float(meta["y0"])
        grid = np.asarray(p.data, float)
        # the GeoTIFF at full resolution, streamed from the receiver's tiles; the PNG and the
        # figures from its drawn level
        write_level_geotiff(out / "map" / f"level_{level}.tif", bathy, level,
                            origin_lat=float(meta.get("origin_lat", 0.0)),
                            origin_lon=float(meta.get("origin_lon", 0.0)))
        write_png(out / "map" / f"level_{level}.png", grid, cell=cell)
        if level <= 3:
            # the survey box (and a margin), not the whole quadtree
            sub, sx0, sy0 = _crop(grid, cell, x0, y0, floor.x0 - 8, floor.y0 - 8, floor.x0 + floor.size + 8,
                                  floor.y0 + floor.size + 8)
            map_svgs.append(map_figure(
                sub, cell=cell, x0=sx0, y0=sy0,
                title=f"Level {level}: {cell:g} m cells, as received topside",
                track=world.received_track,
                targets=[{"x": t.x, "y": t.y, "label": f"target {i + 1}"} for i, t in enumerate(world.cars)],
                decoys=[{"x": t.x, "y": t.y, "label": f"decoy {i + 1} ({t.kind})"} for i, t in enumerate(world.rocks)],
                candidates=[{"x": c["x"], "y": c["y"], "label": f"#{c['rank']}", "visited": c["visited"]}
                            for c in candidates if c["rank"] is not None] if level == 0 else [],
                detections=[{"x": d["x"], "y": d["y"], "label": f"D{d['id']}"} for d in det_rows] if level == 0 else []))
    return map_svgs


def _write_truth(out: Path, world: World) -> None:
    """The ground truth: the seafloor at 1 m (truth.tif) and the objects (truth.json)."""
    floor = world.floor
    xs = np.arange(0.5, floor.size, 1.0) + floor.x0
    ys = np.arange(0.5, floor.size, 1.0) + floor.y0
    gx, gy = np.meshgrid(xs, ys)
    write_geotiff(out / "truth.tif", floor.elevation(gx, gy), x0=floor.x0, y0=floor.y0, cell=1.0)  # row 0 = south
    (out / "truth.json").write_text(json.dumps({
        "seafloor": {"size_m": floor.size, "depth_m": floor.depth, "seed": floor.seed, "cell_m": 1.0},
        "targets": [{"name": f"target {i + 1}", "kind": t.kind, **_obj(t)} for i, t in enumerate(world.cars)],
        "decoys": [{"name": f"decoy {i + 1}", "kind": t.kind, **_obj(t)} for i, t in enumerate(world.rocks)],
    }, indent=2))


def _target_rows(world: World, operator: Operator, names: dict[tuple[str, int], str],
                 per_target: list[dict[str, Any] | None], detections: list[dict[str, Any]],
                 visible_at: dict[int, float]) -> list[dict[str, Any]]:
    """One row per true target (the results JSON's): when it became identifiable topside, its
    first detection, its confirmation and the decision times (or why it was not confirmed)."""
    targets: list[dict[str, Any]] = []
    for i, t in enumerate(world.cars):
        seen = visible_at.get(i)
        conf = per_target[i]
        first = min((d for d in detections if d["truth"] == names[("target", i)]),
                    key=lambda d: d["first_at_s"], default=None)
        targets.append({"name": f"target {i + 1}", "kind": t.kind, "length": t.length, "x": t.x, "y": t.y,
                        "heading": t.heading,
                        "identifiable_at_1m_s": None if seen is None else round(seen - EPOCH, 1),
                        "before_survey_end": seen is not None and seen <= world.survey_end,
                        "first_detection": None if first is None else {
                            "id": first["id"], "first_at_s": first["first_at_s"], "score": first["score"]},
                        "confirmation": conf,
                        # issue 43's decision time: from identifiable at 1 m topside to the
                        # confirming image (negative: confirmed from a detection before the
                        # received 1 m map showed it)
                        "decision_time_s": None if seen is None or conf is None
                        else round(conf["confirmed_at_s"] - (seen - EPOCH), 1),
                        "detection_to_confirmation_s": None if first is None or conf is None
                        else round(conf["confirmed_at_s"] - first["first_at_s"], 1),
                        "why_not": None if conf is not None else _why_not(i, world, operator, seen)})
    return targets


def _image_rows(out: Path, metas: dict[int, dict[str, Any]], targets: list[dict[str, Any]],
                operator: Operator) -> list[dict[str, Any]]:
    """The received images written out (in time order): what each confirms, whether the
    operator asked for it."""
    confirming = {c["image_id"]: t["name"] for t in targets if (c := t["confirmation"]) is not None}
    requested = {i for c in operator.candidates for i in c.looked + ([c.image_id] if c.image_id is not None else [])}
    return [{"file": f"images/image_{i:04d}.png", "image_id": i, "time_s": round(float(m["time"]) - EPOCH, 1),
             "x": m.get("x"), "y": m.get("y"), "bytes": int(m["bytes_used"]), "layers": int(m["layers_complete"]),
             "confirms": confirming.get(i), "requested": i in requested}
            for i, m in sorted(metas.items(), key=lambda kv: float(kv[1]["time"]))
            if (out / "images" / f"image_{i:04d}.png").exists()]


def _goals(targets: list[dict[str, Any]], false: list[dict[str, Any]], world: World,
           ) -> tuple[bool, dict[str, Any]]:
    """The dive's three goals, each met or not with its detail; and its success (every target
    confirmed, nothing else)."""
    all_identifiable = all(t["before_survey_end"] for t in targets)
    all_confirmed = all(t["confirmation"] is not None for t in targets)
    success = all_confirmed and not false
    cycles = [t["confirmation"]["tdma_cycles"] for t in targets if t["confirmation"] is not None]
    fast = success and all(c is not None and c <= 2.0 for c in cycles)
    none_text = "no targets in this scenario" if not targets else ""
    goals = {
        "every target identifiable topside at 1 m before the survey ends": {
            "met": all_identifiable,
            "detail": "; ".join(
                f"{t['name']} at ({t['x']:.0f}, {t['y']:.0f}): "
                + (f"identifiable at {t['identifiable_at_1m_s']:.0f} s" if t["identifiable_at_1m_s"] is not None
                   else "never identifiable") for t in targets) or none_text
            + f"; survey ended at {world.survey_end - EPOCH:.0f} s",
        },
        "every target confirmed by a received image that shows it, and nothing else confirmed": {
            "met": success,
            "detail": "; ".join(
                f"{t['name']}: " + (f"image {t['confirmation']['image_id']} at {t['confirmation']['confirmed_at_s']:.0f} s"
                                    if t["confirmation"] else f"NOT confirmed ({t['why_not']})") for t in targets)
            + (f"; {len(false)} false confirmation(s): " + "; ".join(
                f"({f['x']:.0f}, {f['y']:.0f}) by image {f['image_id']}, which shows {f['shows']}" for f in false)
               if false else "; no false confirmation"),
        },
        "each confirming image within two TDMA cycles of its request": {
            "met": fast,
            "detail": "; ".join(f"{t['name']}: {t['confirmation']['tdma_cycles']} cycles" if t["confirmation"]
                                else f"{t['name']}: not confirmed" for t in targets) or none_text,
        },
    }
    return success, goals


def _charts(world: World, coverage: dict[int, list[tuple[float, float]]], visible_at: dict[int, float],
            link: dict[str, Any], decisions: list[Decision]) -> list[str]:
    """The report's charts: the map filling in, the link's use against its capacity, the
    decisions on a timeline."""
    from .figures import line_chart, timeline_chart

    scn = world.scenario
    return [
        line_chart({f"level {k} ({2**k} m)": v for k, v in sorted(coverage.items())},
                   title="Map filling in over time (fraction of the site's surveyed cells held topside)",
                   xlabel="dive time (s)", ylabel="fraction",
                   markers=[(world.survey_end - EPOCH, "survey ends")] + [
                       (v - EPOCH, f"target {i + 1} identifiable at 1 m") for i, v in visible_at.items()]),
        line_chart({"capacity": link["capacity_series"], "used": link["used_series"],
                    "delivered": link["delivered_series"]},
                   title="Link use against capacity (cumulative bytes, vehicle to topside)",
                   xlabel="dive time (s)", ylabel="bytes"),
        timeline_chart([{"t": d.t, "kind": d.kind, "text": d.text} for d in decisions], t_end=scn.duration),
    ]


def _write_outputs(out: Path, metrics: dict[str, Any], charts: list[str], map_svgs: list[str],
                   images: list[dict[str, Any]], decisions: list[Decision], regions: list[dict[str, Any]]) -> None:
    """The report, metrics.json and decisions.csv."""
    from .report import write_report

    write_report(out, metrics, charts=charts, maps=map_svgs, images=images,
                 decisions=[asdict(d) for d in decisions], regions=regions)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    with (out / "decisions.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dive_time_s", "who", "kind", "text"])
        for d in decisions:
            w.writerow([d.t, d.who, d.kind, d.text])


def _verdicts(operator: Operator, truth_near: Callable[[float, float], str], world: World) -> dict[str, Any]:
    """What the eye said of each candidate it gave a verdict on, against what is really there
    (``truth``: the object's kind, or ``none``); ``car_verdicts_on_cars``: every true car has the
    eye's "car" verdict and nothing else has (the check of ``--zero-labels``, docs/demo.md)."""
    kind_of = {f"target {i + 1}": t.kind for i, t in enumerate(world.cars)}
    kind_of.update({f"decoy {k + 1} ({o.kind})": o.kind for k, o in enumerate(world.rocks)})
    rows = []
    for c in operator.candidates:
        if not c.verdict:
            continue
        where = truth_near(c.x, c.y)
        rows.append({"x": c.x, "y": c.y, "verdict": c.verdict, "truth": where, "kind": kind_of.get(where, "none")})
    car_rows = {r["truth"] for r in rows if r["verdict"] == "car"}
    cars = {f"target {i + 1}" for i, t in enumerate(world.cars) if t.kind == "car"}
    return {"candidates": rows, "car_verdicts_on_cars": car_rows == cars and all(
        r["kind"] == "car" for r in rows if r["verdict"] == "car")}


def _surveys(receiver: Any, operator: Operator, truth: dict[int, dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per survey command topside sent: what was asked, when it was sent, each state
    as topside heard it (dive seconds: the arrival of the vehicle's ack, the stamps of its
    reports), its final state, and the truth: when the command reached the vehicle, what the
    vehicle answered and when it really flew it."""

    def s(t: float | None) -> float | None:
        return None if t is None else round(t - EPOCH, 1)

    out = []
    for sid, rec in sorted(receiver.surveys.items()):
        if rec.command is None:
            continue
        c = rec.command
        first: dict[str, float] = {}
        started: dict[int, float] = {}
        for t, state, text in rec.history:
            first.setdefault(state, t)
            if state == "started":
                k = text.rsplit(" ", 1)[-1]
                if k.isdigit():
                    started.setdefault(int(k), t)
        line = operator.lines.get(sid)
        out.append({
            "id": sid, "command_id": rec.command_id,
            "asked": {"kind": type(c.kind)(c.kind).name.lower(), "x": c.x, "y": c.y, "heading": c.heading,
                      "length": c.length, "altitude": c.altitude, "speed": c.speed, "append": c.append,
                      "points": [[p.x, p.y] for p in c.points]},
            "candidate": None if line is None else {"x": line.candidate.x, "y": line.candidate.y,
                                                    "score": line.candidate.score},
            "sent_at_s": s(first.get("requested")),
            "accepted_at_s": s(first.get("accepted")),
            "started_at_s": s(started.get(0, first.get("started"))),
            "line_start_at_s": s(started.get(1)),
            "completed_at_s": s(first.get("completed")),
            "rejected_at_s": s(first.get("rejected")),
            "final_state": rec.state, "reason": rec.reason, "text": rec.text,
            "truth": truth.get(sid),
        })
    return out


def _obj(t: Target) -> dict[str, Any]:
    return {"x": t.x, "y": t.y, "length": t.length, "width": t.width, "height": t.height,
            "heading": round(t.heading, 1)}


def _crop(grid: np.ndarray, cell: float, x0: float, y0: float, xa: float, ya: float, xb: float, yb: float,
          ) -> tuple[np.ndarray, float, float]:
    """The part of a level grid (row 0 = south) inside [xa, xb] x [ya, yb]."""
    ny, nx = grid.shape
    c0 = max(math.floor((xa - x0) / cell), 0)
    c1 = min(math.ceil((xb - x0) / cell), nx)
    r0 = max(math.floor((ya - y0) / cell), 0)
    r1 = min(math.ceil((yb - y0) / cell), ny)
    if c1 <= c0 or r1 <= r0:
        return grid, x0, y0
    return grid[r0:r1, c0:c1], x0 + c0 * cell, y0 + r0 * cell


def _summary(targets: list[dict[str, Any]], false: list[dict[str, Any]], operator: str,
             goals: dict[str, dict[str, Any]]) -> str:
    """The outcome in words, from the judged metrics: the main goal first, then the others."""
    ok = [t for t in targets if t["confirmation"] is not None]
    missed = [t for t in targets if t["confirmation"] is None]
    main = bool(targets) and not missed and not false
    parts = [f"{'MET' if main else 'NOT MET'}: every true target confirmed by a received image that shows "
             "it, and nothing else confirmed."]
    if not targets:
        parts.append("This scenario has no targets.")
    elif not missed:
        parts.append(f"All {len(targets)} targets were confirmed.")
    else:
        parts.append(f"{len(ok)} of {len(targets)} targets were confirmed.")
    for t in ok:
        c = t["confirmation"]
        parts.append(f"{t['name'].capitalize()} at ({t['x']:.0f}, {t['y']:.0f}): image {c['image_id']}, "
                     f"{c['bytes']} B, confirmed at {c['confirmed_at_s']:.0f} s, {c['tdma_cycles']} TDMA cycles "
                     "after its request.")
    for t in missed:
        parts.append(f"{t['name'].capitalize()} at ({t['x']:.0f}, {t['y']:.0f}) was not confirmed: {t['why_not']}.")
    if false:
        parts.append(f"{len(false)} confirmation(s) of something that is not a target: "
                     + "; ".join(f"({f['x']:.0f}, {f['y']:.0f}) by image {f['image_id']}, which shows {f['shows']}"
                                 for f in false) + ".")
    elif targets:
        parts.append("Nothing that is not a target was confirmed.")
    others = [f"{name}: {'MET' if g['met'] else 'NOT MET'} ({g['detail']})" for name, g in goals.items()
              if not name.startswith("every target confirmed")]
    if others:
        parts.append("Other goals: " + "; ".join(others) + ".")
    if operator == "none":
        parts.append("No scripted operator ran (--operator none): only what a person did in the console counts.")
    return " ".join(parts)


def _decision_summary(targets: list[dict[str, Any]]) -> dict[str, Any]:
    """Decision time (issue 43) over the dive's targets: median and worst of those confirmed,
    and how many targets have none (never identifiable at 1 m, or never confirmed)."""
    times = sorted(t["decision_time_s"] for t in targets if t["decision_time_s"] is not None)
    med = None if not times else float(np.median(times))
    return {"median": None if med is None else round(med, 1), "worst": times[-1] if times else None,
            "missing": len(targets) - len(times)}


def vehicle_summary(node_id: int, role: str, runner: Runner, link_log: Path, *,
                    surveys: dict[int, dict[str, Any]], images_captured: int,
                    received_positions: int) -> dict[str, Any]:
    """One vehicle's section of the report: its link (what it sent, how much arrived), the
    frames it overheard for another node (a fleet), the survey commands that reached it and the
    ones it flew (the simulation's truth), the images it took and the statuses topside heard."""
    link = _link_summary(link_log, src=node_id)
    for k in ("capacity_series", "used_series", "delivered_series"):
        link.pop(k, None)
    stats = runner.node.stats
    return {"node": node_id, "role": role, "link": link,
            "frames_overheard_for_others": int(stats.get("foreign", 0)),
            "bad_frames": int(stats.get("bad_frames", 0)),
            "survey_commands_received": sum(1 for s in surveys.values() if s.get("received_by_vehicle_s") is not None),
            "survey_commands_flown": sum(1 for s in surveys.values() if s.get("set_off_s") is not None),
            "survey_ids": sorted(surveys),
            "images_captured": images_captured, "statuses_received_topside": received_positions}


def _link_summary(path: Path, src: int = VEHICLE) -> dict[str, Any]:
    cap = used = delivered = 0
    cap_s: list[tuple[float, float]] = []
    used_s: list[tuple[float, float]] = []
    del_s: list[tuple[float, float]] = []
    sent = lost = frames = 0
    work_cap = work_used = spare = redundant = 0
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("src") != src:
            continue
        t = float(rec.get("time", 0.0)) - EPOCH
        if rec.get("cause") == "sent":
            cap += int(rec.get("capacity_bytes") or 0)
            used += int(rec.get("used_bytes") or 0)
            sent += 1
            spare += int(rec.get("spare_bytes") or 0)
            redundant += int(rec.get("redundant_bytes") or 0)
            if int(rec.get("backlog_bytes") or 0) > 0:  # work was left: the packet should be full
                work_cap += int(rec.get("capacity_bytes") or 0)
                work_used += int(rec.get("used_bytes") or 0)
            cap_s.append((round(t, 1), cap))
            used_s.append((round(t, 1), used))
        elif rec.get("delivered") is not None and rec.get("dst") in (None, TOPSIDE):  # not the other vehicle's copy
            d = rec.get("delivered")
            n = sum(1 for x in d if x) if isinstance(d, list) else int(d)
            delivered += int(rec.get("delivered_bytes", rec.get("used_bytes") if n else 0) or 0)
            lost += int(rec.get("lost") or 0) if not isinstance(rec.get("lost"), list) else len(rec["lost"])
            frames += int(rec.get("frames") or 0)
            del_s.append((round(t, 1), delivered))
    return {"packets_sent": sent, "capacity_bytes": cap, "used_bytes": used, "delivered_bytes": delivered,
            "frames_lost": lost, "frame_loss": round(lost / frames, 4) if frames else None,
            "fill": round(used / cap, 4) if cap else None,
            "fill_with_work": round(work_used / work_cap, 4) if work_cap else None,
            "spare_bytes": spare, "redundant_bytes": redundant,
            "capacity_series": cap_s, "used_series": used_s,
            "delivered_series": del_s}


def iter_decisions(result: DemoResult) -> Iterator[str]:
    for d in result.decisions:
        yield f"{d.t:7.0f} s  {d.kind:<16} {d.text}"

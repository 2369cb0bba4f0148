"""The console's map: the bathymetry receiver's levels as the page draws them (coverage blocks,
gaps, ages), candidate targets and the vehicle's detections, and the map regions asked.

A part of :class:`~coex_apps.console.state.ConsoleState` (its API is the state's); the
pictures of the levels stay with the state (:meth:`ConsoleState.map_png`). A region's state is
the bathymetry receiver's (the core tracker's, :mod:`coex_core.tracker`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_plugins.bathymetry import BathymetryReceiver, MapLevel

from .model import ConsoleModel
from .records import _RoiRequest
from .words import _num, gap_words

__all__ = ["MAP_BLOCKS", "MapView", "map_delta"]

FloatArray = npt.NDArray[np.float64]

#: The map section shows a level's coverage (the age of its data) in at most this many blocks:
#: every subgrid of a small level, groups of receiver tiles of a big one.
MAP_BLOCKS = 4096


class MapView(ConsoleModel):
    """The map part of :class:`~coex_apps.console.state.ConsoleState`."""

    @property
    def map_receiver(self) -> BathymetryReceiver | None:
        """The bathymetry receiver whose levels the map shows (None before any): with topside's
        navigation applied, seen through it (each subgrid placed by the drift correction at its
        stamp, :class:`coex_plugins.navigation.CorrectedMap`)."""
        rx = self.receivers.get("bathymetry")
        if not isinstance(rx, BathymetryReceiver):
            return None
        nav = self.navigation
        if nav is not None and nav.apply:
            from coex_plugins.navigation import CorrectedMap

            return CorrectedMap(rx, nav, self.vehicle_id)  # type: ignore[return-value]
        return rx

    def _map_product(self, product: MapLevel) -> None:
        """A level of the bathymetry receiver changed: its depth range widens the colour scale
        (the receiver's ``zmin``/``zmax`` when it says them: a big level is not scanned)."""
        data = product.data
        if product.zmin is not None and product.zmax is not None:
            lo, hi = float(product.zmin), float(product.zmax)
            zr = self._zrange or (lo, hi)
            self._zrange = (min(zr[0], lo), max(zr[1], hi))
            self._touch("map")
            return
        z = np.asarray(data, float)
        finite = z[np.isfinite(z)]
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            zr = self._zrange or (lo, hi)
            self._zrange = (min(zr[0], lo), max(zr[1], hi))
        self._touch("map")

    def held_stamps(self, level: int, x0: int, y0: int, w: int, h: int) -> list[int | None]:
        """Per subgrid of the region, row-major (rows = y): the stamp topside holds, or None."""
        rx = self.map_receiver
        if rx is None:
            return [None] * (w * h)
        return list(rx.region_stamps(level, x0, y0, w, h))

    def level_grid(self, level: int) -> tuple[FloatArray, float, float, float] | None:
        """A copy of the receiver's drawn level: ``(z, x0, y0, cell)`` with row 0 = south, or
        None if nothing of it is held. A big level is a decimated overview (``cell`` is then a
        multiple of the level's: at most the receiver's ``max_mosaic_cells``)."""
        rx = self.map_receiver
        if rx is None or level not in rx.levels():
            return None
        p = rx.level_product(level)
        z = np.array(p.data, dtype=float)
        if not np.isfinite(z).any():
            return None
        return z, float(p.x0), float(p.y0), float(p.cell_size)

    def _snap_map(self) -> dict[str, Any]:
        rx = self.map_receiver
        levels = []
        for level in sorted(rx.levels(), reverse=True) if rx is not None else ():
            assert rx is not None
            geometry = rx.geometry(level)
            if geometry is None:
                continue
            c, side = geometry
            version = rx.level_version(level)
            cached = self._map_summary.get(level)
            if cached is None or cached[0] != version:
                # from the receiver's running summary and its coverage in at most MAP_BLOCKS
                # blocks (every subgrid of a small level): a big level is never read whole
                summary = rx.level_summary(level)
                span, keys, ts = rx.coverage(level, MAP_BLOCKS)
                p = rx.level_product(level)
                pc = float(p.cell_size)
                px0, py0 = float(p.x0), float(p.y0)
                image = [px0, py0, px0 + p.data.shape[1] * pc, py0 + p.data.shape[0] * pc]
                cached = (version, summary, span, keys, ts, image, int(p.step))
                self._map_summary[level] = cached
            _, summary, span, keys, ts, image, step = cached
            if summary is None or not summary["subgrids"] or summary["extent"] is None:
                continue
            ix0, iy0, ix1, iy1 = summary["extent"]
            cells = int(summary["cells"])
            # gaps: blocks of tile_span x tile_span subgrids inside the extent with no data
            bx = math.ceil(ix1 / span) - math.floor(ix0 / span)
            by = math.ceil(iy1 / span) - math.floor(iy0 / span)
            empty = max(0, bx * by - len(keys))
            block_m = span * side * c
            levels.append({
                "level": level, "cell": c, "side": side, "subgrids": int(summary["subgrids"]),
                "cells": cells, "coverage_m2": cells * c * c,
                "fill_pct": round(100.0 * cells / max(1, (ix1 - ix0) * (iy1 - iy0) * side * side)),
                "gaps": empty, "gap_block_m": block_m,
                "gap_note": gap_words(empty, block_m, int(summary["subgrids"]) * side * side,
                                      cells),
                "x0": float(ix0 * side * c), "y0": float(iy0 * side * c),
                "x1": float(ix1 * side * c), "y1": float(iy1 * side * c),
                "newest_age": _num(self.now - float(summary["newest"]), 1),
                "oldest_age": _num(self.now - float(summary["oldest"]), 1),
                # absolute times (s): the page takes the ages from its clock, so that a level
                # that did not change is the same in every update (and need not be resent)
                "newest": _num(float(summary["newest"]), 1),
                "oldest": _num(float(summary["oldest"]), 1),
                "version": version, "png": f"/map/{level}.png?v={version}",
                # where the picture goes (the receiver's drawn array, which may be larger than
                # what is held, and coarser: ``step`` level cells per pixel)
                "image": image, "step": step,
                # per block of tile_span x tile_span subgrids: the time of its oldest data
                "tile_span": span,
                "tiles": np.column_stack([keys, np.round(ts)]).astype(np.int64).tolist(),
            })
        meta = rx.metadata if rx is not None else None
        zr = self._zrange
        return {
            "meta": None if meta is None else {
                "resolution": meta.resolution, "vertical_resolution": meta.vertical_resolution,
                "subgrid_side": meta.subgrid_side, "levels": meta.levels,
                "origin_lat": meta.origin_lat, "origin_lon": meta.origin_lon,
                "pending": meta.pending},
            "levels": levels, "zrange": None if zr is None else [zr[0], zr[1]],
            "targets": list(self.targets) + self._auto_targets(),
            "detections": list(self.detections),
            "requests": [self._snap_roi(r) for r in sorted(self.roi.values(),
                                                          key=lambda r: r.sent)][-40:],
        }

    def _auto_targets(self) -> list[dict[str, Any]]:
        """Candidate targets flagged on the finest level held at 2 m or better (cells standing
        out from their surroundings, the bathymetry plugin's ``find_targets``), if it is drawn
        whole (a level too big for that is a decimated overview: no car stands out in it)."""
        rx = self.map_receiver
        if not self.auto_targets or rx is None:
            return []
        fine = [lv for lv in rx.levels() if (rx.geometry(lv) or (99.0, 0))[0] <= 2.0
                and rx.level_product(lv).step == 1]
        if not fine:
            return []
        level = min(fine)
        summary = rx.level_summary(level)
        version, count = rx.level_version(level), int(summary["subgrids"]) if summary else 0
        last = self._targets_cache[0]
        # a big map changes with every subgrid: look again once 5% more of it has come in
        stale = (last is None or last[0] != level or version < last[1]
                 or version - last[1] >= max(1, count // 20))
        if stale:
            from coex_plugins.bathymetry import find_targets

            grid = self.level_grid(level)
            found: list[dict[str, Any]] = []
            if grid is not None:
                z, x0, y0, cell = grid
                cands = find_targets(z, cell=cell, x0=x0, y0=y0, threshold=self.target_threshold,
                                     min_cells=self.target_min_cells)
                for c in sorted(cands, key=lambda c: -c.height):
                    if len(found) >= self.max_targets:
                        break
                    if any(math.hypot(c.x - f["x"], c.y - f["y"]) < self.target_spacing
                           for f in found):
                        continue  # one marker per object
                    found.append({"x": _num(c.x, 1), "y": _num(c.y, 1),
                                  "height": _num(c.height, 2), "cells": int(c.cells),
                                  "level": level, "auto": True})
            self._targets_cache = ((level, version), found)
        return list(self._targets_cache[1])

    def subgrid_metres(self, level: int) -> float:
        """The side of a subgrid of ``level`` in metres."""
        rx = self.map_receiver
        geometry = rx.geometry(level) if rx is not None else None
        meta = rx.metadata if rx is not None else None
        if geometry is not None:
            return float(geometry[0] * geometry[1])
        if meta is not None:
            return float(meta.resolution * 2 ** level * meta.subgrid_side)
        return float(8.0 * 2 ** level)

    def _snap_roi(self, r: _RoiRequest) -> dict[str, Any]:
        """A region request as the bathymetry receiver sends and retries it: ``waiting`` (not
        sent yet), ``sent``, ``queued`` (the vehicle queued ``queued`` subgrids for it; asked
        again until it has nothing newer), ``waiting for survey`` (the request stands on the
        vehicle for ``awaiting_survey`` subgrids not surveyed yet) or ``nothing newer`` (done)."""
        rx = self.map_receiver
        geometry = rx.geometry(r.level) if rx is not None else None
        meta = rx.metadata if rx is not None else None
        if geometry is not None:
            span = geometry[0] * geometry[1]
        elif meta is not None:
            span = meta.resolution * 2 ** r.level * meta.subgrid_side
        else:
            span = 8.0 * 2 ** r.level
        region = r.region
        rid = region.request_id if region.request_id is not None else -1
        queued, waiting = region.queued, region.waiting
        got = max(int(r.got or 0), int(queued or 0))
        r.got = got
        # ``status``: the request as the receiver sends it; ``state``: what it means for the
        # operator (requested, in flight, waiting for data, filled, nothing to send)
        if region.done:
            status = "nothing newer"
            state = "filled" if got else "nothing to send"
        elif queued:
            status, state = "queued", "in flight"
        elif waiting:
            status, state = "waiting for survey", "waiting for data"
        elif region.sends:
            status, state = "sent", "requested"
        else:
            status, state = "waiting", "requested"
        text = {"requested": "asked" + (f" ({region.sends}x)" if region.sends > 1 else "")
                             if region.sends else "waiting for a topside slot",
                "in flight": f"{queued} subgrid{'s' if queued != 1 else ''} on the way",
                "waiting for data": f"{waiting} subgrid{'s' if waiting != 1 else ''} not surveyed yet",
                "filled": f"filled ({got} subgrid{'s' if got != 1 else ''})",
                "nothing to send": "nothing to send: topside had it all"}[state]
        return {"request_id": rid, "level": r.level, "x0": r.x0, "y0": r.y0,
                "w": r.w, "h": r.h, "status": status, "state": state, "text": text,
                "got": got, "queued": queued, "awaiting_survey": waiting,
                "sent": _num(r.sent, 1),
                "rect": [r.x0 * span, r.y0 * span, (r.x0 + r.w) * span, (r.y0 + r.h) * span]}

    def _detections_product(self, data: Any, now: float) -> None:
        """The detections receiver's rows: what the vehicle's detectors suggest (new ones are
        logged once)."""
        known = {int(d["id"]) for d in self.detections}
        rows = []
        for r in data if isinstance(data, list | tuple) else ():
            if not isinstance(r, Mapping) or r.get("x") is None or r.get("y") is None:
                continue
            rows.append({k: (_num(v, 2) if isinstance(v, float) else v) for k, v in r.items()
                         if k in ("id", "source", "x", "y", "score", "height", "length", "width", "orientation",
                                  "footprint", "image_id", "time", "first_at")})
            if int(r["id"]) not in known:
                size = "" if r.get("length") is None else f", {r['length']:.1f} x {r['width']:.1f} m"
                high = "" if r.get("height") is None else f", {r['height']:.1f} m high"
                self._log(now, f"the vehicle suggests a detection at ({r['x']:.0f}, {r['y']:.0f}){high}{size}, "
                          f"score {r['score']:.2f} (detection {r['id']}, in its {r.get('source', 'data')})")
        self.detections = rows
        self._touch("map")

    def _targets_product(self, data: Any, meta: Mapping[str, Any]) -> None:
        rows = data if isinstance(data, list | tuple) else meta.get("targets", [])
        out = []
        for t in rows:
            d = t if isinstance(t, Mapping) else getattr(t, "__dict__", {})
            if "x" in d and "y" in d:
                out.append({k: (_num(v) if isinstance(v, float) else v) for k, v in d.items()
                            if isinstance(v, int | float | str | bool)})
        self.targets = out
        self._touch("map")

    def add_targets(self, targets: Iterable[Mapping[str, Any]]) -> None:
        """Add candidate targets (``x``, ``y`` and optionally ``height``, ``level``, ``score``)."""
        for t in targets:
            self.targets.append({k: (_num(v) if isinstance(v, float) else v) for k, v in t.items()})
        self._touch("map")


def map_delta(full: Mapping[str, Any], held: dict[int, Any]) -> dict[str, Any]:
    """The map section ``full`` as a delta against what a client holds (``held``: level ->
    (version, {(ix, iy): t}, tile_span), updated to what it holds after it): see
    :meth:`ConsoleState.changes`."""
    levels = []
    present = set()
    for lv in full["levels"]:
        n = int(lv["level"])
        present.add(n)
        tiles = {(int(a), int(b)): int(t) for a, b, t in lv["tiles"]}
        had = held.get(n)
        if had is None or had[2] != lv["tile_span"]:
            levels.append(lv)
        elif had[0] == lv["version"]:
            levels.append({"level": n, "same": True})
        else:
            old = had[1]
            part = {k: v for k, v in lv.items() if k != "tiles"}
            part["tiles_changed"] = [[a, b, t] for (a, b), t in tiles.items() if old.get((a, b)) != t]
            part["tiles_removed"] = [[a, b] for (a, b) in old if (a, b) not in tiles]
            levels.append(part)
        held[n] = (lv["version"], tiles, lv["tile_span"])
    for n in [n for n in held if n not in present]:
        del held[n]
    return {**full, "levels": levels, "delta": True}

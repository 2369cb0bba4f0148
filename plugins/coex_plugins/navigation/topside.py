"""Topside's navigation: per vehicle one :class:`~.estimator.DriftEstimator`, fed with the
vehicle's dead-reckoned track as it arrives (its statuses) and the ship's USBL fixes
(:class:`~.usbl.UsblInput`), and what the correction does to what topside shows.

:class:`Navigation` is what the console, ``coex topside`` and the demo hold. Its
:meth:`Navigation.corrected_level` places every received subgrid of a map level by the smoothed
correction at the subgrid's own stamp (the time its newest sounding was taken): the map in
corrected, georeferenced coordinates, without jumps where the correction changed between two
passes. :meth:`Navigation.to_vehicle` turns a point of the corrected map into the vehicle's own
frame (the correction now, and what the estimated biases add on the way there), which is where a
survey command must send it.

The views below (:class:`CorrectedMap`, :class:`CorrectedDetections`, :class:`CorrectedImages`,
:class:`VehicleFrameSurveys`) wrap a topside receiver for a client that works in the corrected
frame (the demo's scripted operator, a script): what they read is corrected, what they send is
put back into the vehicle's frame. They hold no data of their own.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import Nav, Product, unwrap
from coex.messages import SurveyCommand, VehicleStatus

from .estimator import DriftEstimator, NavConfig

__all__ = ["CorrectedDetections", "CorrectedImages", "CorrectedMap", "Navigation", "VehicleFrameSurveys"]

FloatArray = npt.NDArray[np.float64]
#: blocks of subgrids the correction of a big level is looked up in (the receiver's coverage)
MAP_BLOCKS = 4096


class Navigation:
    """Topside's estimate of each vehicle's drift (see the module docstring). ``apply``: False
    keeps estimating (what the console shows) but :meth:`correction` is zero: the map, the
    images and commands stay in the vehicle's frame (the demo's ``--no-correction``).
    ``targets``: USBL target or transponder number -> vehicle node id (default: the number is the
    node id; a fix without one, such as a GGA, is the only vehicle's)."""

    def __init__(self, config: NavConfig | None = None, *, apply: bool = True,
                 targets: Mapping[int, int] | None = None) -> None:
        self.config = config or NavConfig()
        self.apply = apply
        self.targets = dict(targets or {})
        self.estimators: dict[int, DriftEstimator] = {}
        self._levels: dict[tuple[int, int, int], tuple[tuple[int, int], Any]] = {}
        #: fixes that named no vehicle this topside follows
        self.unrouted = 0

    def estimator(self, vehicle: int) -> DriftEstimator:
        est = self.estimators.get(vehicle)
        if est is None:
            est = self.estimators[vehicle] = DriftEstimator(self.config)
        return est

    # ------------------------------------------------------------------ data in
    def status(self, vehicle: int, status: VehicleStatus, now: float) -> None:
        """A vehicle status topside received: a point of its dead-reckoned track at its stamp."""
        self.estimator(vehicle).add_track(unwrap(status.stamp, now), float(status.x), float(status.y),
                                          float(status.heading))

    def fix(self, nav: Nav, vehicle: int | None = None) -> int | None:
        """A USBL fix (an item of :class:`~.usbl.UsblInput`) for ``vehicle`` or the vehicle its
        target number names; the vehicle it went to (None: none)."""
        if nav.x is None or nav.y is None:
            return None
        if vehicle is None:
            target = nav.extra.get("target")
            if target is not None:
                vehicle = self.targets.get(int(target), int(target))
                if self.estimators and vehicle not in self.estimators and len(self.estimators) == 1:
                    vehicle = next(iter(self.estimators))
            elif len(self.estimators) <= 1:
                vehicle = next(iter(self.estimators), None)
        if vehicle is None:
            self.unrouted += 1
            return None
        self.estimator(vehicle).add_fix(float(nav.time), float(nav.x), float(nav.y))
        return vehicle

    # ------------------------------------------------------------------ the correction
    def correction(self, vehicle: int, t: npt.ArrayLike) -> FloatArray:
        """The correction applied (believed - true, m) at times ``t``: ``(..., 2)``; zeros when
        :attr:`apply` is off or nothing is known of the vehicle."""
        est = self.estimators.get(vehicle)
        times = np.asarray(t, float)
        if not self.apply or est is None:
            return np.zeros((*times.shape, 2))
        return est.correction(times)

    def corrected(self, vehicle: int, t: float, x: float, y: float) -> tuple[float, float]:
        """A point the vehicle placed at ``(x, y)`` at ``t``, in the corrected frame."""
        c = self.correction(vehicle, t)
        return float(x - c[0]), float(y - c[1])

    def to_vehicle(self, vehicle: int, x: float, y: float, t: float,
                   start: tuple[float, float] | None = None) -> tuple[float, float]:
        """A point of the corrected frame in the vehicle's own frame, to go there after ``t``
        from ``start`` (corrected frame; None: the correction at ``t`` alone)."""
        est = self.estimators.get(vehicle)
        if not self.apply or est is None:
            return float(x), float(y)
        return est.to_vehicle(x, y, t, start)

    def corrected_level(self, receiver: Any, level: int, vehicle: int
                        ) -> tuple[FloatArray, float, tuple[float, float]] | None:
        """A bathymetry receiver's level in the corrected frame: ``(grid, cell, (x0, y0))``,
        row 0 south, NaN where nothing is held, or None. Each cell is taken from the received
        level where the correction of its subgrid (at the subgrid's stamp) puts it, bilinear
        between the four received cells around that point (the nearest where one of them is
        empty), so a subgrid moves whole by a fraction of a cell and two neighbours whose
        corrections differ meet without a gap. Cached until the level or the estimate changes."""
        try:
            p = receiver.level_product(level)
        except Exception:
            return None
        if p.data is None:
            return None
        z = np.asarray(p.data, dtype=float)
        cell = float(p.meta["cell_size"])
        x0, y0 = float(p.meta["x0"]), float(p.meta["y0"])
        est = self.estimators.get(vehicle)
        if not self.apply or est is None or est.solution() is None or z.size == 0:
            return z, cell, (x0, y0)
        key = (id(receiver), level, vehicle)
        stamp = (receiver.level_version(level), est.version)
        cached = self._levels.get(key)
        if cached is not None and cached[0] == stamp:
            return cached[1]  # type: ignore[no-any-return]
        out = self._resample(receiver, level, est, z, cell, x0, y0)
        self._levels[key] = (stamp, out)
        return out

    def _resample(self, receiver: Any, level: int, est: DriftEstimator, z: FloatArray, cell: float,
                  x0: float, y0: float) -> tuple[FloatArray, float, tuple[float, float]]:
        geometry = receiver.geometry(level)
        span, keys, stamps = receiver.coverage(level, MAP_BLOCKS)
        if geometry is None or len(keys) == 0:
            return z, cell, (x0, y0)
        level_cell, side = geometry
        block = float(level_cell) * int(side) * int(span)  # metres per coverage block
        # the correction of every coverage block (at its oldest stamp: one subgrid at fine levels)
        corr = est.correction(np.asarray(stamps, float))
        kx0, ky0 = keys.min(axis=0)
        kx1, ky1 = keys.max(axis=0)
        lut = np.full((ky1 - ky0 + 1, kx1 - kx0 + 1, 2), np.nan)
        lut[keys[:, 1] - ky0, keys[:, 0] - kx0] = corr
        fill = np.nanmean(corr, axis=0) if np.isfinite(corr).any() else np.zeros(2)
        lim = float(np.nanmax(np.abs(corr))) if np.isfinite(corr).any() else 0.0
        pad = math.ceil(lim / cell) + 1
        ny, nx = z.shape
        oy, ox = ny + 2 * pad, nx + 2 * pad
        X0, Y0 = x0 - pad * cell, y0 - pad * cell
        qx = X0 + (np.arange(ox) + 0.5) * cell
        qy = Y0 + (np.arange(oy) + 0.5) * cell
        gx, gy = np.meshgrid(qx, qy)

        def field(px: FloatArray, py: FloatArray) -> FloatArray:
            bx = np.floor(px / block).astype(np.int64) - kx0
            by = np.floor(py / block).astype(np.int64) - ky0
            inside = (bx >= 0) & (by >= 0) & (bx < lut.shape[1]) & (by < lut.shape[0])
            c = np.broadcast_to(fill, (*px.shape, 2)).copy()
            got = lut[np.clip(by, 0, lut.shape[0] - 1), np.clip(bx, 0, lut.shape[1] - 1)]
            ok = inside & np.isfinite(got[..., 0])
            c[ok] = got[ok]
            return c

        # where in the received level does each corrected cell come from: q + c(source), with the
        # source's correction found by two fixed-point steps
        c = field(gx + fill[0], gy + fill[1])
        c = field(gx + c[..., 0], gy + c[..., 1])
        # bilinear between the four source cells around that point (a subgrid lands where its
        # correction puts it, to a fraction of a cell); nearest where one of them is empty
        u = (gx + c[..., 0] - x0) / cell - 0.5
        v = (gy + c[..., 1] - y0) / cell - 0.5
        j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        fu, fv = u - j0, v - i0
        zp = np.pad(z, 1, constant_values=np.nan)  # index + 1: one empty cell all round

        def at(i: npt.NDArray[np.int64], j: npt.NDArray[np.int64]) -> FloatArray:
            return zp[np.clip(i + 1, 0, ny + 1), np.clip(j + 1, 0, nx + 1)]

        z00, z01, z10, z11 = at(i0, j0), at(i0, j0 + 1), at(i0 + 1, j0), at(i0 + 1, j0 + 1)
        out = (z00 * (1 - fu) * (1 - fv) + z01 * fu * (1 - fv) + z10 * (1 - fu) * fv + z11 * fu * fv)
        near = at(np.where(fv < 0.5, i0, i0 + 1), np.where(fu < 0.5, j0, j0 + 1))
        out = np.where(np.isfinite(out), out, near)
        return out, cell, (X0, Y0)

    # ------------------------------------------------------------------ what is shown
    def state(self, vehicle: int, now: float, *, recent: int = 200) -> dict[str, Any]:
        """What the console shows of a vehicle's navigation: the correction now (``dx``, ``dy``,
        ``size`` m, its 1-sigma, ``age`` s since the newest fix used), the newest ``recent`` fixes
        (t, x, y, used, outlier), the raw (dead-reckoned) and corrected tracks, and counts."""
        est = self.estimators.get(vehicle)
        out: dict[str, Any] = {"vehicle": vehicle, "applied": self.apply, "fixes": [], "raw_track": [],
                               "corrected_track": [], "correction": None, "fix_count": 0, "outliers": 0}
        if est is None:
            return out
        track = est.track()
        sol = est.solution()
        out["fix_count"] = est.fix_count
        out["raw_track"] = [[round(float(a), 1), round(float(b), 1), round(float(c), 1)] for a, b, c in track[-2000:]]
        if sol is None:
            return out
        c_track = est.correction(track[:, 0]) if len(track) else np.zeros((0, 2))
        out["corrected_track"] = [[round(float(t), 1), round(float(x - cx), 1), round(float(y - cy), 1)]
                                  for (t, x, y), (cx, cy) in zip(track[-2000:], c_track[-2000:], strict=True)]
        fx = sol.fixes
        out["fixes"] = [[round(float(r[0]), 1), round(float(r[1]), 1), round(float(r[2]), 1), bool(r[3]), bool(r[4])]
                        for r in fx[-recent:]]
        out["outliers"] = int(fx[:, 4].sum())
        used = fx[fx[:, 3] > 0]
        newest = float(used[:, 0].max()) if len(used) else None
        c = est.correction(now)
        out["correction"] = {"dx": round(float(c[0]), 2), "dy": round(float(c[1]), 2),
                             "size": round(float(math.hypot(c[0], c[1])), 2),
                             "sigma": round(float(est.sigma(now)), 2),
                             "age": None if newest is None else round(max(now - newest, 0.0), 1),
                             "fix_sigma": round(sol.fix_sigma, 2)}
        return out


# ================================================================================ views
class _View:
    """A receiver seen through the navigation (attributes not overridden are the receiver's)."""

    def __init__(self, receiver: Any, nav: Navigation, vehicle: int) -> None:
        self._rx = receiver
        self._nav = nav
        self._vehicle = vehicle

    def __getattr__(self, name: str) -> Any:
        return getattr(self._rx, name)


class CorrectedMap(_View):
    """A bathymetry receiver whose levels are corrected (:meth:`Navigation.corrected_level`)
    and whose area requests are put back into the vehicle's frame."""

    def level_product(self, level: int, now: float | None = None) -> Product:
        p = self._rx.level_product(level) if now is None else self._rx.level_product(level, now)
        got = self._nav.corrected_level(self._rx, level, self._vehicle)
        if got is None:
            return p  # type: ignore[no-any-return]
        grid, cell, (x0, y0) = got
        return Product(p.kind, p.key, p.version, grid, {**p.meta, "x0": x0, "y0": y0, "cell_size": cell,
                                                         "corrected": self._nav.apply})

    def level_version(self, level: int) -> int:
        """Changes when the level or the estimate does (a corrected level moves with the estimate)."""
        est = self._nav.estimators.get(self._vehicle)
        return int(self._rx.level_version(level)) * 1_000_000 + (est.version % 1_000_000 if est is not None else 0)

    def _corrected(self, level: int) -> tuple[FloatArray, float, tuple[float, float]] | None:
        """The corrected level when it is at the level's own cells (not a decimated overview)."""
        if not self._nav.apply:
            return None
        got = self._nav.corrected_level(self._rx, level, self._vehicle)
        geometry = self._rx.geometry(level)
        if got is None or geometry is None or abs(got[1] - float(geometry[0])) > 1e-9:
            return None
        return got

    def level_summary(self, level: int) -> dict[str, Any] | None:
        """The receiver's summary with the extent (subgrid indices) of the corrected level."""
        summary: dict[str, Any] | None = self._rx.level_summary(level)
        got = self._corrected(level)
        if summary is None or got is None:
            return summary
        grid, cell, (x0, y0) = got
        rows, cols = np.nonzero(np.isfinite(grid))
        if not len(rows):
            return summary
        size = cell * int(summary["side"])
        extent = (math.floor((x0 + cols.min() * cell) / size + 1e-9), math.floor((y0 + rows.min() * cell) / size + 1e-9),
                  math.ceil((x0 + (cols.max() + 1) * cell) / size - 1e-9),
                  math.ceil((y0 + (rows.max() + 1) * cell) / size - 1e-9))
        return {**summary, "extent": extent}

    def window(self, level: int, x_min: float, y_min: float, x_max: float, y_max: float,
               max_cells: int | None = None) -> tuple[FloatArray, tuple[float, float, float]]:
        """A part of the corrected level at its own cells (the receiver's :meth:`window` when the
        correction is off, or the window would need decimating: the raw level then)."""
        got = self._corrected(level)
        if got is not None:
            grid, cell, (x0, y0) = got
            c0, r0 = round((x_min - x0) / cell), round((y_min - y0) / cell)
            w, h = max(round((x_max - x_min) / cell), 0), max(round((y_max - y_min) / cell), 0)
            if max_cells is None or w * h <= max_cells:
                out = np.full((h, w), np.nan)
                a, b = max(c0, 0), min(c0 + w, grid.shape[1])
                c, d = max(r0, 0), min(r0 + h, grid.shape[0])
                if a < b and c < d:
                    out[c - r0:d - r0, a - c0:b - c0] = grid[c:d, a:b]
                return out, (x0 + c0 * cell, y0 + r0 * cell, cell)
        if max_cells is None:
            return self._rx.window(level, x_min, y_min, x_max, y_max)  # type: ignore[no-any-return]
        return self._rx.window(level, x_min, y_min, x_max, y_max, max_cells)  # type: ignore[no-any-return]

    def request_area(self, level: int, x_min: float, y_min: float, x_max: float, y_max: float,
                     *args: Any, **kw: Any) -> Any:
        t = self._newest()
        c = self._nav.correction(self._vehicle, t)
        return self._rx.request_area(level, x_min + float(c[0]), y_min + float(c[1]), x_max + float(c[0]),
                                     y_max + float(c[1]), *args, **kw)

    def _newest(self) -> float:
        est = self._nav.estimators.get(self._vehicle)
        track = est.track() if est is not None else np.zeros((0, 3))
        return float(track[-1, 0]) if len(track) else 0.0


class CorrectedDetections(_View):
    """A detections receiver whose rows are corrected (at each detection's stamp)."""

    def rows(self) -> list[dict[str, Any]]:
        rows = self._rx.rows()
        out = []
        for r in rows:
            t = r.get("stamp") or r.get("updated_at") or r.get("first_at") or 0.0
            x, y = self._nav.corrected(self._vehicle, float(t), float(r["x"]), float(r["y"]))
            out.append({**r, "x": round(x, 1), "y": round(y, 1)})
        return out


class CorrectedImages(_View):
    """An imagery receiver whose images' positions are corrected (at their capture time)."""

    def products(self) -> list[Product]:
        out = []
        for p in self._rx.products():
            meta = p.meta
            if p.kind == "image" and meta.get("x") is not None and meta.get("time") is not None:
                x, y = self._nav.corrected(self._vehicle, float(meta["time"]), float(meta["x"]), float(meta["y"]))
                p = Product(p.kind, p.key, p.version, p.data, {**meta, "x": round(x, 1), "y": round(y, 1)})
            out.append(p)
        return out


class VehicleFrameSurveys(_View):
    """A survey receiver whose commands are drawn in the corrected frame and sent in the vehicle's
    own: each point moved by the correction the vehicle will have when it gets there (from the end
    of the survey queued before it, or from where it is: :attr:`position`, corrected frame)."""

    #: where the vehicle sets off from for the next survey (corrected frame; None: where it was
    #: last heard of) and the correction predicted there (None: the correction now)
    position: tuple[float, float] | None = None
    carry: FloatArray | None = None
    #: when the surveys queued so far should be flown (1 m/s between them, their own speed along):
    #: after that the vehicle is where it was last heard of, with the correction of then
    busy_until: float = -math.inf

    def request(self, kind: Any, x: float, y: float, now: float, *, points: Sequence[tuple[float, float]] = (),
                **kw: Any) -> SurveyCommand:
        nav, vid = self._nav, self._vehicle
        est = nav.estimators.get(vid)
        if not nav.apply or est is None:
            return self._rx.request(kind, x, y, now, points=points, **kw)  # type: ignore[no-any-return]
        if now > self.busy_until:
            self.position, self.carry = None, None
        start = self.position
        if start is None:
            track = est.track()
            if len(track):
                start = nav.corrected(vid, float(track[-1, 0]), float(track[-1, 1]), float(track[-1, 2]))
        c = np.asarray(est.correction(now) if self.carry is None else self.carry, dtype=float)
        if start is not None:  # what the estimated biases add on the way there
            c = c + est.drift_along(now, x - start[0], y - start[1])
        path = [(x, y)]
        if kw.get("length") is not None and kw.get("heading") is not None:
            h = math.radians(float(kw["heading"]))
            path.append((x + float(kw["length"]) * math.sin(h), y + float(kw["length"]) * math.cos(h)))
        pts = []
        ends = np.array(c)
        for a, b in points:  # each further waypoint: the correction carried along the path
            prev = path[-1]
            ends = ends + est.drift_along(now, a - prev[0], b - prev[1])
            pts.append((a + float(ends[0]), b + float(ends[1])))
            path.append((a, b))
        cmd: SurveyCommand = self._rx.request(kind, x + float(c[0]), y + float(c[1]), now, points=pts, **kw)
        if kw.get("append"):
            if len(path) > 1 and not points:
                ends = c + est.drift_along(now, path[-1][0] - x, path[-1][1] - y)
            self.position, self.carry = path[-1], ends
            along = sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(path))
            transit = 0.0 if start is None else math.hypot(x - start[0], y - start[1])
            self.busy_until = max(self.busy_until, now) + transit / 1.0 + along / max(float(kw.get("speed") or 1.0), 0.1)
        return replace(cmd)

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

A vehicle whose navigation takes aiding can be sent topside's estimate of where it was
(:meth:`Navigation.aid`, a ``PositionFix`` of source ESTIMATE every :attr:`AidConfig.interval`
seconds): the vehicle takes each fix a set time after its stamp (its survey sender's
``aid_delay``) and blends the correction in (:attr:`AidConfig.blend`), so its own map is laid down
with a small error. Topside sent every aid, so it knows how the vehicle's frame moved: it keeps
the statuses as received, gives the estimator the track with the aids taken out (the
dead-reckoned track the model describes) and takes the aids' shift off the correction of
anything stamped after them (:meth:`Navigation.shift`).

The views below (:class:`CorrectedMap`, :class:`CorrectedDetections`, :class:`CorrectedImages`,
:class:`VehicleFrameSurveys`) wrap a topside receiver for a client that works in the corrected
frame (the demo's scripted operator, a script): what they read is corrected, what they send is
put back into the vehicle's frame. They hold no data of their own.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import Nav, Product, unwrap
from coex.messages import SurveyCommand, VehicleStatus

from ..bathymetry.product import MapLevel
from ..imagery.product import ImageProduct
from .estimator import DriftEstimator, NavConfig

__all__ = ["Aid", "AidConfig", "CorrectedDetections", "CorrectedImages", "CorrectedMap", "MapField", "Navigation",
           "VehicleFrameSurveys", "bridge_gaps"]

FloatArray = npt.NDArray[np.float64]
#: blocks of subgrids the correction of a big level is looked up in (the receiver's coverage)
MAP_BLOCKS = 4096
#: the received track is sampled every this many seconds to find the passes over a map block
PASS_STEP = 5.0
#: ... and counts as a pass of the multibeam only while the vehicle moves at least this fast (m/s):
#: a vehicle holding or descending on the spot is not surveying
PASS_SPEED = 0.2


@dataclass(frozen=True)
class AidConfig:
    """Topside aiding a vehicle's navigation with its estimate (:meth:`Navigation.aid`), and how
    that vehicle takes a fix (``docs/navigation.md``, "Aiding the vehicle")."""

    #: the vehicle takes a fix this long after its stamp (s): its survey sender's ``aid_delay``
    delay: float = 300.0
    #: the vehicle's navigation blends a fix's correction in linearly over this long (s; 0: at once)
    blend: float = 60.0
    #: seconds between two aids
    interval: float = 120.0
    #: an aid is sent only when the correction it would make is at least this (m) ...
    min_correction: float = 0.5
    #: ... and the estimate's 1-sigma at its stamp is at most this (m)
    max_sigma: float = 1.5
    #: no aid is sent that the vehicle would still be blending in after this time (None: no end)
    until: float | None = None


@dataclass
class Aid:
    """A position fix topside sent to aid the vehicle's navigation: its command id, stamp, position
    (as sent, rounded) and sigma; when the vehicle takes it (``at``) and blends it in (``blend``);
    the survey receiver's state of it ("requested", "accepted", "rejected", "given up"); and the
    correction it moves the vehicle's frame by (``delta``: believed less true at its stamp, in the
    frame of the aids before it; zero unless counted)."""

    command_id: int
    stamp: float
    x: float
    y: float
    sigma: float
    at: float
    blend: float
    sent: float
    state: str = "requested"
    delta: tuple[float, float] = (0.0, 0.0)

    @property
    def counted(self) -> bool:
        """Taken by the vehicle, as far as topside knows: accepted, or not answered yet (a fix
        goes out every ``fix_retry`` s until its time: it is the likely case). A refused one, or
        one given up without an answer, is not."""
        return self.state in ("requested", "accepted")


@dataclass(frozen=True)
class MapField:
    """The correction (believed less true, m) of a received map level over the vehicle's frame:
    one value per coverage block of side ``block`` m (``lut[row, col]``, block ``(col + kx0,
    row + ky0)``; NaN where nothing is held), bilinear between block centres when ``smooth`` (the
    pass-weighted corrections of :meth:`Navigation.map_correction`), else constant over each
    block; ``fill`` (the blocks' mean) outside them. Called with points ``(px, py)`` of the
    vehicle's frame it gives their corrections, ``(..., 2)``."""

    lut: FloatArray
    kx0: int
    ky0: int
    block: float
    fill: FloatArray
    smooth: bool

    @property
    def limit(self) -> float:
        """The largest correction of a block along either axis (m)."""
        return float(np.nanmax(np.abs(self.lut))) if np.isfinite(self.lut).any() else 0.0

    def __call__(self, px: FloatArray, py: FloatArray) -> FloatArray:
        lut, block, kx0, ky0 = self.lut, self.block, self.kx0, self.ky0
        if self.smooth:  # bilinear between block centres (over the blocks held)
            u, v = px / block - 0.5 - kx0, py / block - 0.5 - ky0
            j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
            fu, fv = (u - j0)[..., None], (v - i0)[..., None]
            acc = np.zeros((*px.shape, 2))
            wsum = np.zeros((*px.shape, 1))
            for di, dj, w in ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)), (1, 0, (1 - fu) * fv),
                              (1, 1, fu * fv)):
                ii, jj = i0 + di, j0 + dj
                inside = (ii >= 0) & (jj >= 0) & (ii < lut.shape[0]) & (jj < lut.shape[1])
                got = lut[np.clip(ii, 0, lut.shape[0] - 1), np.clip(jj, 0, lut.shape[1] - 1)]
                ok = (inside & np.isfinite(got[..., 0]))[..., None]
                acc += np.where(ok, w * got, 0.0)
                wsum += np.where(ok, w, 0.0)
            return np.asarray(np.where(wsum > 1e-9, acc / np.maximum(wsum, 1e-9), self.fill), np.float64)
        bx = np.floor(px / block).astype(np.int64) - kx0
        by = np.floor(py / block).astype(np.int64) - ky0
        inside = (bx >= 0) & (by >= 0) & (bx < lut.shape[1]) & (by < lut.shape[0])
        c = np.broadcast_to(self.fill, (*px.shape, 2)).copy()
        got = lut[np.clip(by, 0, lut.shape[0] - 1), np.clip(bx, 0, lut.shape[1] - 1)]
        ok = inside & np.isfinite(got[..., 0])
        c[ok] = got[ok]
        return c


class Navigation:
    """Topside's estimate of each vehicle's drift (see the module docstring). ``apply``: False
    keeps estimating (what the console shows) but :meth:`correction` is zero: the map, the
    images and commands stay in the vehicle's frame (the demo's ``--no-correction``).
    ``targets``: USBL target or transponder number -> vehicle node id (default: the number is the
    node id; a fix without one, such as a GGA, is the only vehicle's)."""

    def __init__(self, config: NavConfig | None = None, *, apply: bool = True,
                 targets: Mapping[int, int] | None = None, swath: float | None = None) -> None:
        self.config = config or NavConfig()
        self.apply = apply
        #: the vehicle's multibeam swath (degrees, across track): each subgrid is placed by the
        #: correction of the passes that mapped it (:meth:`map_correction`); None: by the
        #: correction at its stamp
        if swath is not None and not 0.0 < float(swath) < 180.0:
            raise ValueError(f"the swath must be 0-180 degrees, got {swath!r}")
        self.swath = None if swath is None else float(swath)
        self.targets = dict(targets or {})
        self.estimators: dict[int, DriftEstimator] = {}
        self._levels: dict[tuple[int, int, int], tuple[tuple[int, int], Any]] = {}
        self._fields: dict[tuple[int, int, int], tuple[tuple[int, int], MapField | None]] = {}
        #: per vehicle: the statuses as received (stamp -> x, y, heading: the vehicle's frame of the
        #: time), aiding's configuration and the aids sent (by stamp)
        self._received: dict[int, dict[float, tuple[float, float, float]]] = {}
        #: per vehicle: the altitude of each status received (stamp -> m; the swath's width)
        self._altitude: dict[int, dict[float, float]] = {}
        self.aiding: dict[int, AidConfig] = {}
        self.aids: dict[int, list[Aid]] = {}
        #: fixes that named no vehicle this topside follows
        self.unrouted = 0

    def estimator(self, vehicle: int) -> DriftEstimator:
        est = self.estimators.get(vehicle)
        if est is None:
            est = self.estimators[vehicle] = DriftEstimator(self.config)
        return est

    # ------------------------------------------------------------------ data in
    def status(self, vehicle: int, status: VehicleStatus, now: float) -> None:
        """A vehicle status topside received: a point of its dead-reckoned track at its stamp (the
        aids' shift taken out for the estimator)."""
        t = unwrap(status.stamp, now)
        x, y, h = float(status.x), float(status.y), float(status.heading)
        self._received.setdefault(vehicle, {})[t] = (x, y, h)
        if status.altitude is not None:
            self._altitude.setdefault(vehicle, {})[t] = float(status.altitude)
        s = self.shift(vehicle, t)
        self.estimator(vehicle).add_track(t, x + float(s[0]), y + float(s[1]), h)

    def track(self, vehicle: int) -> FloatArray:
        """The vehicle's track as received (t, x, y; its own frame at each time), in time order."""
        got = self._received.get(vehicle)
        if not got:
            return np.zeros((0, 3))
        tt = np.array(sorted(got))
        return np.column_stack([tt, np.array([got[t][:2] for t in tt.tolist()])])

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

    # ------------------------------------------------------------------ aiding the vehicle
    def shift(self, vehicle: int, t: npt.ArrayLike) -> FloatArray:
        """How far the aids topside counts as taken have moved the vehicle's frame by ``t``
        (``(..., 2)``, m): each aid's correction, blended in linearly from when the vehicle takes
        it. The vehicle believes it is at its dead-reckoned position less this."""
        times = np.asarray(t, float)
        out = np.zeros((*times.shape, 2))
        for a in self.aids.get(vehicle, ()):
            if not a.counted:
                continue
            f = (times >= a.at).astype(float) if a.blend <= 0 else np.clip((times - a.at) / a.blend, 0.0, 1.0)
            out += f[..., None] * np.asarray(a.delta)
        return out

    def final_shift(self, vehicle: int) -> FloatArray:
        """The shift once every aid counted is blended in (the frame the vehicle will be in)."""
        return np.asarray(sum((np.asarray(a.delta) for a in self.aids.get(vehicle, ()) if a.counted),
                              np.zeros(2)), dtype=np.float64)

    def _received_at(self, vehicle: int, t: float) -> tuple[float, float] | None:
        got = self._received.get(vehicle) or {}
        if t in got:
            return got[t][:2]
        track = self.track(vehicle)
        if not len(track):
            return None
        return float(np.interp(t, track[:, 0], track[:, 1])), float(np.interp(t, track[:, 0], track[:, 2]))

    def _rebuild(self, vehicle: int) -> None:
        """Work out each counted aid's correction in stamp order (as the vehicle does: its
        position at the stamp, in the frame of the aids before it, less the fix) and give the
        estimator the received track with the aids' shift taken out again."""
        total = np.zeros(2)
        for a in sorted(self.aids.get(vehicle, ()), key=lambda a: a.stamp):
            if not a.counted:
                a.delta = (0.0, 0.0)
                continue
            got = self._received_at(vehicle, a.stamp)
            if got is None:
                a.delta = (0.0, 0.0)
                continue
            raw = np.asarray(got) + self.shift(vehicle, a.stamp)  # the dead-reckoned position then
            d = raw - np.array([a.x, a.y]) - total
            a.delta = (float(d[0]), float(d[1]))
            total = total + d
        est = self.estimator(vehicle)
        track = self._received.get(vehicle) or {}
        if track:
            tt = np.array(sorted(track))
            sh = self.shift(vehicle, tt)
            for t, (dx, dy) in zip(tt.tolist(), sh.tolist(), strict=True):
                x, y, h = track[t]
                est.add_track(t, x + dx, y + dy, h)

    def aid(self, vehicle: int, receiver: Any, now: float) -> Aid | None:
        """Aid ``vehicle``'s navigation when it is time to (:attr:`aiding`, an
        :class:`AidConfig` per vehicle; nothing without): every :attr:`AidConfig.interval` seconds,
        a ``PositionFix`` through ``receiver`` (the vehicle's survey receiver) saying where the
        vehicle truly was at the newest status received, by the estimate (its dead-reckoned
        position then less the correction), when the correction it would make is worth it and
        the estimate good enough. Also follows the answers to the aids sent (a refused one is no
        longer counted). The aid sent, or None."""
        cfg = self.aiding.get(vehicle)
        if cfg is None:
            return None
        aids = self.aids.setdefault(vehicle, [])
        changed = False
        for a in aids:
            state = receiver.fixes.get(a.command_id)
            if state is not None and state[0] != a.state:
                a.state, changed = str(state[0]), True
        if changed:
            self._rebuild(vehicle)
        est = self.estimators.get(vehicle)
        if not self.apply or est is None or (aids and now - aids[-1].sent < cfg.interval):
            return None
        track = self.track(vehicle)
        if not len(track):
            return None
        stamp = float(track[-1, 0])
        if (aids and stamp <= aids[-1].stamp) or (cfg.until is not None and stamp + cfg.delay + cfg.blend > cfg.until):
            return None
        if est.solution() is None or float(est.sigma(stamp)) > cfg.max_sigma:
            return None
        c_raw = est.correction(stamp)
        if float(np.hypot(*(c_raw - self.final_shift(vehicle)))) < cfg.min_correction:
            return None
        raw = track[-1, 1:] + self.shift(vehicle, stamp)
        x, y = raw - c_raw
        fix = receiver.position_fix(float(x), float(y), now, stamp=stamp, sigma=float(est.sigma(stamp)),
                                    source="estimate")
        aid = Aid(int(fix.command_id), stamp, float(fix.x), float(fix.y), float(fix.sigma), stamp + cfg.delay,
                  cfg.blend, now)
        aids.append(aid)
        self._rebuild(vehicle)
        return aid

    # ------------------------------------------------------------------ the correction
    def estimate(self, vehicle: int, t: npt.ArrayLike) -> FloatArray:
        """The estimated correction (believed - true, m) of what the vehicle placed at times ``t``,
        in its frame of then (the aids' shift included), applied or not: ``(..., 2)``."""
        est = self.estimators.get(vehicle)
        times = np.asarray(t, float)
        if est is None:
            return np.zeros((*times.shape, 2))
        return np.asarray(est.correction(times) - self.shift(vehicle, times), dtype=np.float64)

    def correction(self, vehicle: int, t: npt.ArrayLike) -> FloatArray:
        """The correction applied (believed - true, m) at times ``t``: ``(..., 2)``; zeros when
        :attr:`apply` is off or nothing is known of the vehicle."""
        times = np.asarray(t, float)
        if not self.apply or vehicle not in self.estimators:
            return np.zeros((*times.shape, 2))
        return self.estimate(vehicle, times)

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
        vx, vy = est.to_vehicle(x, y, t, start)
        s = self.final_shift(vehicle)  # the frame the vehicle will be in once the aids sent are taken
        return vx - float(s[0]), vy - float(s[1])

    def corrected_level(self, receiver: Any, level: int, vehicle: int
                        ) -> tuple[FloatArray, float, tuple[float, float]] | None:
        """A bathymetry receiver's level in the corrected frame: ``(grid, cell, (x0, y0))``,
        row 0 south, NaN where nothing is held, or None. Each cell is taken from the received
        level where the correction of its subgrid (at the subgrid's stamp) puts it, bilinear
        between the four received cells around that point (the nearest where one of them is
        empty), so a subgrid moves whole by a fraction of a cell and two neighbours whose
        corrections differ meet without a gap. The received level's one-cell gaps (an empty cell
        between two held ones, :func:`bridge_gaps`) are read across first, so a cell whose
        source point falls in one is held; nothing is added beyond the held cells. Cached until
        the level or the estimate changes."""
        try:
            p = receiver.level_product(level)
        except Exception:
            return None
        if p.data is None:
            return None
        z = np.asarray(p.data, dtype=float)
        cell = float(p.cell_size)
        x0, y0 = float(p.x0), float(p.y0)
        est = self.estimators.get(vehicle)
        if not self.apply or est is None or est.solution() is None or z.size == 0:
            return z, cell, (x0, y0)
        key = (id(receiver), level, vehicle)
        stamp = (receiver.level_version(level), est.version)
        cached = self._levels.get(key)
        if cached is not None and cached[0] == stamp:
            return cached[1]  # type: ignore[no-any-return]
        out = self._resample(receiver, level, vehicle, z, cell, x0, y0)
        self._levels[key] = (stamp, out)
        return out

    def map_field(self, receiver: Any, level: int, vehicle: int) -> MapField | None:
        """The correction of a received map level as a field over the vehicle's frame
        (:class:`MapField`: each coverage block's :meth:`map_correction`), the one
        :meth:`corrected_level` resamples the level by and :meth:`place` moves points of it by;
        None when nothing is corrected (:attr:`apply` off, no estimate yet, nothing held).
        Cached until the level or the estimate changes."""
        est = self.estimators.get(vehicle)
        if not self.apply or est is None or est.solution() is None:
            return None
        key = (id(receiver), level, vehicle)
        stamp = (receiver.level_version(level), est.version)
        cached = self._fields.get(key)
        if cached is not None and cached[0] == stamp:
            return cached[1]
        geometry = receiver.geometry(level)
        span, keys, stamps = receiver.coverage(level, MAP_BLOCKS)
        out: MapField | None = None
        if geometry is not None and len(keys):
            level_cell, side = geometry
            block = float(level_cell) * int(side) * int(span)  # metres per coverage block
            # the correction of every coverage block (at its oldest stamp: one subgrid at fine levels)
            centres = (np.asarray(keys, float) + 0.5) * block
            corr = self.map_correction(vehicle, centres, np.asarray(stamps, float), block)
            kx0, ky0 = keys.min(axis=0)
            kx1, ky1 = keys.max(axis=0)
            lut = np.full((ky1 - ky0 + 1, kx1 - kx0 + 1, 2), np.nan)
            lut[keys[:, 1] - ky0, keys[:, 0] - kx0] = corr
            fill = np.nanmean(corr, axis=0) if np.isfinite(corr).any() else np.zeros(2)
            # pass-weighted corrections vary across blocks: bilinear between block centres, no tears
            out = MapField(lut, int(kx0), int(ky0), block, fill, self.swath is not None)
        self._fields[key] = (stamp, out)
        return out

    def place(self, receiver: Any, level: int, vehicle: int, x: npt.ArrayLike, y: npt.ArrayLike) -> FloatArray:
        """Points ``(x, y)`` of a received map level (the vehicle's frame, as received) in the
        corrected frame, ``(..., 2)``: each moved by the correction of the map where it lies
        (:meth:`map_field`), as :meth:`corrected_level` moves the cells around it. What is
        measured in the level as received (a bump's centre) is placed by this, without the
        corrected level's resampling (which spreads a one-cell peak over its neighbours)."""
        px, py = np.asarray(x, float), np.asarray(y, float)
        f = self.map_field(receiver, level, vehicle)
        c = np.zeros((*px.shape, 2)) if f is None else f(px, py)
        return np.stack([px - c[..., 0], py - c[..., 1]], axis=-1)

    def _resample(self, receiver: Any, level: int, vehicle: int, z: FloatArray, cell: float,
                  x0: float, y0: float) -> tuple[FloatArray, float, tuple[float, float]]:
        f = self.map_field(receiver, level, vehicle)
        if f is None:
            return z, cell, (x0, y0)
        field, fill = f, f.fill
        lim = f.limit
        pad = math.ceil(lim / cell) + 1
        ny, nx = z.shape
        oy, ox = ny + 2 * pad, nx + 2 * pad
        X0, Y0 = x0 - pad * cell, y0 - pad * cell
        qx = X0 + (np.arange(ox) + 0.5) * cell
        qy = Y0 + (np.arange(oy) + 0.5) * cell
        gx, gy = np.meshgrid(qx, qy)

        # where in the received level does each corrected cell come from: q + c(source), with the
        # source's correction found by two fixed-point steps
        c = field(gx + fill[0], gy + fill[1])
        c = field(gx + c[..., 0], gy + c[..., 1])
        # bilinear between the four source cells around that point (a subgrid lands where its
        # correction puts it, to a fraction of a cell); nearest where one of them is empty; the
        # received level's one-cell gaps bridged first (a point between two held cells is held)
        u = (gx + c[..., 0] - x0) / cell - 0.5
        v = (gy + c[..., 1] - y0) / cell - 0.5
        j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        fu, fv = u - j0, v - i0
        zp = np.pad(bridge_gaps(z), 1, constant_values=np.nan)  # index + 1: one empty cell all round

        def at(i: npt.NDArray[np.int64], j: npt.NDArray[np.int64]) -> FloatArray:
            return zp[np.clip(i + 1, 0, ny + 1), np.clip(j + 1, 0, nx + 1)]

        z00, z01, z10, z11 = at(i0, j0), at(i0, j0 + 1), at(i0 + 1, j0), at(i0 + 1, j0 + 1)
        out = (z00 * (1 - fu) * (1 - fv) + z01 * fu * (1 - fv) + z10 * (1 - fu) * fv + z11 * fu * fv)
        near = at(np.where(fv < 0.5, i0, i0 + 1), np.where(fu < 0.5, j0, j0 + 1))
        out = np.where(np.isfinite(out), out, near)
        return out, cell, (X0, Y0)

    def map_correction(self, vehicle: int, centres: FloatArray, stamps: FloatArray, size: float) -> FloatArray:
        """The correction (``n x 2``, m) of map blocks of side ``size`` m centred at ``centres``
        (the vehicle's frame) whose newest soundings date from ``stamps``. A block of the vehicle's
        map mixes the soundings of every pass over it, taken with different drifts (and a target
        keeps the place the densest pass gave it: the vehicle's outlier screen refuses a later
        sounding metres off the cell's mean). So with :attr:`swath` known, a block is placed by the
        mean of the correction over the moments the multibeam swath covered it, up to its stamp,
        each weighted by how densely an equiangular multibeam sounds there (``cos² θ``, ``θ`` the
        beam angle: ``h² / (h² + u²)`` at altitude ``h`` and ``u`` m across track); the received
        track (linear between statuses, every :data:`PASS_STEP` s) says where the vehicle was. A
        block no pass is known to have covered, or without :attr:`swath`, takes the correction at
        its stamp."""
        stamps = np.asarray(stamps, float)
        at_stamp = self.correction(vehicle, stamps)
        if self.swath is None or not self.apply or not len(stamps):
            return at_stamp
        track = self.track(vehicle)
        alt = self._altitude.get(vehicle) or {}
        if len(track) < 2 or not alt:
            return at_stamp
        t0, t1 = float(track[0, 0]), float(min(track[-1, 0], np.nanmax(stamps)))
        if t1 <= t0:
            return at_stamp
        ts = np.arange(t0, t1 + PASS_STEP, PASS_STEP)
        px = np.interp(ts, track[:, 0], track[:, 1])
        py = np.interp(ts, track[:, 0], track[:, 2])
        at = np.array(sorted(alt))
        h = np.interp(ts, at, np.array([alt[t] for t in at.tolist()]))
        vx, vy = np.gradient(px, ts), np.gradient(py, ts)
        speed = np.hypot(vx, vy)
        moving = speed >= PASS_SPEED
        ux, uy = np.where(moving, vx / np.maximum(speed, 1e-9), 0.0), np.where(moving, vy / np.maximum(speed, 1e-9), 0.0)
        reach = h * math.tan(math.radians(self.swath / 2.0))
        c = self.correction(vehicle, ts)
        out = at_stamp.copy()
        for i0 in range(0, len(centres), 256):  # blocks in batches: (blocks x samples) arrays
            q = centres[i0:i0 + 256]
            dx, dy = q[:, 0:1] - px[None, :], q[:, 1:2] - py[None, :]
            along = dx * ux[None, :] + dy * uy[None, :]
            across = np.abs(dx * uy[None, :] - dy * ux[None, :])
            hit = (moving[None, :] & (np.abs(along) <= size / 2.0 + PASS_STEP * speed[None, :] / 2.0)
                   & (across <= reach[None, :]) & (ts[None, :] <= stamps[i0:i0 + 256, None] + PASS_STEP))
            w = np.where(hit, h[None, :] ** 2 / (h[None, :] ** 2 + across**2), 0.0)
            total = w.sum(axis=1)
            ok = total > 0
            out[i0:i0 + 256][ok] = (w[ok] @ c) / total[ok, None]
        return out

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
        track = self.track(vehicle)
        sol = est.solution()
        out["fix_count"] = est.fix_count
        out["raw_track"] = [[round(float(a), 1), round(float(b), 1), round(float(c), 1)] for a, b, c in track[-2000:]]
        if sol is None:
            return out
        c_track = self.estimate(vehicle, track[:, 0]) if len(track) else np.zeros((0, 2))
        out["corrected_track"] = [[round(float(t), 1), round(float(x - cx), 1), round(float(y - cy), 1)]
                                  for (t, x, y), (cx, cy) in zip(track[-2000:], c_track[-2000:], strict=True)]
        fx = sol.fixes
        out["fixes"] = [[round(float(r[0]), 1), round(float(r[1]), 1), round(float(r[2]), 1), bool(r[3]), bool(r[4])]
                        for r in fx[-recent:]]
        out["outliers"] = int(fx[:, 4].sum())
        used = fx[fx[:, 3] > 0]
        newest = float(used[:, 0].max()) if len(used) else None
        c = self.estimate(vehicle, now)
        out["correction"] = {"dx": round(float(c[0]), 2), "dy": round(float(c[1]), 2),
                             "size": round(float(math.hypot(c[0], c[1])), 2),
                             "sigma": round(float(est.sigma(now)), 2),
                             "age": None if newest is None else round(max(now - newest, 0.0), 1),
                             "fix_sigma": round(sol.fix_sigma, 2)}
        aids = self.aids.get(vehicle, [])
        if aids:
            out["aids"] = {"sent": len(aids), "counted": sum(a.counted for a in aids),
                           "refused": sum(a.state == "rejected" for a in aids)}
        return out


def bridge_gaps(z: npt.ArrayLike) -> FloatArray:
    """A map level (NaN where empty) with its one-cell gaps bridged: an empty cell whose two
    neighbours along a row (west and east) or along a column (south and north) are both held
    takes their mean (the mean of all four where both pairs are held). Such a cell lies between
    held cells, inside what was received; nothing is added beyond the level's held cells (an
    empty cell at an edge, or in a gap two cells wide, stays empty).

    A vehicle's map has these gaps where its soundings skipped a cell of its own frame: half-way
    between two lines' swaths, or where its dead-reckoned frame stretched between two pings
    (the turns at the lines' ends). Topside's correction moves the map by fractions of a cell,
    so a corrected cell whose source point falls in such a gap would be empty although the
    ground around it was received (:meth:`Navigation.corrected_level`)."""
    a = np.asarray(z, dtype=np.float64)
    if a.ndim != 2 or a.size == 0:
        return a.copy()
    p = np.pad(a, 1, constant_values=np.nan)
    west, east = p[1:-1, :-2], p[1:-1, 2:]
    south, north = p[:-2, 1:-1], p[2:, 1:-1]
    row = np.isfinite(west) & np.isfinite(east)
    col = np.isfinite(south) & np.isfinite(north)
    total = np.where(row, west + east, 0.0) + np.where(col, south + north, 0.0)
    count = 2.0 * row + 2.0 * col
    gap = np.isnan(a) & (count > 0)
    return np.where(gap, total / np.maximum(count, 1.0), a)


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

    def level_product(self, level: int, now: float | None = None) -> MapLevel:
        p: MapLevel = self._rx.level_product(level) if now is None else self._rx.level_product(level, now)
        got = self._nav.corrected_level(self._rx, level, self._vehicle)
        if got is None:
            return p
        grid, cell, (x0, y0) = got
        return replace(p, data=grid, x0=x0, y0=y0, cell_size=cell, corrected=self._nav.apply)

    @property
    def received(self) -> Any:
        """The bathymetry receiver seen through this view: its levels as received (the
        vehicle's frame)."""
        return self._rx

    def place(self, level: int, x: npt.ArrayLike, y: npt.ArrayLike) -> FloatArray:
        """Points of the level as received (:attr:`received`) in the corrected frame,
        ``(..., 2)`` (:meth:`Navigation.place`): a bump measured in the received level, placed
        where the corrected level puts the cells around it."""
        return self._nav.place(self._rx, level, self._vehicle, x, y)

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
        track = self._nav.track(self._vehicle)
        return float(track[-1, 0]) if len(track) else 0.0


class CorrectedDetections(_View):
    """A detections receiver whose rows are corrected. A detection is stamped (its row's
    ``time``) with the newest data it rests on; one the vehicle found in its own map (source
    ``map``) is placed as the map around it is (:meth:`Navigation.map_correction`: with the
    swath known, the passes that mapped it up to its stamp), any other by the correction at its
    stamp. (Before issue 56's fourth pass every detection took the correction at the time its
    row last reached topside, ``updated_at``.)"""

    #: the side (m) of the map block a map detection is placed as (one 1 m subgrid's cells around it)
    block: float = 8.0

    def rows(self) -> list[dict[str, Any]]:
        rows = self._rx.rows()
        if not rows:
            return []
        t = np.array([float(r.get("time") or r.get("updated_at") or r.get("first_at") or 0.0) for r in rows])
        xy = np.array([(float(r["x"]), float(r["y"])) for r in rows])
        c = self._nav.correction(self._vehicle, t)
        mapped = np.array([r.get("source") == "map" for r in rows])
        if mapped.any() and self._nav.apply and self._vehicle in self._nav.estimators:
            c[mapped] = self._nav.map_correction(self._vehicle, xy[mapped], t[mapped], self.block)
        out = []
        for r, (x, y), (cx, cy) in zip(rows, xy, c, strict=True):
            out.append({**r, "x": round(float(x - cx), 1), "y": round(float(y - cy), 1)})
        return out


class CorrectedImages(_View):
    """An imagery receiver whose images' positions are corrected (at their capture time)."""

    def products(self) -> list[Product]:
        out = []
        for p in self._rx.products():
            if isinstance(p, ImageProduct) and p.x is not None and p.y is not None:
                x, y = self._nav.corrected(self._vehicle, float(p.time), float(p.x), float(p.y))
                p = replace(p, x=round(x, 1), y=round(y, 1))
            out.append(p)
        return out


class VehicleFrameSurveys(_View):
    """A survey receiver whose commands are drawn in the corrected frame and sent in the vehicle's
    own: each point moved by the correction the vehicle is predicted to have when it gets there.

    The prediction is made afresh at every command from the estimate *now* (never carried over
    from an earlier command's): the correction at the newest status, plus what the estimated
    heading bias adds over the displacement from where the vehicle was then to the point, plus
    what the estimated bias adds over the distance it will travel to get there, through the
    surveys it was sent before and has not flown yet (:attr:`plan`, topside's own idea of when
    each is flown: 1 m/s between them, their own speed along), relaxed by the time it gets there
    (:meth:`~.estimator.DriftEstimator.drift_along`)."""

    #: the vehicle's speed between surveys (m/s), for :attr:`plan`
    transit_speed: float = 1.0
    #: where the vehicle sets off from for the next survey (corrected frame: the end of the plan;
    #: None: where it was last heard of)
    position: tuple[float, float] | None = None
    #: when the surveys queued so far should be flown: after that the vehicle is where it was last
    #: heard of
    busy_until: float = -math.inf
    #: every command sent through the view: (survey id, when, the correction its first point was
    #: moved by, m): what topside predicted the vehicle's error to be when it gets there
    sent: list[tuple[int, float, tuple[float, float]]]

    @property
    def plan(self) -> list[tuple[float, float, tuple[float, float], tuple[float, float]]]:
        """The legs of the surveys queued (``append``) and not flown yet, as topside expects them:
        (from, until (s), start, end (corrected frame)), in the order the vehicle flies them."""
        plan: list[tuple[float, float, tuple[float, float], tuple[float, float]]] = self.__dict__.setdefault("_plan", [])
        return plan

    def _path_from(self, now: float, here: tuple[float, float], path: Sequence[tuple[float, float]],
                   speed: float) -> list[tuple[float, float, float]]:
        """The pieces the vehicle travels from ``here`` (now) through the plan's legs not yet
        flown, then along ``path`` (the first leg at the transit speed, the rest at ``speed``):
        (length, seconds from now to its middle, index in ``path`` of its end or -1) per piece."""
        pieces: list[tuple[float, float, float]] = []
        t = now
        pos = here
        for _t0, t1, _a, b in self.plan:
            if t1 <= now:
                continue
            d = math.hypot(b[0] - pos[0], b[1] - pos[1])
            end = max(t1, t + d / self.transit_speed)
            pieces.append((d, (t + end) / 2 - now, -1.0))
            t, pos = end, b
        for i, p in enumerate(path):
            d = math.hypot(p[0] - pos[0], p[1] - pos[1])
            dt = d / (self.transit_speed if i == 0 else max(speed, 0.1))
            pieces.append((d, t + dt / 2 - now, float(i)))
            t, pos = t + dt, p
        return pieces

    def request(self, kind: Any, x: float, y: float, now: float, *, points: Sequence[tuple[float, float]] = (),
                **kw: Any) -> SurveyCommand:
        nav, vid = self._nav, self._vehicle
        est = nav.estimators.get(vid)
        if not nav.apply or est is None:
            return self._rx.request(kind, x, y, now, points=points, **kw)  # type: ignore[no-any-return]
        plan = self.plan
        plan[:] = [leg for leg in plan if leg[1] > now] if now <= self.busy_until else []
        track = nav.track(vid)
        here = (nav.corrected(vid, float(track[-1, 0]), float(track[-1, 1]), float(track[-1, 2]))
                if len(track) else (plan[0][2] if plan else (x, y)))
        path = [(float(x), float(y))]
        if kw.get("length") is not None and kw.get("heading") is not None:
            h = math.radians(float(kw["heading"]))
            path.append((x + float(kw["length"]) * math.sin(h), y + float(kw["length"]) * math.cos(h)))
        path += [(float(a), float(b)) for a, b in points]
        speed = float(kw.get("speed") or 1.0)
        pieces = self._path_from(now, here, path, speed)
        # the correction now, in the frame the vehicle will be in once the aids sent are taken
        c_now = np.asarray(est.correction(now) - nav.final_shift(vid), dtype=float)
        moved = np.zeros(2)
        at: dict[int, FloatArray] = {}
        for d, mid, idx in pieces:  # the bias over the distance travelled, relaxed by then
            moved = moved + est.drift_along(now, 0.0, 0.0, distance=d, after=mid)
            if idx >= 0:
                p = path[int(idx)]
                turn = est.drift_along(now, p[0] - here[0], p[1] - here[1], distance=0.0)
                at[int(idx)] = c_now + moved + turn
        c = at[0]
        # the line's end is the vehicle's own (its start plus length along heading): only the
        # further waypoints are moved by their own prediction
        first = 2 if len(path) > 1 and kw.get("length") is not None and kw.get("heading") is not None else 1
        pts = [(a + float(at[i][0]), b + float(at[i][1])) for i, (a, b) in enumerate(path) if i >= first]
        cmd: SurveyCommand = self._rx.request(kind, x + float(c[0]), y + float(c[1]), now, points=pts, **kw)
        if "sent" not in self.__dict__:
            self.sent = []
        self.sent.append((int(cmd.survey_id), float(now), (float(c[0]), float(c[1]))))
        if kw.get("append"):
            t = max(now, self.busy_until)
            prev = plan[-1][3] if plan else here
            for i, p in enumerate(path):
                d = math.hypot(p[0] - prev[0], p[1] - prev[1])
                dt = d / (self.transit_speed if i == 0 else max(speed, 0.1))
                plan.append((t, t + dt, prev, p))
                t, prev = t + dt, p
            self.position, self.busy_until = path[-1], t
        return replace(cmd)

"""How the demo's vehicle navigates (issue 56): dead reckoning that drifts, and the ship's USBL.

:class:`DeadReckoning` is the vehicle's own position estimate. The simulation keeps the truth (the
:class:`~.world.Track`, what the camera sees and the referee judges); the vehicle believes it is
at ``truth + error(t)``. The error grows as a real DVL-aided INS's does
(``docs/navigation.md``):

* during the descent, without bottom lock, it grows in time to ``seed_offset`` metres at the
  bottom, in a direction the seed draws;
* then with the distance travelled: a slowly varying bias (a 2-D Ornstein-Uhlenbeck process of
  1-sigma ``drift`` metres per metre travelled, time scale :data:`BIAS_TIME`), a heading bias
  (the vehicle's heading reads ``heading_bias`` degrees clockwise of the truth, so every leg it
  travels is turned by that much) and a random walk of :data:`WALK` x ``drift`` metres per square
  root of the metres travelled.

Everything the vehicle reports is in its believed frame: multibeam soundings (the swath turned
by the heading bias about the vehicle, and moved by the error), image positions, status and so
the detections it finds in its own map; the waypoints of a survey command are flown in that frame
(:meth:`DeadReckoning.true_path`). ``drift = 0`` is perfect navigation, today's dive.

:class:`UsblTracker` is the ship's USBL: every ``interval`` seconds a fix of the vehicle's true
position with an error of 1-sigma ``sigma`` x the slant range (the radial, horizontal error;
``sigma / sqrt 2`` per axis) and, a fraction ``outliers`` of the time, a wild fix (multipath)
4 to 30 sigmas off. It writes each fix as an NMEA sentence (``$RATLL`` by default,
:func:`~coex_plugins.navigation.usbl.tll_sentence`) to a UDP port, where topside's
:class:`~coex_plugins.navigation.usbl.UsblInput` reads it like any ship's tracking system.
"""

from __future__ import annotations

import math
import socket
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from coex_plugins.navigation.frame import LocalFrame
from coex_plugins.navigation.usbl import gga_sentence, psimssb_sentence, tll_sentence

from .world import Track

__all__ = ["BIAS_TIME", "WALK", "DeadReckoning", "DiveNavigation", "UsblTracker", "track_positions"]

FloatArray = npt.NDArray[np.float64]

#: time scale (s) of the slowly varying dead-reckoning bias
BIAS_TIME = 1800.0
#: the random walk: this many ``drift`` per square root of the metres travelled
WALK = math.sqrt(10.0)
#: the grid (s) the error is integrated on
STEP = 1.0


def track_positions(track: Track, ts: FloatArray) -> FloatArray:
    """The track's true x, y at each time of ``ts`` (``n x 2``): :meth:`Track.position`,
    vectorised (a leg's position where a leg covers the time, else the survey sample)."""
    ts = np.asarray(ts, float)
    out = np.zeros((len(ts), 2))
    covered = np.zeros(len(ts), bool)
    for leg in track.legs:
        m = ~covered & (ts >= leg.t0) & (ts <= leg.t1)
        if not m.any():
            continue
        span = leg.t1 - leg.t0
        f = np.zeros(int(m.sum())) if span <= 0 else np.clip((ts[m] - leg.t0) / span, 0.0, 1.0)
        out[m, 0] = leg.p0[0] + f * (leg.p1[0] - leg.p0[0])
        out[m, 1] = leg.p0[1] + f * (leg.p1[1] - leg.p0[1])
        covered |= m
    rest = ~covered
    if rest.any() and track.samples:
        st = np.array([s[0] for s in track.samples])
        sxy = np.array([(s[1], s[2]) for s in track.samples])
        i = np.clip(np.searchsorted(st, ts[rest]), 0, len(st) - 1)
        out[rest] = sxy[i]
    return out


class DeadReckoning:
    """The vehicle's dead-reckoned position over ``track`` (the truth): see the module docstring.
    ``t0`` is when it leaves the surface with a GPS fix, ``bottom`` when it reaches the bottom
    (bottom lock), ``end`` the end of the dive."""

    def __init__(self, track: Track, t0: float, bottom: float, end: float, *, drift: float,
                 heading_bias: float, seed_offset: float, rng: np.random.Generator) -> None:
        self.track = track
        self.t0, self.bottom = float(t0), float(bottom)
        self.drift = float(drift)
        self.psi = math.radians(heading_bias)
        n = math.ceil((end + 600.0 - self.bottom) / STEP) + 2
        #: the grid after the bottom: times, the bias (n x 2), the random walk's unit draws
        self.times = self.bottom + STEP * np.arange(n)
        sd = self.drift / math.sqrt(2.0)
        a = math.exp(-STEP / BIAS_TIME)
        shocks = rng.normal(0.0, sd * math.sqrt(1.0 - a * a), (n, 2))
        bias = np.zeros((n, 2))
        bias[0] = rng.normal(0.0, sd, 2)
        for k in range(1, n):  # an AR(1) recursion: sequential by nature (once per dive)
            bias[k] = a * bias[k - 1] + shocks[k]
        self.bias = bias
        self.walk = rng.normal(0.0, 1.0, (n, 2)) * (WALK * self.drift)
        angle = rng.uniform(0.0, 2.0 * math.pi)
        #: the error at the bottom (believed - true)
        self.at_bottom = np.array([math.sin(angle), math.cos(angle)]) * float(seed_offset)
        self._err = np.zeros((n, 2))
        self._err[0] = self.at_bottom
        self._done = 0  # the grid index the error is integrated to

    @property
    def active(self) -> bool:
        """False with ``drift = 0``: perfect navigation (the vehicle knows where it is)."""
        return self.drift > 0.0

    # ------------------------------------------------------------------ the error
    def _increments(self, k0: int, pos: FloatArray) -> FloatArray:
        """The error's steps from grid index ``k0`` along true positions ``pos`` (one per grid
        point from ``k0``): bias x distance, the heading bias's turn of each step, the walk."""
        step = np.diff(pos, axis=0)
        d = np.hypot(step[:, 0], step[:, 1])
        m = len(d)
        turn = self.psi * np.column_stack([step[:, 1], -step[:, 0]])
        return self.bias[k0:k0 + m] * d[:, None] + turn + self.walk[k0:k0 + m] * np.sqrt(d)[:, None]

    def _integrate(self, k: int) -> None:
        """Integrate the error to grid index ``k`` along the track as flown."""
        k = min(k, len(self.times) - 1)
        if k <= self._done:
            return
        pos = track_positions(self.track, np.asarray(self.times[self._done:k + 1], dtype=np.float64))
        self._err[self._done + 1:k + 1] = self._err[self._done] + np.cumsum(
            self._increments(self._done, pos), axis=0)
        self._done = k

    def error(self, t: float) -> FloatArray:
        """Believed less true position (m) at ``t`` (``t`` no later than now: the track beyond
        it may still change)."""
        if not self.active:
            return np.zeros(2)
        if t <= self.bottom:  # the descent: no bottom lock, the error grows in time
            f = 0.0 if self.bottom <= self.t0 else min(max((t - self.t0) / (self.bottom - self.t0), 0.0), 1.0)
            return self.at_bottom * f
        k = min(int((t - self.bottom) // STEP), len(self.times) - 2)
        self._integrate(k)
        pos = track_positions(self.track, np.array([self.times[k], t]))
        return np.asarray(self._err[k] + self._increments(k, pos)[0], dtype=np.float64)

    def believed(self, t: float, x: float, y: float) -> tuple[float, float]:
        """Where the vehicle believes it is at ``t`` when truly at ``(x, y)``."""
        e = self.error(t)
        return float(x + e[0]), float(y + e[1])

    def believed_points(self, xyz: FloatArray, t: float, centre: tuple[float, float]) -> FloatArray:
        """Soundings as the vehicle places them: turned by the heading bias about the vehicle
        (``centre``, true) and moved by the error at ``t``."""
        if not self.active:
            return xyz
        e = self.error(t)
        c, s = math.cos(self.psi), math.sin(self.psi)
        dx, dy = xyz[:, 0] - centre[0], xyz[:, 1] - centre[1]
        out = np.array(xyz, dtype=float, copy=True)
        out[:, 0] = centre[0] + c * dx + s * dy + e[0]
        out[:, 1] = centre[1] - s * dx + c * dy + e[1]
        return out

    def heading(self, heading: float) -> float:
        """The heading the vehicle reads when truly heading ``heading`` (degrees)."""
        return (heading + math.degrees(self.psi)) % 360.0 if self.active else heading

    def true_path(self, now: float, start: tuple[float, float], waypoints: Sequence[tuple[float, float]],
                  speeds: Sequence[float]) -> list[tuple[float, float]]:
        """Where the vehicle truly goes when it flies ``waypoints`` of its own frame from
        ``start`` (true) at ``now``: leg ``i`` (to waypoint ``i``) at ``speeds[i]``. Each waypoint
        is reached where the vehicle believes it is there: less the error it will have by then
        (predicted along the path with the same bias and walk the dive then draws)."""
        wps = np.asarray(waypoints, float)
        if not self.active or len(wps) == 0:
            return [tuple(map(float, w)) for w in wps]  # type: ignore[misc]
        e_now = self.error(now)
        true = wps - e_now
        for _ in range(3):
            pts = np.vstack([np.asarray(start, float), true])
            legs = np.hypot(*np.diff(pts, axis=0).T)
            arrive = now + np.cumsum(legs / np.maximum(np.asarray(speeds, float), 1e-6))
            k0 = min(max(int((now - self.bottom) // STEP), 0), len(self.times) - 2)
            k1 = min(int((arrive[-1] - self.bottom) // STEP) + 2, len(self.times) - 1)
            grid = np.concatenate([[now], self.times[k0 + 1:k1 + 1]])
            tknots = np.concatenate([[now], arrive])
            pos = np.column_stack([np.interp(grid, tknots, pts[:, 0]), np.interp(grid, tknots, pts[:, 1])])
            inc = self._increments(k0, pos)
            err = np.vstack([e_now, e_now + np.cumsum(inc, axis=0)])
            at = np.column_stack([np.interp(arrive, grid, err[:, 0]), np.interp(arrive, grid, err[:, 1])])
            true = wps - at
        return [(float(a), float(b)) for a, b in true]


class UsblTracker:
    """The ship's USBL (see the module docstring): :meth:`fix` draws a fix of a vehicle, and
    :meth:`send` writes it as an NMEA sentence to ``address`` (UDP)."""

    FORMATS = ("tll", "psimssb", "gga")

    def __init__(self, ship: tuple[float, float], frame: LocalFrame, *, sigma: float, outliers: float,
                 rng: np.random.Generator, address: tuple[str, int] | None = None, form: str = "tll",
                 epoch_utc: Callable[[float], float] = float) -> None:
        if form not in self.FORMATS:
            raise ValueError(f"USBL format must be one of {', '.join(self.FORMATS)}")
        self.ship = ship
        self.frame = frame
        self.sigma = float(sigma)
        self.outliers = float(outliers)
        self.rng = rng
        self.form = form
        self.address = address
        self._sock: socket.socket | None = None
        #: every fix drawn: t, target, true x, y, fix x, y, wild (for the report)
        self.log: list[tuple[float, int, float, float, float, float, bool]] = []

    def fix(self, t: float, target: int, x: float, y: float, depth: float) -> tuple[float, float, bool]:
        """A fix of the vehicle truly at ``(x, y)`` and ``depth``: its x, y and whether it is wild."""
        slant = math.sqrt((x - self.ship[0]) ** 2 + (y - self.ship[1]) ** 2 + depth**2)
        sd = self.sigma * slant / math.sqrt(2.0)
        nx, ny = self.rng.normal(0.0, sd, 2)
        wild = bool(self.rng.random() < self.outliers)
        if wild:
            angle = self.rng.uniform(0.0, 2.0 * math.pi)
            size = self.rng.uniform(4.0, 30.0) * max(sd, 0.5)
            nx, ny = nx + size * math.sin(angle), ny + size * math.cos(angle)
        fx, fy = x + float(nx), y + float(ny)
        self.log.append((t, target, x, y, fx, fy, wild))
        return fx, fy, wild

    def sentence(self, t: float, target: int, fx: float, fy: float, depth: float) -> str:
        lat, lon = self.frame.geodetic(fx, fy)
        if self.form == "psimssb":
            e, n = self.frame.to_utm(fx, fy)
            return psimssb_sentence(t, target, e, n, depth)
        if self.form == "gga":
            return gga_sentence(t, lat, lon, -depth)
        return tll_sentence(t, target, lat, lon)

    def send(self, t: float, target: int, x: float, y: float, depth: float) -> str:
        """Draw a fix and write it to the UDP address (if any); the sentence."""
        fx, fy, _ = self.fix(t, target, x, y, depth)
        line = self.sentence(t, target, fx, fy, depth)
        if self.address is not None:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.sendto((line + "\r\n").encode("ascii"), self.address)
        return line

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def summary(self) -> dict[str, Any]:
        n = len(self.log)
        return {"fixes": n, "wild": sum(1 for r in self.log if r[6]), "format": self.form,
                "sigma": self.sigma, "outliers": self.outliers}


# ================================================================================ the dive's hooks
class DiveNavigation:
    """Navigation in one dive (:class:`~.run.DiveRun`): each vehicle's :class:`DeadReckoning`,
    the ship's :class:`UsblTracker` writing to topside's
    :class:`~coex_plugins.navigation.usbl.UsblInput` over UDP, and topside's
    :class:`~coex_plugins.navigation.Navigation` (the estimate; applied unless the dive runs with
    ``--no-correction``). With ``drift = 0`` nothing is active: every hook gives back what it got,
    no fix is drawn and no event is scheduled (today's dive)."""

    def __init__(self, run: Any) -> None:
        from coex import InputContext
        from coex_plugins.navigation import Navigation, UsblInput

        from .config import CAMERA, EPOCH, VEHICLE
        from .world import rng_for

        self.run = run
        scn, cfg = run.scn, run.cfg
        bottom = EPOCH + run.descent
        self.models: dict[int, DeadReckoning] = {
            VEHICLE: DeadReckoning(run.track, EPOCH, bottom, run.end, drift=scn.drift, heading_bias=scn.heading_bias,
                                   seed_offset=scn.seed_offset, rng=rng_for(cfg.seed, 560))}
        self.tracks: dict[int, Track] = {VEHICLE: run.track}
        if run.fleet is not None:
            self.models[CAMERA] = DeadReckoning(run.camera_track, EPOCH, bottom, run.end, drift=scn.drift,
                                                heading_bias=scn.heading_bias, seed_offset=scn.seed_offset,
                                                rng=rng_for(cfg.seed, 561))
            self.tracks[CAMERA] = run.camera_track
        self.camera_vehicle = CAMERA if run.fleet is not None else VEHICLE
        self.active = scn.drift > 0.0
        self.navigation = Navigation(apply=bool(getattr(cfg, "correction", True)))
        for v in self.models:
            self.navigation.estimator(v)
        self.input: Any = None
        self.tracker: UsblTracker | None = None
        self.stats = {"fixes_read": 0}
        if not self.active:
            return
        self.input = UsblInput({"udp": "127.0.0.1:0"}, InputContext(0.0, 0.0))
        self.input.open()
        address = self.input.udp_address()
        self.tracker = UsblTracker(scn.ship, self.input.frame, sigma=scn.usbl_sigma, outliers=scn.usbl_outliers,
                                   rng=rng_for(cfg.seed, 562), address=address)
        t = EPOCH + scn.usbl_interval
        while t < run.end:
            run.at(t, self.usbl_round)
            t += scn.usbl_interval

    # ------------------------------------------------------------------ the vehicle's side
    def model(self, vehicle: int) -> DeadReckoning:
        return self.models.get(vehicle, self.models[min(self.models)])

    def status(self, vehicle: int, status: Any, now: float) -> Any:
        """The status the vehicle sends: its believed position and heading."""
        if not self.active:
            return status
        from dataclasses import replace

        dr = self.model(vehicle)
        x, y = dr.believed(now, status.x, status.y)
        return replace(status, x=round(x, 1), y=round(y, 1), heading=round(dr.heading(status.heading) % 359.9, 1))

    def soundings(self, xyz: FloatArray, pings: npt.NDArray[np.int64], times: FloatArray) -> FloatArray:
        """A batch of soundings as the vehicle places them: each ping turned by the heading bias
        about the vehicle (the ping's centre) and moved by the error at its time (linear over the
        batch)."""
        if not self.active or len(xyz) == 0:
            return xyz
        dr = self.model(min(self.models))
        _, inv = np.unique(pings, return_inverse=True)
        n = np.bincount(inv).astype(float)
        cx = (np.bincount(inv, xyz[:, 0]) / n)[inv]
        cy = (np.bincount(inv, xyz[:, 1]) / n)[inv]
        e0, e1 = dr.error(float(times[0])), dr.error(float(times[-1]))
        span = float(times[-1] - times[0])
        f = (times - times[0]) / span if span > 0 else np.ones(len(times))
        c, s = math.cos(dr.psi), math.sin(dr.psi)
        dx, dy = xyz[:, 0] - cx, xyz[:, 1] - cy
        out = np.array(xyz, dtype=float, copy=True)
        out[:, 0] = cx + c * dx + s * dy + e0[0] + f * (e1[0] - e0[0])
        out[:, 1] = cy - s * dx + c * dy + e0[1] + f * (e1[1] - e0[1])
        return out

    def believed(self, vehicle: int, now: float, x: float, y: float) -> tuple[float, float]:
        return self.model(vehicle).believed(now, x, y) if self.active else (x, y)

    # ------------------------------------------------------------------ the ship's side
    def usbl_round(self, now: float) -> None:
        """The ship's USBL fixes every vehicle; topside reads the sentences from its UDP port."""
        assert self.tracker is not None
        for vehicle, track in self.tracks.items():
            x, y, depth, _alt, _h = track.position(now)
            self.tracker.send(now, vehicle, x, y, depth)
        self.read_fixes(now)

    def read_fixes(self, now: float) -> None:
        if self.input is None:
            return
        for item in self.input.poll(now):
            if self.navigation.fix(item) is not None:
                self.stats["fixes_read"] += 1

    def heard_status(self, vehicle: int, status: Any, now: float) -> Any:
        """A status topside received: a point of the vehicle's track for the estimate; the
        status in the corrected frame (what the operator follows)."""
        if not self.active:
            return status
        from dataclasses import replace

        from coex import unwrap

        self.navigation.status(vehicle, status, now)
        x, y = self.navigation.corrected(vehicle, unwrap(status.stamp, now), status.x, status.y)
        return replace(status, x=round(x, 1), y=round(y, 1))

    def views(self, receivers: dict[str, Any]) -> dict[str, Any]:
        """The receivers as the operator (and the outputs) see them: in the corrected frame."""
        if not self.active:
            return receivers
        from coex_plugins.navigation import (
            CorrectedDetections,
            CorrectedImages,
            CorrectedMap,
            VehicleFrameSurveys,
        )

        from .config import VEHICLE

        nav, cam = self.navigation, self.camera_vehicle
        out = dict(receivers)
        out["bathymetry"] = CorrectedMap(receivers["bathymetry"], nav, VEHICLE)
        if receivers.get("detections") is not None:
            out["detections"] = CorrectedDetections(receivers["detections"], nav, VEHICLE)
        out["imagery"] = CorrectedImages(receivers["imagery"], nav, cam)
        out["survey"] = VehicleFrameSurveys(receivers["survey"], nav, cam)
        return out

    def close(self) -> None:
        if self.tracker is not None:
            self.tracker.close()
        if self.input is not None:
            self.input.close()

    # ------------------------------------------------------------------ judged against the truth
    def metrics(self, cars: Sequence[Any], candidates: Sequence[Any], camera_legs: Sequence[Any], end: float
                ) -> dict[str, Any]:
        """``metrics.json`` ``navigation``: ``drift_at_end_m`` (true less believed position at
        the end of the dive, m) and per true target ``x``, ``y`` (truth), ``map_error_m`` (the
        corrected topside map's estimate of it, the nearest car-like candidate within
        :data:`MAP_MATCH` m, against the truth; null if none) and ``camera_pass_m`` (closest
        distance of the camera's true track to its centre; null if the camera never went); and
        how the estimate did against the truth."""
        from .operator import MIN_SCORE

        dr = self.model(self.camera_vehicle)
        out: dict[str, Any] = {
            "drift_at_end_m": round(float(np.hypot(*dr.error(end))), 2),
            "correction": "on" if self.navigation.apply else "off",
            "active": self.active,
        }
        targets = []
        for car in cars:
            near = [(math.hypot(c.x - car.x, c.y - car.y), c) for c in candidates if c.score >= MIN_SCORE]
            best = min(near, key=lambda d: d[0], default=None)
            targets.append({"x": car.x, "y": car.y,
                            "map_error_m": round(best[0], 2) if best is not None and best[0] <= MAP_MATCH else None,
                            "camera_pass_m": _closest(camera_legs, car.x, car.y)})
        out["targets"] = targets
        if self.active:
            out["estimate"] = {str(v): self._judge(v) for v in self.models}
            out["usbl"] = {**(self.tracker.summary() if self.tracker else {}), "fixes_read": self.stats["fixes_read"],
                           "input_counts": dict(self.input.counts) if self.input is not None else {}}
        return out

    def _judge(self, vehicle: int) -> dict[str, Any]:
        """The smoothed correction against the true error, at the times of the track topside
        received; the fixes flagged wild against the truth."""
        est = self.navigation.estimator(vehicle)
        track = est.track()
        sol = est.solution()
        dr = self.model(vehicle)
        if sol is None or not len(track):
            return {"track_points": len(track), "fixes": est.fix_count}
        truth = np.array([dr.error(float(t)) for t in track[:, 0]])
        err = np.hypot(*(est.correction(track[:, 0]) - truth).T)
        wild = {round(r[0], 3) for r in (self.tracker.log if self.tracker else []) if r[1] == vehicle and r[6]}
        flagged = {round(float(r[0]), 3) for r in sol.fixes if r[4] > 0}
        used = {round(float(r[0]), 3) for r in sol.fixes if r[3] > 0}
        return {"track_points": len(track), "fixes": est.fix_count,
                "error_median_m": round(float(np.median(err)), 2), "error_p95_m": round(float(np.percentile(err, 95)), 2),
                "error_max_m": round(float(err.max()), 2), "fix_sigma_m": round(sol.fix_sigma, 2),
                "wild_fixes": len(wild), "flagged": len(flagged), "wild_flagged": len(wild & flagged),
                "wild_used": len(wild & used), "fixes_used": len(used)}


#: a target's map estimate is the nearest car-like candidate within this distance (m)
MAP_MATCH = 25.0


def _closest(legs: Sequence[Any], x: float, y: float) -> float | None:
    """Closest distance (m) of the camera legs (straight, true) to ``(x, y)``; None without legs."""
    best = math.inf
    for leg in legs:
        (ax, ay), (bx, by) = leg.p0, leg.p1
        dx, dy = bx - ax, by - ay
        seg = dx * dx + dy * dy
        f = 0.0 if seg == 0 else min(max(((x - ax) * dx + (y - ay) * dy) / seg, 0.0), 1.0)
        best = min(best, math.hypot(ax + f * dx - x, ay + f * dy - y))
    return None if best == math.inf else round(best, 2)

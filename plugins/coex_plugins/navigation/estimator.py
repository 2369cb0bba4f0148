"""One estimate of the vehicle's dead-reckoning drift: a Kalman filter with a Rauch-Tung-Striebel
smoother over the vehicle's dead-reckoned track and the ship's USBL fixes (``docs/navigation.md``).

Sans-I/O: data goes in with its own time stamps (:meth:`DriftEstimator.add_track`,
:meth:`DriftEstimator.add_fix`), and the correction comes out for any times asked
(:meth:`DriftEstimator.correction`, vectorised over an array of times). Nothing here reads a
clock, sleeps or opens a socket.

The **correction** ``c(t)`` is the vehicle's believed (dead-reckoned) position less its true
position at time ``t``: a point the vehicle placed at ``p`` at time ``t`` (a sounding, an image,
a detection, a status) is truly at ``p - c(t)``; a point ``q`` of the true (corrected) frame is
``q + c(t)`` in the vehicle's own frame.

The state is ``[cx, cy, bx, by, psi]``: the correction, a slowly varying bias of the
dead-reckoning (metres of error per metre travelled, east and north) and a heading bias (rad,
the vehicle's heading reads ``psi`` clockwise of the truth). Between two points of the
dead-reckoned track the vehicle moved ``(dx, dy)`` over ``d`` metres, and the correction grows
by ``b * d + psi * (dy, -dx)`` plus a random walk in the distance travelled (and a little in
time: currents while the vehicle has no bottom lock). A USBL fix ``f`` at time ``t`` measures
``c(t) = p(t) - f`` with ``p(t)`` the dead-reckoned position interpolated at ``t``.

Outliers are rejected twice: in the filter, a fix whose innovation lies beyond the gate
(Mahalanobis distance, :attr:`NavConfig.gate`) is not used; after smoothing, fixes whose residual
to the smoothed correction exceeds :attr:`NavConfig.reject` robust standard deviations are
dropped and the filter and smoother run again. The fixes' spread is learnt from the residuals
(median absolute deviation), so the estimator needs no USBL accuracy figure to be right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

__all__ = ["DriftEstimator", "NavConfig", "Solution"]

FloatArray = npt.NDArray[np.float64]
_N = 5  # state size


@dataclass(frozen=True)
class NavConfig:
    """The estimator's model (defaults suit a DVL-aided INS and a ship's USBL; docs/navigation.md)."""

    #: 1-sigma dead-reckoning bias, fraction of the distance travelled (prior and its spread)
    drift: float = 0.005
    #: the bias's time scale (s): how slowly it varies
    drift_time: float = 1800.0
    #: 1-sigma heading bias prior (degrees)
    heading_sigma: float = 1.0
    #: random walk of the correction per metre travelled (m per sqrt(m))
    walk: float = 0.02
    #: random walk of the correction in time (m per sqrt(s)): currents, no bottom lock
    time_walk: float = 0.01
    #: 1-sigma of the correction before any fix (m)
    prior: float = 20.0
    #: the fixes' 1-sigma error per axis (m) to start with; learnt from the residuals after
    fix_sigma: float = 5.0
    #: the learnt fix sigma is kept at least this (m)
    min_fix_sigma: float = 0.3
    #: innovation gate of the filter (Mahalanobis distance, 2 degrees of freedom)
    gate: float = 4.0
    #: fixes whose residual to the smoothed correction exceeds this many robust sigmas are outliers
    reject: float = 3.5
    #: a fix is used only where the dead-reckoned track is known: between two track points at
    #: most this far apart in time (s) ...
    max_gap: float = 180.0
    #: ... and, when the vehicle moved between them, with headings within this of the leg's (deg)
    max_turn: float = 25.0
    #: or at most this long after the newest track point (extrapolated at its velocity, s)
    extrapolate: float = 30.0


@dataclass
class Solution:
    """The smoothed correction on the estimator's time grid, and what went into it."""

    #: grid times (s), smoothed states (n x 5) and their covariances (n x 5 x 5)
    times: FloatArray
    states: FloatArray
    covs: FloatArray
    #: every fix: time, x, y, used (bool), outlier (bool), residual to the smoothed correction (m)
    fixes: FloatArray = field(default_factory=lambda: np.zeros((0, 6)))
    #: the fixes' learnt 1-sigma per axis (m)
    fix_sigma: float = 0.0


def _interp_track(tt: FloatArray, xy: FloatArray, t: FloatArray) -> FloatArray:
    return np.column_stack([np.interp(t, tt, xy[:, 0]), np.interp(t, tt, xy[:, 1])])


class DriftEstimator:
    """The drift estimate (see the module docstring). ``config``: the model (:class:`NavConfig`)."""

    def __init__(self, config: NavConfig | None = None) -> None:
        self.config = config or NavConfig()
        self._track: dict[float, tuple[float, float, float]] = {}  # t -> x, y, heading (nan: unknown)
        self._fixes: list[tuple[float, float, float]] = []
        self._version = 0
        self._solved: tuple[int, Solution] | None = None
        #: warm start of the next solve: the fixes' learnt sigma and the outliers found
        self._sigma: float | None = None
        self._outliers: set[float] = set()

    # ------------------------------------------------------------------ data in
    def add_track(self, t: float, x: float, y: float, heading: float | None = None) -> None:
        """A point of the vehicle's dead-reckoned track: where it believed it was at ``t`` (a
        status, an image's position); the same time again replaces it."""
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)):
            return
        self._track[float(t)] = (float(x), float(y), math.nan if heading is None else float(heading))
        self._version += 1

    def add_fix(self, t: float, x: float, y: float) -> None:
        """A USBL fix: where the ship's tracking system saw the vehicle at ``t`` (local frame)."""
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)):
            return
        self._fixes.append((float(t), float(x), float(y)))
        self._version += 1

    @property
    def version(self) -> int:
        """Grows with every track point and fix added (the solution is cached per version)."""
        return self._version

    @property
    def fix_count(self) -> int:
        return len(self._fixes)

    @property
    def track_count(self) -> int:
        return len(self._track)

    def track(self) -> FloatArray:
        """The dead-reckoned track received: ``n x 3`` (t, x, y), in time order."""
        if not self._track:
            return np.zeros((0, 3))
        tt = np.array(sorted(self._track))
        xy = np.array([self._track[t][:2] for t in tt.tolist()])
        return np.column_stack([tt, xy])

    # ------------------------------------------------------------------ the estimate
    def solution(self) -> Solution | None:
        """The smoothed solution (None before the first usable fix)."""
        if self._solved is not None and self._solved[0] == self._version:
            return self._solved[1]
        sol = self._solve()
        if sol is not None:
            self._solved = (self._version, sol)
        return sol

    def correction(self, t: npt.ArrayLike) -> FloatArray:
        """The smoothed correction (believed - true, metres) at each time of ``t``: shape
        ``(..., 2)``; zeros before any usable fix. Before the first and after the last point of
        the grid it is held at the nearest (the live estimate at the newest)."""
        times = np.asarray(t, dtype=float)
        sol = self.solution()
        if sol is None:
            return np.zeros((*times.shape, 2))
        cx = np.interp(times, sol.times, sol.states[:, 0])
        cy = np.interp(times, sol.times, sol.states[:, 1])
        return np.stack([cx, cy], axis=-1)

    def sigma(self, t: npt.ArrayLike) -> FloatArray:
        """The 1-sigma of the smoothed correction (m, the larger axis) at each time of ``t``."""
        times = np.asarray(t, dtype=float)
        sol = self.solution()
        if sol is None:
            return np.full(times.shape, math.inf)
        sd = np.sqrt(np.maximum(sol.covs[:, 0, 0], sol.covs[:, 1, 1]))
        return np.asarray(np.interp(times, sol.times, sd), dtype=np.float64)

    def drift_along(self, t: float, dx: float, dy: float, distance: float | None = None, after: float = 0.0
                    ) -> FloatArray:
        """What the estimated bias and heading bias (at ``t``) add to the correction while the
        vehicle moves ``(dx, dy)`` metres (zeros before any solution). ``distance``: the metres it
        travels doing so (default: the straight line; the bias grows with the distance travelled,
        the heading bias with the displacement); ``after``: how many seconds after ``t`` it does so,
        by when the bias is expected to have relaxed toward zero by ``exp(-after / drift_time)``
        (the model's bias is a slowly varying process of that time scale, not a constant)."""
        sol = self.solution()
        if sol is None:
            return np.zeros(2)
        i = int(np.clip(np.searchsorted(sol.times, t), 0, len(sol.times) - 1))
        bx, by, psi = sol.states[i, 2:]
        d = math.hypot(dx, dy) if distance is None else float(distance)
        d *= math.exp(-max(float(after), 0.0) / self.config.drift_time)
        return np.array([bx * d + psi * dy, by * d - psi * dx], dtype=np.float64)

    def predict(self, t: float, dx: float, dy: float) -> FloatArray:
        """The correction expected after the vehicle, from time ``t``, moves ``(dx, dy)`` metres
        in a straight line: the correction at ``t`` plus what the estimated bias and heading bias
        add over that leg (:meth:`drift_along`)."""
        return np.asarray(self.correction(t) + self.drift_along(t, dx, dy), dtype=np.float64)

    def to_vehicle(self, x: float, y: float, t: float, start: tuple[float, float] | None = None
                   ) -> tuple[float, float]:
        """A point of the true (corrected) frame in the vehicle's own frame, for the vehicle to go
        there after ``t``: ``start`` (true frame) is where it sets off from (None: the correction at
        ``t`` alone)."""
        c = self.correction(t) if start is None else self.predict(t, x - start[0], y - start[1])
        return float(x + c[0]), float(y + c[1])

    # ------------------------------------------------------------------ the solver
    def _usable(self, tt: FloatArray, txy: FloatArray, heading: FloatArray, ft: FloatArray
                ) -> npt.NDArray[np.bool_]:
        """Fixes at times where the dead-reckoned track is known well enough to compare with."""
        cfg = self.config
        n = len(tt)
        j = np.searchsorted(tt, ft, side="right")  # tt[j-1] <= ft < tt[j]
        ok = np.zeros(len(ft), bool)
        inside = (j > 0) & (j < n)
        a = np.clip(j - 1, 0, n - 1)
        b = np.clip(j, 0, n - 1)
        gap = tt[b] - tt[a]
        step = txy[b] - txy[a]
        moved = np.hypot(step[:, 0], step[:, 1])
        bearing = np.degrees(np.arctan2(step[:, 0], step[:, 1]))

        def off(h: FloatArray) -> FloatArray:
            d = np.abs((h - bearing + 180.0) % 360.0 - 180.0)
            return np.where(np.isfinite(h), d, 0.0)

        straight = (off(heading[a]) <= cfg.max_turn) & (off(heading[b]) <= cfg.max_turn)
        still = moved < 2.0  # holding: the track between is known however long the gap (within an hour)
        ok |= inside & (((gap <= cfg.max_gap) & (straight | still)) | (still & (gap <= 3600.0)))
        ok |= (j == n) & (ft - tt[-1] <= cfg.extrapolate)
        ok |= (j == 0) & (tt[0] - ft <= cfg.extrapolate) & (tt[0] - ft >= 0)
        return ok

    def _solve(self) -> Solution | None:
        cfg = self.config
        if not self._fixes or len(self._track) < 1:
            return None
        track = self.track()
        tt, txy = track[:, 0], track[:, 1:]
        heading = np.array([self._track[t][2] for t in tt.tolist()])
        fixes = np.array(sorted(self._fixes))
        ft, fxy = fixes[:, 0], fixes[:, 1:]
        usable = self._usable(tt, txy, heading, ft)
        if not usable.any():
            return None
        # the dead-reckoned position at every fix (extrapolated at the newest velocity after it)
        believed = _interp_track(tt, txy, ft)
        if len(tt) >= 2:
            v = (txy[-1] - txy[-2]) / max(tt[-1] - tt[-2], 1e-6)
            late = ft > tt[-1]
            believed[late] = txy[-1] + np.outer(ft[late] - tt[-1], v)
        z = believed - fxy
        sigma = self._sigma or cfg.fix_sigma
        use = usable.copy()
        if self._outliers:
            use &= ~np.isin(ft, np.fromiter(self._outliers, float))
        states = covs = grid = np.zeros(0)
        for _ in range(4):
            grid, states, covs, _gated = self._smooth(tt, txy, ft[use], z[use], sigma)
            resid = z - np.column_stack([np.interp(ft, grid, states[:, 0]), np.interp(ft, grid, states[:, 1])])
            r = np.hypot(resid[:, 0], resid[:, 1])
            base = use if use.sum() >= 5 else usable
            # per-axis sigma from the median radial residual (Rayleigh: median = 1.1774 sigma)
            sigma = max(float(np.median(r[base])) / 1.1774, cfg.min_fix_sigma)
            new = usable & (r <= cfg.reject * sigma)
            if np.array_equal(new, use) or new.sum() < 1:
                break
            use = new
        resid = z - np.column_stack([np.interp(ft, grid, states[:, 0]), np.interp(ft, grid, states[:, 1])])
        r = np.hypot(resid[:, 0], resid[:, 1])
        self._sigma = sigma
        self._outliers = set(ft[usable & ~use].tolist())
        table = np.column_stack([ft, fxy, use, usable & ~use, r])
        return Solution(grid, states, covs, table, sigma)

    def _smooth(self, tt: FloatArray, txy: FloatArray, ft: FloatArray, z: FloatArray, sigma: float
                ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """Kalman filter and RTS smoother on the grid of track and fix times: ``(grid, smoothed
        states, their covariances, which of the fixes the filter's gate refused)``."""
        cfg = self.config
        grid = np.unique(np.concatenate([tt, ft]))
        # the dead-reckoned displacement between grid points (the track held before/after its ends)
        pos = _interp_track(tt, txy, grid)
        step = np.diff(pos, axis=0)
        dist = np.hypot(step[:, 0], step[:, 1])
        dt = np.diff(grid)
        n = len(grid)
        # transition matrices and process noise of every step at once
        F = np.broadcast_to(np.eye(_N), (n - 1, _N, _N)).copy()
        F[:, 0, 2] = dist
        F[:, 1, 3] = dist
        F[:, 0, 4] = step[:, 1]
        F[:, 1, 4] = -step[:, 0]
        Q = np.zeros((n - 1, _N, _N))
        qe = cfg.walk**2 * dist + cfg.time_walk**2 * dt
        Q[:, 0, 0] = Q[:, 1, 1] = qe
        qb = 2.0 * (cfg.drift**2 / 2.0) / cfg.drift_time * dt
        Q[:, 2, 2] = Q[:, 3, 3] = qb
        Q[:, 4, 4] = (math.radians(cfg.heading_sigma) * 0.05) ** 2 * dt / 3600.0
        # the measurement at each grid point (a fix, or none)
        at = np.searchsorted(grid, ft)
        has = np.zeros(n, bool)
        zz = np.zeros((n, 2))
        has[at] = True
        zz[at] = z  # two fixes at one time: the later wins (rare)
        x = np.zeros(_N)
        P = np.diag([cfg.prior**2, cfg.prior**2, cfg.drift**2 / 2.0, cfg.drift**2 / 2.0,
                     math.radians(cfg.heading_sigma) ** 2])
        xf = np.zeros((n, _N))
        Pf = np.zeros((n, _N, _N))
        xp = np.zeros((n, _N))
        Pp = np.zeros((n, _N, _N))
        r2 = sigma**2
        gated = np.zeros(n, bool)
        misses = 0
        gate2 = cfg.gate**2
        FT = np.transpose(F, (0, 2, 1))
        for k in range(n):  # the forward filter: sequential by nature
            if k:
                x = F[k - 1] @ x
                P = F[k - 1] @ P @ FT[k - 1] + Q[k - 1]
            xp[k], Pp[k] = x, P
            if has[k]:
                nu0, nu1 = zz[k, 0] - x[0], zz[k, 1] - x[1]
                a, b, d = P[0, 0] + r2, P[0, 1], P[1, 1] + r2
                det = a * d - b * b
                i00, i01, i11 = d / det, -b / det, a / det
                d2 = nu0 * (i00 * nu0 + i01 * nu1) + nu1 * (i01 * nu0 + i11 * nu1)
                if d2 <= gate2 or misses >= 5:  # after five refused in a row the filter gives in
                    Si = np.array([[i00, i01], [i01, i11]])
                    K = P[:, :2] @ Si
                    x = x + K @ np.array([nu0, nu1])
                    P = P - K @ P[:2, :]
                    misses = 0
                else:
                    gated[k] = True
                    misses += 1
            xf[k], Pf[k] = x, P
        # the RTS smoother: its gains for every step at once, then the backward recursion
        xs = xf.copy()
        Ps = Pf.copy()
        if n > 1:
            C = np.einsum("kij,kjl->kil", np.einsum("kij,kjl->kil", Pf[:-1], FT), np.linalg.inv(Pp[1:]))
            CT = np.transpose(C, (0, 2, 1))
            for k in range(n - 2, -1, -1):
                xs[k] = xf[k] + C[k] @ (xs[k + 1] - xp[k + 1])
                Ps[k] = Pf[k] + C[k] @ (Ps[k + 1] - Pp[k + 1]) @ CT[k]
        return grid, xs, Ps, gated[at]

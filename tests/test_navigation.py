"""Navigation that holds (issue 56): the drift estimator, the USBL sentences and input, the local
frame, the demo's dead reckoning, the corrected views, the position-fix command and the
configuration keys."""

from __future__ import annotations

import math
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from coex import ConfigError, InputContext, Nav, PositionAid, to_stamp
from coex.messages import (
    AckStatus,
    CommandAck,
    PositionFix,
    PositionSource,
    VehicleMode,
    VehicleStatus,
)
from coex.wire import decode, encode
from coex_plugins.navigation import (
    CorrectedDetections,
    CorrectedMap,
    DriftEstimator,
    LocalFrame,
    Navigation,
    UsblInput,
    VehicleFrameSurveys,
    bridge_gaps,
    gga_sentence,
    psimssb_sentence,
    resolve_time,
    tll_sentence,
)
from coex_plugins.survey import SurveyModality

from . import _products as typed

T0 = 1_656_633_600.0  # 2022-07-01T00:00:00Z


# ------------------------------------------------------------------ a synthetic dive
def _lawnmower(n_lines: int = 4, length: float = 256.0, spacing: float = 100.0, speed: float = 1.0
               ) -> tuple[np.ndarray, np.ndarray]:
    """True positions every second of a lawnmower (north/south lines), then a hold."""
    pts = []
    for i in range(n_lines):
        ys = np.arange(0.0, length, speed)
        x = np.full_like(ys, i * spacing)
        pts.append(np.column_stack([x, ys if i % 2 == 0 else length - ys]))
        if i + 1 < n_lines:
            xs = np.arange(i * spacing, (i + 1) * spacing, speed)
            pts.append(np.column_stack([xs, np.full_like(xs, length if i % 2 == 0 else 0.0)]))
    xy = np.vstack(pts)
    xy = np.vstack([xy, np.repeat(xy[-1:], 1200, axis=0)])
    return np.arange(len(xy), dtype=float), xy


def _drift(xy: np.ndarray, rng: np.random.Generator, bias: float = 0.006, psi_deg: float = 0.5) -> np.ndarray:
    """Believed - true: a bias per metre travelled, a heading bias, a little walk, 2 m at the start."""
    step = np.diff(xy, axis=0, prepend=xy[:1])
    d = np.hypot(step[:, 0], step[:, 1])
    b = rng.normal(0.0, bias / math.sqrt(2), 2)
    psi = math.radians(psi_deg)
    inc = b * d[:, None] + psi * np.column_stack([step[:, 1], -step[:, 0]])
    inc += rng.normal(0.0, 0.02, (len(d), 2)) * np.sqrt(d)[:, None]
    return np.array([1.5, -1.2]) + np.cumsum(inc, axis=0)


def _fed(seed: int, *, sigma: float = 4.0, wild: float = 0.03) -> tuple[DriftEstimator, np.ndarray, np.ndarray,
                                                                        np.ndarray, set[float]]:
    rng = np.random.default_rng(seed)
    t, xy = _lawnmower()
    err = _drift(xy, rng)
    est = DriftEstimator()
    wild_times = set()
    for k in range(0, len(t), 10):  # a fix every 10 s
        f = xy[k] + rng.normal(0.0, sigma, 2)
        if rng.random() < wild:
            f = f + rng.choice([-1, 1], 2) * rng.uniform(30.0, 120.0, 2)
            wild_times.add(float(t[k]))
        est.add_fix(float(t[k]), float(f[0]), float(f[1]))
    for k in range(0, len(t), 40):  # statuses: the believed track, a third of them lost
        if rng.random() > 0.33:
            b = xy[k] + err[k]
            est.add_track(float(t[k]), float(b[0]), float(b[1]))
    return est, t, xy, err, wild_times


def test_the_estimate_follows_the_drift_and_rejects_wild_fixes() -> None:
    """With fixes of 4 m per axis every 10 s and a few wild ones 30-120 m off, the smoothed
    correction stays within about a metre of the true drift over the whole dive (while the drift
    itself grows to several metres), and the wild fixes are the ones flagged."""
    est, t, _xy, err, wild = _fed(3)
    c = est.correction(t)
    miss = np.hypot(*(c - err).T)
    assert np.hypot(*err[-1]) > 3.0  # the drift is real ...
    assert np.median(miss) < 1.0 and np.percentile(miss, 95) < 2.0, (np.median(miss), miss.max())  # ... and followed
    sol = est.solution()
    assert sol is not None
    flagged = {float(r[0]) for r in sol.fixes if r[4] > 0}
    assert wild and wild <= flagged, (wild - flagged)
    assert len(flagged - wild) <= 0.02 * len(sol.fixes)
    assert 2.5 < sol.fix_sigma < 5.5  # learnt from the residuals (true: 4 m per axis)
    # the correction is smooth: no step between two seconds bigger than the drift can make
    assert np.abs(np.diff(c, axis=0)).max() < 0.2


def test_the_estimate_without_wild_fixes_and_the_gate_matter() -> None:
    """The same dive with the wild fixes left in and no rejection (a huge gate and threshold) is
    worse: the robust steps are what keeps the estimate."""
    from coex_plugins.navigation import NavConfig

    est, t, _xy, err, _ = _fed(5, wild=0.08)
    blind = DriftEstimator(NavConfig(gate=1e9, reject=1e9))
    for f in est._fixes:
        blind.add_fix(*f)
    for tt, (x, y, _h) in est._track.items():
        blind.add_track(tt, x, y)
    good = np.hypot(*(est.correction(t) - err).T).mean()
    bad = np.hypot(*(blind.correction(t) - err).T).mean()
    assert good < 0.6 * bad, (good, bad)


def test_no_fix_or_no_track_is_no_correction() -> None:
    est = DriftEstimator()
    assert est.solution() is None and np.array_equal(est.correction([1.0, 2.0]), np.zeros((2, 2)))
    est.add_fix(10.0, 1.0, 2.0)
    assert est.solution() is None  # no track to compare with
    est.add_track(0.0, 5.0, 5.0)
    est.add_track(20.0, 5.0, 5.0)
    c = est.correction(10.0)
    assert c == pytest.approx([4.0, 3.0], abs=0.5)  # believed (5, 5) less the fix (1, 2)


def test_to_vehicle_adds_the_correction() -> None:
    est, t, _xy, _err, _ = _fed(7)
    end = float(t[-1])
    vx, vy = est.to_vehicle(100.0, 100.0, end)
    c = est.correction(end)
    assert (vx, vy) == pytest.approx((100.0 + c[0], 100.0 + c[1]))


# ------------------------------------------------------------------ USBL sentences and input
def test_sentences_parse_back_with_their_time_and_position() -> None:
    frame = LocalFrame(36.8, -122.0)
    inp = UsblInput({"udp": "127.0.0.1:0"}, InputContext(36.8, -122.0))
    lat, lon = frame.geodetic(123.4, -56.7)
    t = T0 + 3600 * 5 + 61.5
    items: list = []
    samples: dict = {}
    for line in (tll_sentence(t, 2, lat, lon), gga_sentence(t, lat, lon, -480.0)):
        from coex_plugins.inputs.nmea import parse_sentence

        f = parse_sentence(line)
        kind = f[0][2:]
        assert inp._sentence(kind, f, t + 3.0, items, samples)
    e, n = frame.to_utm(123.4, -56.7)
    from coex_plugins.inputs.nmea import parse_sentence

    f = parse_sentence(psimssb_sentence(t, 2, e, n, 480.0, accuracy=3.2))
    assert inp._sentence("PSIMSSB", f, t + 3.0, items, samples)
    assert len(items) == 3
    for it in items:
        assert isinstance(it, Nav) and it.time == pytest.approx(t, abs=0.01)
        assert (it.x, it.y) == pytest.approx((123.4, -56.7), abs=0.05)
    assert items[0].extra["target"] == 2 and items[1].depth == pytest.approx(480.0)
    assert items[2].extra == {"target": 2.0, "accuracy": 3.2}


def _line(body: str) -> str:
    from coex_plugins.inputs.nmea import checksum

    return f"${body}*{checksum(body):02X}"


def test_ttm_is_a_range_and_bearing_from_the_ship() -> None:
    frame = LocalFrame(10.0, 20.0)
    inp = UsblInput({"udp": "127.0.0.1:0", "gga": "ship", "target": "B03"}, InputContext(10.0, 20.0))
    from coex_plugins.inputs.nmea import parse_sentence

    items: list = []
    lat, lon = frame.geodetic(0.0, 0.0)
    ship = gga_sentence(T0 + 10, lat, lon)
    inp._sentence("GGA", parse_sentence(ship), T0 + 10, items, {})
    assert items == [] and inp.ship == pytest.approx((0.0, 0.0), abs=0.01)
    # target 3 at 0.5 km bearing 90 (true): 500 m east; target 4 is filtered out
    inp._sentence("TTM", parse_sentence(_line("RATTM,03,0.5,90.0,T,0.0,0.0,T,,,K,ROV,T,,000010.00,A")),
                  T0 + 11, items, {})
    inp._sentence("TTM", parse_sentence(_line("RATTM,04,0.5,90.0,T,0.0,0.0,T,,,K,X,T,,000010.00,A")),
                  T0 + 11, items, {})
    assert len(items) == 1 and (items[0].x, items[0].y) == pytest.approx((500.0, 0.0), abs=0.01)
    assert items[0].time == pytest.approx(T0 + 10.0) and inp.counts["other_target"] == 1
    # lost targets and relative bearings without the ship's heading give no fix
    inp._sentence("TTM", parse_sentence(_line("RATTM,03,0.5,90.0,T,0.0,0.0,T,,,K,ROV,L,,000011.00,A")),
                  T0 + 12, items, {})
    inp._sentence("TTM", parse_sentence(_line("RATTM,03,0.5,90.0,R,0.0,0.0,T,,,K,ROV,T,,000012.00,A")),
                  T0 + 12, items, {})
    assert len(items) == 1 and inp.counts["void"] == 2


def test_fix_times_roll_over_midnight() -> None:
    day = 86400.0 * 19000
    assert resolve_time(86399.0, day + 86400.0 + 1.0) == day + 86399.0  # read just after midnight
    assert resolve_time(1.0, day + 86399.0) == day + 86400.0 + 1.0
    assert resolve_time(3600.0, day + 3605.0) == day + 3600.0


def test_the_usbl_input_reads_udp_counts_bad_lines_and_checks_its_options() -> None:
    inp = UsblInput({"udp": "127.0.0.1:0"}, InputContext(0.0, 0.0))
    inp.open()
    try:
        host, port = inp.udp_address()  # type: ignore[misc]
        lat, lon = inp.frame.geodetic(10.0, 20.0)
        now = time.time()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto((tll_sentence(now, 2, lat, lon) + "\r\n").encode(), (host, port))
            s.sendto(b"$RATLL,02,garbage*00\r\n", (host, port))
            s.sendto(b"$PSIMSSB,000000.00,B02,V,,U,E,M,1,2,3,0,N,,*00\r\n", (host, port))
        got: list = []
        for _ in range(50):
            got += inp.poll(time.time())
            if inp.counts["lines"] >= 3:
                break
            time.sleep(0.02)
        assert len(got) == 1 and (got[0].x, got[0].y) == pytest.approx((10.0, 20.0), abs=0.05)
        assert inp.counts["bad_checksum"] == 2 and inp.counts["skipped"] == 2
    finally:
        inp.close()
    from coex import adapter_check

    # its own check (udp, utm_zone) and its declared options (gga: "vehicle" or "ship")
    problems = adapter_check(UsblInput, {"udp": "nohost", "gga": "boat", "utm_zone": "99X"}).items
    assert any("udp" in p for p in problems) and any("gga" in p for p in problems)
    assert any("utm_zone" in p for p in problems)
    assert UsblInput.check({}).items  # serial or udp needed


def test_local_frame_round_trips_through_pyproj() -> None:
    f = LocalFrame(-33.9, 151.2)
    assert f.utm_zone == "56S"
    lat, lon = f.geodetic(1234.5, -678.9)
    assert f.local(lat, lon) == pytest.approx((1234.5, -678.9), abs=1e-6)
    assert f.from_utm(*f.to_utm(1234.5, -678.9)) == pytest.approx((1234.5, -678.9), abs=1e-6)
    # 1 km north is 1 km: an equidistant projection, not degrees scaled
    lat1, _ = f.geodetic(0.0, 1000.0)
    assert (lat1 - (-33.9)) * 110_950 == pytest.approx(1000.0, rel=0.01)


# ------------------------------------------------------------------ the position fix on the wire
def test_the_position_fix_command_round_trips_and_a_vehicle_without_aiding_refuses_it() -> None:
    fix = PositionFix(3, PositionSource.USBL, 7200, 102.3, -45.6, 5.3, 471.2)
    assert decode(encode(fix)) == fix
    rx = SurveyModality().receiver(None)
    rx.next_command_id = lambda: 9  # type: ignore[method-assign]
    sent = rx.position_fix(10.0, -20.0, 1000.0, sigma=2.5, source="estimate")
    assert rx.poll(1000.0) == [sent] and sent.source == PositionSource.ESTIMATE
    plain = SurveyModality().sender(None)
    assert plain.handle(sent, 1001.0) == [CommandAck(9, AckStatus.REJECTED)] and plain.take_aids() == []
    aided = SurveyModality().sender({"aiding": True})
    ack = aided.handle(sent, 1001.0)
    assert ack == [CommandAck(9, AckStatus.ACCEPTED)]
    assert aided.take_aids() == [PositionAid(1000.0, 10.0, -20.0, 2.5, None, "estimate")]
    assert aided.handle(sent, 1002.0) == ack and aided.take_aids() == []  # a repeat: answered, not twice
    rx.receive(ack[0], 1003.0)
    assert rx.fixes[9][0] == "accepted" and 9 not in [m.command_id for m in rx.pending_requests()]


def test_autonomy_outputs_map_the_fix() -> None:
    """The MOOS output posts ``USM_RESET = x=..,y=..`` (uSimMarine moves there) and the full
    fix; the MAVLink output sends GPS_INPUT at the origin-relative latitude and longitude."""
    from coex_plugins.autonomy.mavlink import MavlinkAutonomy
    from coex_plugins.autonomy.moos import MoosAutonomy

    posted: list[tuple[str, str]] = []

    class Client:
        def notify(self, var: str, value: str) -> None:
            posted.append((var, value))

    out = MoosAutonomy({}, InputContext(0.0, 0.0), client=Client())
    fix = PositionAid(T0, 12.34, -5.0, 1.5, 400.0, "usbl")
    assert out.aid(fix, T0 + 1)
    assert posted[0] == ("USM_RESET", "x=12.34,y=-5")
    assert posted[1][0] == "COEX_POSITION_FIX" and "sigma=1.5" in posted[1][1] and "depth=400" in posted[1][1]
    assert not MoosAutonomy({"position_fix_var": ""}, InputContext(0.0, 0.0), client=Client()).aid(fix, T0)

    sent: list[dict] = []

    class Mav:
        def gps_input_send(self, **fields: object) -> None:
            sent.append(dict(fields))

    class Conn:
        mav = Mav()

    ctx = InputContext(45.0, 7.0)
    mav = MavlinkAutonomy({"connection": "udpout:127.0.0.1:9"}, ctx)
    mav.conn = Conn()
    assert mav.aid(fix, T0)
    lat, lon = ctx.geodetic(12.34, -5.0)
    g = sent[0]
    assert g["lat"] == round(lat * 1e7) and g["lon"] == round(lon * 1e7) and g["alt"] == -400.0
    assert g["fix_type"] == 3 and g["horiz_accuracy"] == 1.5 and g["time_usec"] == int(T0 * 1e6)
    assert not MavlinkAutonomy({"connection": "udpout:127.0.0.1:9", "position_fix": False}, ctx).aid(fix, T0)


# ------------------------------------------------------------------ topside's corrected views
class _Rx:
    """A bathymetry receiver's surface enough for the corrected views: one level of 1 m cells
    in 8 x 8 subgrids, two subgrids stamped at different times."""

    def __init__(self) -> None:
        self.z = np.full((8, 16), -100.0)
        self.z[3:5, 2:4] = -98.0  # a bump in the first subgrid
        self.requested: list[tuple] = []

    def level_product(self, level: int, now: float | None = None):  # type: ignore[no-untyped-def]
        return typed.map_level(0, self.z)

    def level_version(self, level: int) -> int:
        return 1

    def geometry(self, level: int) -> tuple[float, int]:
        return 1.0, 8

    def coverage(self, level: int, max_blocks: int = 4096):  # type: ignore[no-untyped-def]
        return 1, np.array([[0, 0], [1, 0]]), np.array([100.0, 200.0])

    def request_area(self, *args: float) -> None:
        self.requested.append(args)


def _steady(dx: float, dy: float) -> Navigation:
    """Vehicle 2 sat believing (50, 50) for 300 s while USBL fixed it at (50 - dx, 50 - dy)
    every 10 s: a steady correction (dx, dy)."""
    nav = Navigation()
    est = nav.estimator(2)
    for t in (0.0, 300.0):
        est.add_track(t, 50.0, 50.0)
    for t in np.arange(0.0, 300.0, 10.0):
        est.add_fix(float(t), 50.0 - dx, 50.0 - dy)
    return nav

def test_a_subgrid_moves_by_the_correction_at_its_stamp() -> None:
    nav = _steady(2.0, 3.0)  # believed (50, 50), truly (48, 47)
    rx = _Rx()
    view = CorrectedMap(rx, nav, 2)
    p = view.level_product(0)
    grid = np.asarray(p.data)
    x0, y0 = p.meta["x0"], p.meta["y0"]
    rows, cols = np.nonzero(grid > -99.0)
    # the bump (cells 2..3, rows 3..4: centre (3, 4)) lands 2 m west and 3 m south
    cx, cy = x0 + cols.mean() + 0.5, y0 + rows.mean() + 0.5
    assert (cx, cy) == pytest.approx((1.0, 1.0), abs=0.15)
    assert np.nanmax(grid) == pytest.approx(-98.0)  # depths kept (a whole-cell shift here)
    view.request_area(0, 10.0, 10.0, 20.0, 20.0)
    assert rx.requested[0][1:] == pytest.approx((12.0, 13.0, 22.0, 23.0), abs=0.2)  # in the vehicle's frame
    surveys = VehicleFrameSurveys(SurveyModality().receiver(None), nav, 2)
    surveys._rx.next_command_id = lambda: 1
    cmd = surveys.request("goto", 100.0, 100.0, 300.0)
    assert (cmd.x, cmd.y) == pytest.approx((102.0, 103.0), abs=0.2)
    off = Navigation(apply=False)
    off.estimators[2] = nav.estimators[2]
    assert np.array_equal(np.asarray(CorrectedMap(rx, off, 2).level_product(0).data), rx.z)


class _GapRx(_Rx):
    """A 24 x 24 level of 1 m cells (3 x 3 subgrids, one stamp) on a depth ramp, with a gap of
    one row across it (row 12: the vehicle's soundings skipped a row of its frame), and a gap
    two columns wide (columns 16-17 over rows 2-5)."""

    def __init__(self) -> None:
        super().__init__()
        iy, ix = np.mgrid[0:24, 0:24]
        self.ramp = -100.0 + 0.1 * (ix + 0.5) + 0.05 * (iy + 0.5)  # the depth at a cell's centre
        self.z = self.ramp.copy()
        self.z[12, :] = np.nan
        self.z[2:6, 16:18] = np.nan

    def coverage(self, level: int, max_blocks: int = 4096):  # type: ignore[no-untyped-def]
        keys = np.array([[i, j] for j in range(3) for i in range(3)])
        return 1, keys, np.full(len(keys), 100.0)


def test_the_corrected_map_has_no_holes_where_its_source_lies_between_held_cells() -> None:
    """Issue 54: a corrected cell whose source point falls in a one-cell gap of the received
    level (between two held cells) gets a value, read across the gap; nothing is added beyond
    the held cells (a gap two cells wide, the level's edges)."""
    nav = _steady(0.3, 0.4)  # a fraction of a cell
    rx = _GapRx()
    p = CorrectedMap(rx, nav, 2).level_product(0)
    grid = np.asarray(p.data, dtype=float)
    x0, y0 = p.meta["x0"], p.meta["y0"]
    ny, nx = grid.shape
    qx = x0 + np.arange(nx) + 0.5
    qy = y0 + np.arange(ny) + 0.5
    c = nav.correction(2, 100.0)
    assert c == pytest.approx((0.3, 0.4), abs=0.02)
    sx, sy = np.meshgrid(qx + c[0], qy + c[1])  # each corrected cell's source point
    col, row = np.floor(sx).astype(int), np.floor(sy).astype(int)
    inside = (col >= 0) & (row >= 0) & (col < 24) & (row < 24)
    wide = inside & (col >= 16) & (col <= 17) & (row >= 2) & (row <= 5)
    # every cell whose source lies in the held level, or in its one-row gap, is held
    gap_row = inside & (row == 12)
    assert gap_row.sum() >= 20 and np.isfinite(grid[gap_row]).all()
    assert np.isfinite(grid[inside & ~wide]).all()
    # ... with the ramp's depth there (bilinear, read across the gap)
    want = -100.0 + 0.1 * sx + 0.05 * sy
    interior = inside & ~wide & (sx >= 0.5) & (sx <= 23.5) & (sy >= 0.5) & (sy <= 23.5)
    near_wide = (sx >= 15.0) & (sx <= 19.0) & (sy >= 1.0) & (sy <= 7.0)
    assert np.abs(grid - want)[interior & ~near_wide].max() < 1e-9
    # nothing made up: the gap two cells wide and everything beyond the level stay empty
    assert wide.sum() == 8 and np.isnan(grid[wide]).all()
    assert np.isnan(grid[~inside]).all()
    # the received level itself is unchanged (what the vehicle sent, in its frame)
    assert np.isnan(np.asarray(rx.level_product(0).data)[12]).all()


def test_bridge_gaps_fills_one_cell_gaps_only() -> None:
    z = np.full((5, 6), np.nan)
    z[1:4, 1:5] = 1.0
    z[2, 2] = np.nan  # a hole held all round: the mean of four
    z[1, 4] = 3.0
    z[3, 4] = 5.0
    z[2, 4] = np.nan  # held north and south only
    z[2, 3] = 7.0
    before = z.copy()
    out = bridge_gaps(z)
    assert np.array_equal(z, before, equal_nan=True)  # the input is not changed
    assert out[2, 2] == pytest.approx((1.0 + 7.0 + 1.0 + 1.0) / 4)
    assert out[2, 4] == pytest.approx(4.0)  # (3 + 5) / 2: its east is empty
    assert np.isnan(out[0]).all() and np.isnan(out[:, 0]).all() and np.isnan(out[:, 5]).all()  # no edge grows
    two = np.array([[1.0, np.nan, np.nan, 2.0]])
    assert np.isnan(bridge_gaps(two)[0, 1:3]).all()  # a gap two cells wide stays


# ------------------------------------------------------------------ the demo's dead reckoning
def test_dead_reckoning_drifts_with_distance_and_flies_waypoints_in_its_own_frame() -> None:
    from coex_apps.demo.navigation import DeadReckoning
    from coex_apps.demo.world import Leg, Track
    from coex_plugins.bathymetry.sim import Seafloor

    track = Track(Seafloor(size=64.0, depth=100.0, seed=0))
    track.legs.append(Leg(0.0, 300.0, (0.0, 0.0), (0.0, 0.0), 10.0))
    dr = DeadReckoning(track, 0.0, 300.0, 5000.0, drift=0.01, heading_bias=1.0, seed_offset=2.0,
                       rng=np.random.default_rng(1))
    assert np.hypot(*dr.error(300.0)) == pytest.approx(2.0)  # the error at the bottom
    assert np.hypot(*dr.error(150.0)) == pytest.approx(1.0)  # grown in time on the way down
    # the vehicle flies to a waypoint of its own frame: it arrives where it believes it is there
    wps = dr.true_path(300.0, (0.0, 0.0), [(0.0, 400.0), (400.0, 400.0)], [1.0, 1.0])
    t1 = 300.0 + math.hypot(*wps[0])
    t2 = t1 + math.hypot(wps[1][0] - wps[0][0], wps[1][1] - wps[0][1])
    track.legs += [Leg(300.0, t1, (0.0, 0.0), wps[0], 10.0), Leg(t1, t2, wps[0], wps[1], 10.0)]
    assert dr.believed(t1, *wps[0]) == pytest.approx((0.0, 400.0), abs=0.05)
    assert dr.believed(t2, *wps[1]) == pytest.approx((400.0, 400.0), abs=0.05)
    # ... and truly somewhere else: the drift over 800 m at 1 % and a 1 degree heading bias
    assert math.hypot(wps[1][0] - 400.0, wps[1][1] - 400.0) > 3.0
    still = DeadReckoning(track, 0.0, 300.0, 5000.0, drift=0.0, heading_bias=1.0, seed_offset=2.0,
                          rng=np.random.default_rng(1))
    assert not still.active and np.array_equal(still.error(t2), np.zeros(2))
    assert still.true_path(300.0, (0.0, 0.0), [(0.0, 400.0)], [1.0]) == [(0.0, 400.0)]


def test_scenario_keys_and_their_ranges() -> None:
    from coex_apps.demo.scenario import preset, scenario_from_dict

    s = preset("default")
    assert (s.drift, s.heading_bias, s.seed_offset) == (0.005, 0.5, 2.0)
    assert (s.usbl_interval, s.usbl_sigma, s.usbl_outliers) == (10.0, 0.01, 0.02)
    t = scenario_from_dict({"navigation": {"drift": 0.0, "heading_bias": -1.0, "seed_offset": 5.0},
                            "usbl": {"interval": 30, "sigma": 0.002, "outliers": 0.1}})
    assert (t.drift, t.heading_bias, t.seed_offset, t.usbl_interval, t.usbl_sigma, t.usbl_outliers) == (
        0.0, -1.0, 5.0, 30.0, 0.002, 0.1)
    with pytest.raises(ConfigError) as exc:
        scenario_from_dict({"navigation": {"drift": -1, "bogus": 1}, "usbl": {"outliers": 0.9}})
    keys = {p.key for p in exc.value.problems or []}
    assert {"navigation.drift", "navigation.bogus", "usbl.outliers"} <= keys


def test_the_topside_file_knows_usbl(tmp_path: Path) -> None:
    from coex_apps.vehicle.config import check

    base = ('[node]\nrole = "topside"\nid = 1\nstore = false\n[[modems]]\nuri = "loopback://x"\n')
    good = tmp_path / "topside.toml"
    good.write_text(base + '[usbl]\nudp = "0.0.0.0:10111"\ntarget = "B02"\napply = false\n')
    cfg, problems = check(good)
    assert not problems and cfg is not None and cfg.usbl == {"udp": "0.0.0.0:10111", "target": "B02", "apply": False}
    bad = tmp_path / "bad.toml"
    bad.write_text(base + '[usbl]\nspeed = 3\napply = "yes"\n')
    _, problems = check(bad)
    text = "\n".join(problems)
    assert "'speed'" in text and "usbl.apply" in text
    bad.write_text(base + '[usbl]\nudp = "nowhere"\n')
    _, problems = check(bad)
    assert any("'udp'" in p for p in problems), problems
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(base.replace("topside", "vehicle").replace("id = 1", "id = 2") + '[usbl]\nudp = "0.0.0.0:1"\n')
    _, problems = check(vehicle)
    assert any(p.startswith("usbl") for p in problems)


def test_the_console_survey_action_sends_in_the_vehicles_frame() -> None:
    from coex_apps.console import ConsoleState
    from coex_apps.console.actions import ConsoleActions

    nav = Navigation()
    est = nav.estimator(2)
    est.add_track(0.0, 50.0, 50.0)
    est.add_track(100.0, 50.0, 50.0)
    for t in range(0, 100, 10):
        est.add_fix(float(t), 45.0, 55.0)  # correction (5, -5)
    rx = SurveyModality().receiver(None)
    rx.next_command_id = lambda: 4  # type: ignore[method-assign]
    state = ConsoleState(receivers={"survey": rx})
    state.own_receivers = False
    state.navigation = nav
    actions = ConsoleActions(state, lambda m: None, lambda: 100.0)
    cmd = actions.survey("goto", 10.0, 20.0)
    assert (cmd.x, cmd.y) == pytest.approx((15.0, 15.0), abs=0.3)
    state.apply_message(VehicleStatus(100, 51.0, 50.0, 400.0, 30.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0), 100.0)
    snap = state.section("navigation")
    assert snap["enabled"] and snap["correction"]["size"] == pytest.approx(7.1, abs=0.4)
    assert snap["fix_count"] == 10 and snap["raw_track"] and snap["corrected_track"]


# ------------------------------------------------------------------ the map placed by its passes
class _KnownCorrection(Navigation):
    """A navigation whose correction is given (by time), to test where the map is placed."""

    def correction(self, vehicle: int, t: object) -> np.ndarray:
        times = np.asarray(t, float)
        out = np.zeros((*times.shape, 2))
        out[..., 0] = np.where(times < T0 + 220.0, 2.0, -2.0)  # line 1: +2 m east, line 2: -2 m
        return out


def _two_passes(nav: Navigation) -> None:
    """Statuses every 5 s: north along x = 0 (30 m up), east to x = 40, south along x = 40, and a
    hold there (not a pass)."""
    pts = [(t, 0.0, t) for t in np.arange(0.0, 200.0, 5.0)]
    pts += [(t, t - 200.0, 200.0) for t in np.arange(200.0, 240.0, 5.0)]
    pts += [(t, 40.0, 200.0 - (t - 240.0)) for t in np.arange(240.0, 440.0, 5.0)]
    pts += [(t, 40.0, 0.0) for t in np.arange(440.0, 740.0, 5.0)]
    for t, x, y in pts:
        nav.status(2, VehicleStatus(to_stamp(T0 + t), x, y, 400.0, 30.0, 0.0, 1.0, 90, VehicleMode.SURVEY, 0), T0 + t)


def test_a_map_block_is_placed_by_the_passes_whose_swath_covered_it() -> None:
    """A block seen by two passes with different drifts sits where the passes' corrections,
    weighted by the multibeam's sounding density there (cos² of the beam angle), put it; a block
    stamped before the second pass, or a navigation that does not know the swath, takes the
    correction at its stamp."""
    nav = _KnownCorrection(swath=135.0)
    nav.estimator(2)
    _two_passes(nav)
    size = 8.0
    centres = np.array([[4.0, 100.0], [36.0, 100.0], [20.0, 100.0], [4.0, 100.0]])
    stamps = np.array([T0 + 700.0, T0 + 700.0, T0 + 700.0, T0 + 150.0])
    got = nav.map_correction(2, centres, stamps, size)
    w_near, w_far = 1.0 / (1.0 + (4.0 / 30.0) ** 2), 1.0 / (1.0 + (36.0 / 30.0) ** 2)
    expect = (2.0 * w_near - 2.0 * w_far) / (w_near + w_far)  # about 0.8 m, not the stamp's -2 m
    assert got[0, 0] == pytest.approx(expect, abs=0.15) and got[1, 0] == pytest.approx(-expect, abs=0.15)
    assert got[2, 0] == pytest.approx(0.0, abs=0.15)  # half-way between the lines: both alike
    assert got[3, 0] == pytest.approx(2.0)  # only line 1 had passed by its stamp
    assert np.allclose(got[:, 1], 0.0)
    plain = _KnownCorrection()
    plain.estimator(2)
    _two_passes(plain)
    assert plain.map_correction(2, centres, stamps, size)[:, 0] == pytest.approx([-2.0, -2.0, -2.0, 2.0])
    # a block beyond the swath's reach (72 m at 30 m up) of every pass keeps its stamp's correction
    assert nav.map_correction(2, np.array([[150.0, 100.0]]), np.array([T0 + 700.0]), size)[0, 0] == -2.0
    with pytest.raises(ValueError):
        Navigation(swath=180.0)


# ------------------------------------------------------------------ aiding the vehicle's navigation
def test_a_fix_is_handed_on_after_its_delay_and_a_late_or_older_one_is_refused() -> None:
    rx = SurveyModality().receiver(None)
    vehicle = SurveyModality().sender({"aiding": True, "aid_delay": 100.0})
    first = rx.position_fix(10.0, 20.0, T0 + 50.0, stamp=T0, sigma=1.0)
    assert rx.poll(T0 + 50.0) == [first]
    assert rx.poll(T0 + 100.0) == [] and rx.poll(T0 + 111.0) == [first]  # a fix is re-sent after 60 s
    assert vehicle.handle(first, T0 + 60.0) == [CommandAck(first.command_id, AckStatus.ACCEPTED)]
    assert vehicle.take_aids(T0 + 99.0) == []  # not yet: taken 100 s after its stamp
    assert [a.time for a in vehicle.take_aids(T0 + 100.0)] == [T0]
    older = rx.position_fix(11.0, 21.0, T0 + 120.0, stamp=T0 - 10.0)
    late = rx.position_fix(12.0, 22.0, T0 + 120.0, stamp=T0 + 10.0)
    assert vehicle.handle(older, T0 + 121.0) == [CommandAck(older.command_id, AckStatus.REJECTED)]
    assert vehicle.handle(late, T0 + 105.0) == [CommandAck(late.command_id, AckStatus.ACCEPTED)]
    late2 = rx.position_fix(12.0, 22.0, T0 + 200.0, stamp=T0 + 20.0)
    assert vehicle.handle(late2, T0 + 121.0) == [CommandAck(late2.command_id, AckStatus.REJECTED)]  # past due
    with pytest.raises(ConfigError):
        SurveyModality().sender({"aid_delay": -1.0})


def test_topside_aids_the_vehicle_and_keeps_the_aids_out_of_its_estimate() -> None:
    """The vehicle believes it is 5 m east and 3 m south of the truth; topside's fixes say so.
    Topside sends its estimate as a position fix; the vehicle takes it 100 s after its stamp and
    its statuses are true from then on. Topside still sees one dead-reckoned track (no jump in
    its estimate), knows the vehicle's frame is now right, and sends a survey point uncorrected;
    an aid the vehicle refused is not counted."""
    from coex_plugins.navigation import AidConfig

    e = np.array([5.0, -3.0])
    for answer in (AckStatus.ACCEPTED, AckStatus.REJECTED):
        nav = Navigation()
        nav.aiding[2] = AidConfig(delay=100.0, blend=0.0, interval=1000.0, max_sigma=5.0)
        rx = SurveyModality().receiver(None)
        shift = np.zeros(2)
        aid = None
        for k in range(0, 600, 10):
            t = T0 + k
            true = np.array([float(k), 0.0])  # east at 1 m/s
            if aid is not None and answer == AckStatus.ACCEPTED and t >= aid.stamp + 100.0:
                shift = e  # the vehicle took the fix
            bx, by = true + e - shift
            nav.status(2, VehicleStatus(to_stamp(t), round(bx, 1), round(by, 1), 400.0, 30.0, 90.0, 1.0, 90,
                                        VehicleMode.SURVEY, 0), t)
            nav.estimator(2).add_fix(t, float(true[0]), float(true[1]))
            if k == 200:
                aid = nav.aid(2, rx, t)
                assert aid is not None and (aid.x, aid.y) == pytest.approx((200.0, 0.0), abs=0.3)
                fix = rx.poll(t)[0]
                assert isinstance(fix, PositionFix)
                rx.receive(CommandAck(fix.command_id, answer), t + 30.0)
                assert nav.aid(2, rx, t + 30.0) is None  # the answer is followed, nothing new is due
        assert aid is not None
        if answer == AckStatus.ACCEPTED:
            assert aid.counted and aid.delta == pytest.approx(tuple(e), abs=0.3)
            assert nav.estimate(2, T0 + 250.0) == pytest.approx(e, abs=0.3)  # before the vehicle took it
            assert nav.estimate(2, T0 + 550.0) == pytest.approx((0.0, 0.0), abs=0.3)  # its frame is true now
            raw = nav.estimator(2).track()
            assert raw[-1, 1:] == pytest.approx((590.0 + 5.0, -3.0), abs=0.3)  # the estimator's track: no jump
        else:
            assert not aid.counted and nav.estimate(2, T0 + 550.0) == pytest.approx(e, abs=0.3)
        assert nav.corrected(2, T0 + 590.0, *nav.track(2)[-1, 1:]) == pytest.approx((590.0, 0.0), abs=0.4)


def test_the_scenario_key_aiding() -> None:
    from coex_apps.demo.scenario import preset, scenario_from_dict

    assert preset("default").aiding is False
    assert scenario_from_dict({"navigation": {"aiding": True}}).aiding is True
    with pytest.raises(ConfigError) as exc:
        scenario_from_dict({"navigation": {"aiding": 1}})
    assert {p.key for p in exc.value.problems or []} == {"navigation.aiding"}


def test_version_2_survey_state_loads() -> None:
    """A store saved before ``aid_delay`` and the fixes' own re-send tracker (state version 2)
    loads: no delay, a fix it was re-sending is still answered, new fixes use their own tracker."""
    import json

    from coex_core.state import dumps_parts, loads_parts

    rx = SurveyModality().receiver(None)
    old = rx.position_fix(1.0, 2.0, T0, sigma=1.0)
    tx = SurveyModality().sender({"aiding": True})
    text, arrays = dumps_parts([rx, tx])
    doc = json.loads(text)
    rf, sf = doc["root"][0]["f"], doc["root"][1]["f"]
    rf["_requests"] = rf.pop("_fix_requests")  # version 2 re-sent fixes with the surveys
    rf["_requests"]["f"]["retry"] = 300.0
    del sf["aid_delay"], sf["_newest_taken"]
    doc["classes"]["survey.Receiver"] = doc["classes"]["survey.Sender"] = 2
    rx2, tx2 = loads_parts(json.dumps(doc).encode(), arrays)
    assert tx2.aid_delay == 0.0 and tx2.aiding
    assert rx2.poll(T0) == [old]
    ack = tx2.handle(old, T0 + 1.0)
    assert ack == [CommandAck(old.command_id, AckStatus.ACCEPTED)] and len(tx2.take_aids(T0 + 1.0)) == 1
    rx2.receive(ack[0], T0 + 2.0)
    assert rx2.fixes[old.command_id][0] == "accepted" and rx2.pending_requests() == []
    new = rx2.position_fix(3.0, 4.0, T0 + 10.0)
    assert rx2.poll(T0 + 10.0) == [new] and rx2.poll(T0 + 71.0) == [new]  # its own 60 s re-send


# ------------------------------------------------------------------ camera lines sent in the vehicle's frame
def test_the_bias_prediction_follows_the_distance_and_relaxes_with_time() -> None:
    est = DriftEstimator()
    for t in (0.0, 300.0):
        est.add_track(t, 50.0, 50.0, 0.0)
    est.add_fix(100.0, 48.0, 47.0)
    sol = est.solution()
    assert sol is not None
    sol.states[:, 2:] = [0.004, -0.002, 0.0]  # a known bias, no heading bias
    tau = est.config.drift_time
    assert est.drift_along(300.0, 0.0, 100.0) == pytest.approx([0.4, -0.2])
    # the bias grows with the distance travelled, not the displacement: 300 m of path for 100 m
    assert est.drift_along(300.0, 0.0, 100.0, distance=300.0) == pytest.approx([1.2, -0.6])
    # and relaxes toward zero: travelled half an hour from now, it is expected smaller by 1/e
    assert est.drift_along(300.0, 0.0, 100.0, after=tau) == pytest.approx([0.4 / math.e, -0.2 / math.e])


def _nav_holding(correction: tuple[float, float], until: float, nav: Navigation | None = None) -> Navigation:
    """Topside's navigation of vehicle 2 holding at (50, 50) in its own frame, fixed every 10 s
    up to ``until`` at its true position: (50, 50) less ``correction``."""
    nav = nav or Navigation()
    est = nav.estimator(2)
    for t in np.arange(0.0, until + 1.0, 20.0):
        nav.status(2, VehicleStatus(to_stamp(T0 + t), 50.0, 50.0, 500.0, 10.0, 0.0, 0.0, 90, VehicleMode.HOVER, 0),
                   T0 + t)
    start = max((f[0] for f in est._fixes), default=T0 - 10.0) + 10.0
    for t in np.arange(start, T0 + until + 1.0, 10.0):
        est.add_fix(float(t), 50.0 - correction[0], 50.0 - correction[1])
    return nav


def test_a_line_sent_later_is_moved_by_the_estimate_now_not_by_an_earlier_line_s() -> None:
    """Two camera lines queued one after the other, sent 20 minutes apart: the second is put into
    the vehicle's frame by the correction topside estimates when it sends it (the vehicle's
    drift changed meanwhile), not by the correction it had predicted for the first."""
    nav = _nav_holding((2.0, 3.0), 600.0)
    surveys = VehicleFrameSurveys(SurveyModality().receiver(None), nav, 2)
    ids = iter(range(1, 100))
    surveys._rx.next_command_id = lambda: next(ids)
    # a long line: the vehicle is still flying it when the next is sent
    first = surveys.request("line", 60.0, 60.0, T0 + 600.0, heading=0.0, length=200.0, speed=0.1, append=True)
    assert (first.x, first.y) == pytest.approx((62.0, 63.0), abs=0.3)
    assert surveys.busy_until > T0 + 1800.0
    # the drift moved: topside now estimates (5, 3)
    _nav_holding((5.0, 3.0), 1800.0, nav)
    est = nav.estimator(2)
    assert est.correction(T0 + 1800.0) == pytest.approx([5.0, 3.0], abs=0.5)
    second = surveys.request("line", 80.0, 60.0, T0 + 1800.0, heading=0.0, length=30.0, speed=0.3, append=True)
    sid, at, c = surveys.sent[-1]
    assert sid == second.survey_id and at == T0 + 1800.0
    # the estimate now, plus what the estimated biases add on the way (small here: a holding vehicle)
    along = np.asarray(c) - est.correction(T0 + 1800.0)
    assert np.hypot(*along) < 0.5, c
    assert (second.x, second.y) == pytest.approx((80.0 + c[0], 60.0 + c[1]), abs=0.1)
    # the plan: what is left of the first line, then the second's transit and line
    assert [leg[3] for leg in surveys.plan] == [(60.0, 260.0), (80.0, 60.0), (80.0, 90.0)]


def test_the_operator_sends_a_camera_line_only_when_the_vehicle_nearly_needs_it() -> None:
    """The scripted operator keeps at most :data:`LINE_AHEAD` seconds of camera lines queued on
    the vehicle: each further line is sent (and put into the vehicle's frame) at a later round,
    nearer the time it is flown, not all at the survey's end."""
    from coex.messages import SurveyCommand
    from coex_apps.demo.operator import LINE_AHEAD, CandidateView, Operator

    sent: list[SurveyCommand] = []

    class Survey:
        surveys: dict[int, object] = {}

        def request(self, kind: str, x: float, y: float, now: float, **kw: object) -> SurveyCommand:
            cmd = SurveyCommand(command_id=len(sent) + 1, survey_id=len(sent), kind=kind, x=x, y=y,  # type: ignore[arg-type]
                                **kw)  # type: ignore[arg-type]
            sent.append(cmd)
            return cmd

    op = Operator(None, {"bathymetry": None, "imagery": None, "survey": Survey()},  # type: ignore[arg-type]
                  (0.0, 0.0, 200.0, 200.0), lambda *a: None, camera_altitude=5.0)
    op.position = (100.0, 100.0)
    for i in range(4):
        op.candidates.append(CandidateView(40.0 + 40.0 * i, 60.0, 1.5, 10, 4.5, 1.8, 0.9 - 0.1 * i, 0.0))
    op.camera_round(0.0, end=100_000.0, reserve=0.0, half=15.0)
    assert 1 <= len(sent) < 4
    t, _ = op._queue_end(0.0)
    assert t <= LINE_AHEAD + 250.0  # the lines queued fill the horizon, not the whole camera time
    n = len(sent)
    op.camera_round(10.0, end=100_000.0, reserve=0.0, half=15.0)
    assert len(sent) == n  # nothing more while the vehicle has lines enough
    for line in op.lines.values():  # the vehicle reported reaching each line's start
        line.at_start = 0.0
    op.camera_round(200.0, end=100_000.0, reserve=0.0, half=15.0)
    assert len(sent) > n  # the next, once the queue runs short


def test_the_report_shows_how_far_the_camera_missed_with_the_correction_off(tmp_path: Path) -> None:
    from coex_apps.demo.report import write_report

    nav = {"active": True, "correction": "off", "drift_at_end_m": 10.9,
           "targets": [{"x": 70.7, "y": 117.3, "map_error_m": 5.41, "camera_pass_m": 4.58},
                       {"x": 116.0, "y": 52.5, "map_error_m": 1.2, "camera_pass_m": None}],
           "estimate": {"2": {"error_median_m": 0.24, "error_p95_m": 1.24, "error_max_m": 1.58}}}
    page = write_report(tmp_path, {"navigation": nav}, charts=[], maps=[], images=[], decisions=[]).read_text()
    section = page[page.index("<h3>Navigation</h3>"):page.index("<h2 id=\"map\">")]
    assert "OFF (--no-correction)" in section and "10.9 m at the dive" in section
    assert "<td class='r bad'>4.58</td>" in section and "<td class='r bad'>5.41</td>" in section
    assert "<td class='r'>1.20</td>" in section and "<td class='bad c'>none</td>" in section
    assert "95th percentile 1.24 m" in section
    on = write_report(tmp_path, {"navigation": {**nav, "correction": "on"}}, charts=[], maps=[], images=[],
                      decisions=[]).read_text()
    assert "Correction on:" in on
    # no drift, no navigation section
    assert "<h3>Navigation</h3>" not in write_report(tmp_path, {"navigation": {"active": False}}, charts=[], maps=[],
                                                     images=[], decisions=[]).read_text()


def test_a_map_detection_is_placed_like_the_map_at_its_stamp_not_when_it_arrived() -> None:
    """A detection the vehicle found in its own map sits where the passes that mapped it put it
    (as the map around it does), from its stamp (the row's ``time``), not from when its row last
    reached topside (``updated_at``); a detection of another source takes the correction at its
    stamp."""
    nav = _KnownCorrection(swath=135.0)
    nav.estimator(2)
    _two_passes(nav)

    class Rows:
        def rows(self) -> list[dict[str, object]]:
            return [{"id": 0, "source": "map", "x": 4.0, "y": 100.0, "time": T0 + 700.0, "updated_at": T0 + 100.0},
                    {"id": 1, "source": "map", "x": 4.0, "y": 120.0, "time": T0 + 150.0, "updated_at": T0 + 700.0},
                    {"id": 2, "source": "image", "x": 4.0, "y": 140.0, "time": T0 + 700.0, "updated_at": T0 + 100.0}]

    got = {r["id"]: (r["x"], r["y"]) for r in CorrectedDetections(Rows(), nav, 2).rows()}
    w_near, w_far = 1.0 / (1.0 + (4.0 / 30.0) ** 2), 1.0 / (1.0 + (36.0 / 30.0) ** 2)
    expect = (2.0 * w_near - 2.0 * w_far) / (w_near + w_far)  # both passes, weighted: about 0.8 m
    assert got[0] == pytest.approx((4.0 - expect, 100.0), abs=0.15)  # not 4 - 2 (arrival) nor 4 + 2 (stamp)
    assert got[1] == pytest.approx((2.0, 120.0), abs=0.05)  # stamped before the second pass
    assert got[2] == pytest.approx((6.0, 140.0), abs=0.05)  # an image's: the correction at its stamp


def test_the_operator_measures_a_small_bump_in_the_map_as_received_and_places_it() -> None:
    """A two-cell bump 0.9 m high (a small debris patch's main piece) moved by half a cell
    each way: the corrected level's bilinear resampling spreads it below the bump threshold;
    the operator measures it in the level as received and places it by the map's correction."""
    from coex_apps.demo.operator import Operator

    nav = _steady(0.5, 0.5)  # believed (50, 50), truly (49.5, 49.5)

    class Small(_Rx):
        def __init__(self) -> None:
            super().__init__()
            self.z = np.full((24, 24), -100.0)
            self.z[10, 10:12] = -99.1  # cells (10, 10) and (11, 10): centre (11.0, 10.5)

        def levels(self) -> list[int]:
            return [0]

        def coverage(self, level: int, max_blocks: int = 4096):  # type: ignore[no-untyped-def]
            return 1, np.array([[i, j] for i in range(3) for j in range(3)]), np.full(9, 100.0)

    view = CorrectedMap(Small(), nav, 2)
    corrected = np.asarray(view.level_product(0).data)
    assert np.nanmax(corrected) - np.nanmedian(corrected) < 0.7  # spread below the threshold
    op = Operator(None, {"bathymetry": view, "imagery": None, "survey": None},  # type: ignore[arg-type]
                  (0.0, 0.0, 24.0, 24.0), lambda *a: None, camera_altitude=5.0)
    found = op.measured(0.0)
    assert len(found) == 1
    assert (found[0].x, found[0].y) == pytest.approx((10.5, 10.0), abs=0.15)
    assert found[0].height == pytest.approx(0.9, abs=0.05)

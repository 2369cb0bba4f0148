"""Onboard detections (issue 41): the relief measures, the vehicle's relief detector on its own
map, the neighbourhood that follows a detection, the detections sender and receiver, the
detector plugin point, and the finest level leaving the background on a low link."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from coex_core import wire
from coex_core.detect import Detector, Finding
from coex_core.errors import ConfigError, RequestRejected
from coex_core.messages import (
    Detection,
    DetectionSource,
    MapRoiRequest,
    Message,
    SubgridMessage,
)
from coex_core.modality import ModalitySender
from coex_core.registry import load_detector
from coex_core.timefmt import to_stamp
from coex_plugins.bathymetry import BathymetrySender
from coex_plugins.bathymetry.relief import CAR, bumps, despike, likeness, measure_bump
from coex_plugins.bathymetry.sim import Seafloor, Target, simulate_survey
from coex_plugins.detections import (
    DetectionsModality,
    DetectionsReceiver,
    DetectionsSender,
    detection_message,
)
from coex_plugins.detections.relief import ReliefDetector


def _grid(objs: list[Target], size: int = 48) -> np.ndarray:
    """A flat 1 m grid (row 0 = south) holding ``objs`` as the seafloor simulator shapes them."""
    floor = Seafloor(size=float(size), relief=0.0, ripple_amplitude=0.0, depth=100.0, targets=tuple(objs), seed=0)
    xs = np.arange(size) + 0.5
    gx, gy = np.meshgrid(xs, xs)
    return np.asarray(floor.elevation(gx, gy), float)


def test_a_car_measures_as_a_car_and_scores_above_a_boulder_of_its_size() -> None:
    """Length, width, height, orientation (clockwise from north, an axis) and a flat top from the
    1 m grid; a dome of a car's footprint scores lower (its top is not flat)."""
    car = _grid([Target(20.0, 24.0, heading=30.0)])
    (c, b), = bumps(car, cell=1.0)
    assert math.hypot(b.x - 20.0, b.y - 24.0) < 1.0
    assert b.length == pytest.approx(4.5, abs=0.8) and b.width == pytest.approx(1.8, abs=0.7)
    assert b.height == pytest.approx(1.5, abs=0.2) and b.flatness > 0.8
    assert min(abs(b.orientation - 30.0), 180 - abs(b.orientation - 30.0)) < 12.0
    across = measure_bump(_grid([Target(20.0, 24.0, heading=120.0)]), 1.0, 0.0, 0.0, c.peak_x, c.peak_y, c.height)
    rock = _grid([Target(20.0, 24.0, 3.6, 2.6, 1.6, heading=30.0, shape="dome")])
    (_, r), = bumps(rock, cell=1.0)
    car_score = likeness(b.height, b.length, b.width, b.flatness, CAR)
    assert car_score > 0.5 and likeness(r.height, r.length, r.width, r.flatness, CAR) < 0.6 * car_score
    assert across is None or abs(across.orientation - b.orientation) > 45  # turned: another axis


def test_a_wild_sounding_on_a_car_does_not_hide_it() -> None:
    """One cell 5 m above a car (an outlier the rejection let through) made the car a one-cell
    spike; despiked, it measures as a car again. A lone spike on sand is gone; a car keeps its
    end cells."""
    clean = _grid([Target(20.0, 24.0, heading=100.0)])
    spiked = clean.copy()
    (_, b0), = bumps(clean, cell=1.0)
    spiked[int(b0.y), int(b0.x)] += 5.0
    spiked[10, 40] += 6.0  # on sand
    raw = bumps(spiked, cell=1.0, spikes=None)
    assert max(r.height for _, r in raw) > 4.0 and min(r.length for _, r in raw) < 1.5
    (_, b), = bumps(spiked, cell=1.0)
    assert (b.length, b.width, round(b.height, 2)) == (b0.length, b0.width, round(b0.height, 2))
    assert np.array_equal(despike(clean), clean)


def test_a_one_cell_peak_on_a_foot_is_a_bump_with_foot_and_a_lone_one_is_not() -> None:
    """A peak filling one map cell (a small debris patch's main piece) with raised cells around
    it (its smaller pieces) has too few cells above the threshold for a bump; counted on its
    foot (``foot``) it is one, measured at its peak. One cell raised alone, or a foot without a
    peak above the threshold, is no bump either way."""
    z = np.full((40, 40), -100.0)
    z[20, 20] = -99.1  # the peak: 0.9 m
    z[20, 21] = z[21, 20] = -99.45  # the foot: 0.55 m
    z[8, 8] = -99.1  # a lone cell
    z[30, 30:32] = -99.4  # a foot without a peak: 0.6 m
    assert bumps(z, cell=1.0) == []
    (c, b), = bumps(z, cell=1.0, foot=0.5)
    assert (c.peak_x, c.peak_y) == (20.5, 20.5) and b.height == pytest.approx(0.9, abs=0.05)
    assert math.hypot(b.x - 20.5, b.y - 20.5) < 0.6
    # a wild sounding on a boulder's edge is still a spike (its raised neighbours are the boulder):
    # the boulder is measured, not a one-cell spike 4.5 m high
    rock = np.full((40, 40), -100.0)
    rock[10:12, 30:33] = -98.7
    rock[10, 33] = -95.5
    (_, r), = bumps(rock, cell=1.0, foot=0.4)
    assert r.cells == 6 and r.height == pytest.approx(1.3, abs=0.05)


def test_the_despike_median_is_numpys_bit_for_bit() -> None:
    """despike's median of the neighbours (one sort, issue 55's speed) is np.nanmedian's, NaN
    and infinite neighbours included."""
    import warnings

    from coex_plugins.bathymetry.relief import _nanmedian0

    rng = np.random.default_rng(2)
    for t in range(100):
        a = rng.normal(size=(8, 13, 11)) * 10.0 ** rng.integers(-3, 4)
        a[rng.random(a.shape) < rng.random()] = np.nan
        if t % 4 == 0:
            a[rng.random(a.shape) < 0.05] = rng.choice([np.inf, -np.inf])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            assert np.array_equal(np.nanmedian(a, axis=0), _nanmedian0(a), equal_nan=True), t


def _survey(size: float = 96.0, seed: int = 3) -> tuple[Seafloor, Any]:
    floor = Seafloor.default(size=size, seed=seed, relief=1.0)
    return floor, simulate_survey(floor, beams=128, ping_rate=2.0, seed=seed + 1)


def test_the_relief_detector_finds_the_cars_in_the_vehicles_map_once_the_swath_has_passed() -> None:
    """Run every 10 s as the survey goes, the relief detector reports each car once the cells
    around it have been quiet for ``settle`` seconds, with car-like measures, and nothing else
    that scores like one; a map region it has seen unchanged is not looked at again."""
    floor, survey = _survey()
    sender = BathymetrySender({"levels": 4})
    det = ReliefDetector({"settle": 20.0})
    found: list[tuple[float, Finding]] = []
    nxt = None
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, float(t))
        nxt = t if nxt is None else nxt
        if t >= nxt:
            nxt += 10.0
            found += [(float(t), f) for f in det.detect(sender.detector_view(), float(t))]
    end = float(survey.times[-1])
    found += [(end + 30.0, f) for f in det.detect(sender.detector_view(), end + 30.0)]
    for car in floor.targets:
        near = [(t, f) for t, f in found if math.hypot(f.x - car.x, f.y - car.y) <= 3.5]
        assert near, f"the car at ({car.x:.0f}, {car.y:.0f}) was never found"
        t, f = max(near, key=lambda tf: tf[1].score)
        assert f.score >= 0.2 and f.height is not None and f.height > 1.0
        assert t - f.time >= 20.0  # judged only after its cells were quiet
    for _, f in found:
        if all(math.hypot(f.x - c.x, f.y - c.y) > 3.5 for c in floor.targets):
            assert f.score < 0.2, f"a false finding that scores like a car: {f}"
    assert det.detect(sender.detector_view(), end + 60.0) == []  # nothing changed since: nothing looked at


def _sender_with_map() -> tuple[Seafloor, BathymetrySender, float]:
    floor, survey = _survey()
    sender = BathymetrySender({"levels": 4, "send_delay": 5.0})
    for t, xyz in survey.pings(batch=10):
        sender.ingest(xyz, float(t))
    return floor, sender, float(survey.times[-1]) + 30.0


def test_focus_queues_the_finest_subgrids_around_a_detection_ahead_of_the_background() -> None:
    """``focus(x, y, r)`` queues the level-0 subgrids within r of the point, nearest first, as a
    region request would (without a reply); they go before the background, a lost one is queued
    again, and a second focus on the same place queues nothing sent already."""
    floor, sender, now = _sender_with_map()
    car = floor.targets[0]
    n = sender.focus(car.x, car.y, 12.0, now)
    assert 4 <= n <= 16
    first = sender.fill(240, now)
    subs = [m for m in first if isinstance(m, SubgridMessage)]
    assert subs and all(s.level == 0 for s in subs)
    nearest = subs[0]
    assert math.hypot((nearest.ix + 0.5) * 8 - car.x, (nearest.iy + 0.5) * 8 - car.y) <= 8.0
    sent = list(subs)
    while len(sent) < n:
        sent += [m for m in sender.fill(240, now) if isinstance(m, SubgridMessage) and m.level == 0]
    assert sender.focus(car.x, car.y, 12.0, now) == 0  # sent (and not found lost) already
    assert sender.focus_bytes == sum(wire.encoded_size(s) for s in sent[:n])
    sender.lost(sent[0], now + 1.0)
    again = [m for m in sender.fill(240, now + 2.0) if isinstance(m, SubgridMessage)]
    assert again[0] == sent[0], "a lost neighbourhood subgrid goes again, ahead of the background"


def test_on_a_low_link_the_finest_level_is_spare_work_not_background() -> None:
    """While the channel finds the link low, ``fill`` sends the coarse levels (and requests and
    neighbourhoods) only; the finest level goes with ``spare``; a normal link brings it back."""
    _, sender, now = _sender_with_map()
    sender.throughput(16.0, True, now)
    levels: set[int] = set()
    for i in range(400):
        got = sender.fill(240, now + i)
        if not any(isinstance(m, SubgridMessage) for m in got):
            break
        levels |= {m.level for m in got if isinstance(m, SubgridMessage)}
    assert levels and 0 not in levels
    spare = [m for m in sender.spare(240, now + 500) if isinstance(m, SubgridMessage)]
    assert spare and {m.level for m in spare} == {0}
    sender.throughput(300.0, False, now + 501)
    assert any(isinstance(m, SubgridMessage) and m.level == 0 for m in sender.fill(240, now + 502))


class FakeMapSender(ModalitySender):
    """Stands in for the bathymetry sender: records where it was asked to focus."""

    def __init__(self) -> None:
        self.focused: list[tuple[float, float, float]] = []

    def ingest(self, data: Any, now: float) -> None:
        pass

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        return []

    def handle(self, message: Message, now: float) -> list[Message]:
        return []

    def focus(self, x: float, y: float, radius: float, now: float) -> int:
        self.focused.append((x, y, radius))
        return 4

    def detector_view(self) -> FakeMapSender:
        return self


class Scripted(Detector[FakeMapSender]):
    """Finds what the test tells it to."""

    name = "scripted"
    modality = "fakemap"
    view = FakeMapSender
    source = DetectionSource.MAP
    neighbourhood = 10.0

    def __init__(self, script: list[list[Finding]]) -> None:
        self.script = script
        self.calls = 0
        self.seen: list[object] = []

    def detect(self, data: FakeMapSender, now: float) -> list[Finding]:
        self.calls += 1
        self.seen.append(data)
        return self.script.pop(0) if self.script else []


class Silent(FakeMapSender):
    """A sender of the same modality that offers detectors nothing."""

    def detector_view(self) -> None:
        return None


def test_a_detector_is_handed_only_a_view_of_the_type_it_declares(caplog: pytest.LogCaptureFixture) -> None:
    """The detections sender gives a detector the view its modality's sender offers when it is
    of the detector's declared ``view`` type; a sender offering none (or another type) is
    told in the log once, and the detector is not called."""
    fake = FakeMapSender()
    det = Scripted([[Finding(10.0, 10.0, 0.5, 100.0)]])
    sender = DetectionsSender({"detectors": [det], "interval": 10.0})
    sender.bind_peers(lambda name: fake if name == "fakemap" else None)
    assert sender.run(100.0) == 1 and det.seen == [fake]
    other = Scripted([[Finding(10.0, 10.0, 0.5, 100.0)]])
    quiet = DetectionsSender({"detectors": [other], "interval": 10.0})
    quiet.bind_peers(lambda name: Silent() if name == "fakemap" else None)
    with caplog.at_level("WARNING"):
        assert quiet.run(100.0) == 0 and quiet.run(110.0) == 0
    assert other.calls == 0
    told = [r.getMessage() for r in caplog.records if "scripted" in r.getMessage()]
    assert told == ["detector scripted takes a FakeMapSender of modality 'fakemap', whose sender offers none"]


def test_a_detector_declares_the_modality_and_the_view_it_takes() -> None:
    """A detector class that implements ``detect`` without ``view`` (or ``modality``), or with a
    view that cannot be checked, is refused when it is defined; an abstract one is not."""
    from typing import Protocol

    with pytest.raises(TypeError, match="declares no view"):
        class NoView(Detector[Any]):
            modality = "bathymetry"

            def detect(self, data: Any, now: float) -> list[Finding]:
                return []

    class Unchecked(Protocol):
        def frames(self) -> list[Any]: ...

    with pytest.raises(TypeError, match="cannot be checked"):
        class Bad(Detector[Any]):
            modality, view = "imagery", Unchecked

            def detect(self, data: Any, now: float) -> list[Finding]:
                return []

    class Base(Detector[Any]):  # abstract: its subclasses declare them
        name = "base"

    assert Base.__abstractmethods__ == frozenset({"detect"})


def test_the_built_in_senders_offer_the_views_their_detectors_declare() -> None:
    """The bathymetry sender's view is its map (a ``MapView``, what the relief detector takes);
    the imagery sender's its frames (``ImageFrames``, what the sample's darkspot takes)."""
    from coex_core.detect import ImageFrames, MapView

    bathy = BathymetrySender({"levels": 2})
    assert isinstance(bathy.detector_view(), MapView) and bathy.detector_view() is bathy.map
    assert ReliefDetector.view is MapView and ReliefDetector.modality == "bathymetry"
    pytest.importorskip("glymur")
    from coex_plugins.imagery import ImageryModality

    frames = ImageryModality().sender(None)
    assert isinstance(frames.detector_view(), ImageFrames)
    assert not isinstance(bathy.detector_view(), ImageFrames)


def test_the_detections_sender_sends_the_best_first_once_again_when_lost_or_changed() -> None:
    """New findings go highest score first (those below ``min_score`` not at all); one is not
    sent again unless the channel reports it lost or its measures change; its neighbourhood is
    asked of the detector's modality (score at least ``focus_score``), again when newer data
    changed it."""
    fake = FakeMapSender()
    det = Scripted([[Finding(10.0, 10.0, 0.3, 100.0, height=1.2), Finding(50.0, 50.0, 0.9, 100.0, height=1.5,
                                                                          length=4.4, width=1.9),
                     Finding(80.0, 0.0, 0.01, 100.0)],
                    [Finding(10.2, 10.1, 0.31, 110.0, height=1.2)],  # the same, barely changed
                    [Finding(50.1, 50.0, 0.6, 120.0, height=1.5, length=4.4, width=1.9)]])  # changed score
    sender = DetectionsSender({"detectors": [det], "interval": 10.0})
    sender.bind_peers(lambda name: fake if name == "fakemap" else None)
    first = sender.fill(64, 105.0)
    assert [m.detection_id for m in first if isinstance(m, Detection)] == [1, 0]  # best first
    assert [m.score for m in first] == [0.9, 0.3] and len(first) == 2  # 0.01 is kept, not sent
    assert sorted(f[:2] for f in fake.focused) == [(10.0, 10.0), (50.0, 50.0)]
    assert sender.fill(64, 116.0) == [] and det.calls == 2  # nothing new worth sending
    lost = first[1]
    sender.lost(lost, 117.0)
    resent = sender.fill(64, 118.0)  # again, in its newest version
    assert [(m.detection_id, m.stamp, m.score) for m in resent] == [(0, 110, 0.31)]
    changed = sender.fill(64, 126.0)
    assert len(changed) == 1 and changed[0].detection_id == 1 and changed[0].score == 0.6
    # the neighbourhood again whenever a finding rests on newer data (the modality sends only
    # what changed)
    assert [f[:2] for f in fake.focused[2:]] == [(10.2, 10.1), (50.1, 50.0)]
    assert sender.bytes_sent == sum(wire.encoded_size(m) for m in first + resent + changed)
    with pytest.raises(RequestRejected):
        sender.handle(MapRoiRequest(0, 0, 0, 0, 1, 1, False, (None,)), 0.0)


def test_findings_made_outside_coex_are_ingested_and_garbage_refused() -> None:
    sender = DetectionsSender({"detectors": []})
    sender.ingest([Finding(1.0, 2.0, 0.5, 3.0), Finding(4.0, 5.0, 0.7, 6.0, image_id=9,
                                                        source=DetectionSource.IMAGE)], 10.0)
    out = sender.fill(64, 10.0)
    assert [(m.source, m.image_id) for m in out] == [(DetectionSource.IMAGE, 9), (DetectionSource.OTHER, None)]
    for bad in ("car", [Finding(math.nan, 0.0, 0.5, 1.0)], {"x": 1}):
        with pytest.raises(ValueError):
            sender.ingest(bad, 11.0)
    with pytest.raises(ConfigError):
        DetectionsSender({"detectors": [{"type": "no-such-detector"}]})
    with pytest.raises(ConfigError):
        DetectionsSender({"detectors": [{"type": "relief", "threshold": -1}]})


def test_the_wire_form_keeps_every_measure_in_range() -> None:
    """Out-of-range measures are clamped into their fields, a width above the length swaps
    them, an orientation of 180 is 0: every finding makes a valid message."""
    m = detection_message(1030, DetectionSource.MAP, Finding(60000.0, -3.04, 1.7, 5.0, height=40.0, length=2.0,
                                                              width=3.0, orientation=180.2, footprint=5000.0))
    assert (m.detection_id, m.x, m.y, m.score, m.height, m.length, m.width, m.orientation, m.footprint) == (
        6, 50000.0, -3.0, 1.0, 25.4, 3.0, 2.0, 0.0, 1022)
    assert wire.decode(wire.encode(m)) == m


def test_topside_keeps_the_newest_version_of_each_detection() -> None:
    rx = DetectionsModality().receiver()
    assert isinstance(rx, DetectionsReceiver) and rx.products() == []
    d1 = Detection(3, DetectionSource.MAP, to_stamp(100.0), 10.0, 20.0, 0.5, 1.4)
    d2 = Detection(3, DetectionSource.MAP, to_stamp(130.0), 10.5, 20.0, 0.8, 1.5)
    assert rx.receive(d2, 140.0) and not rx.receive(d1, 150.0)  # an older version arrives late
    assert not rx.receive(d2, 160.0)  # a duplicate
    (row,) = rx.rows()
    assert (row["score"], row["first_at"], row["time"]) == (0.8, 140.0, 130.0)
    assert rx.products()[0].kind == "detections"


def test_the_relief_detector_is_registered_under_coex_detectors() -> None:
    """The plugin point: built-in detectors are found by name through the entry-point group,
    exactly as a vehicle team's own."""
    cls = load_detector("relief")
    assert cls is ReliefDetector and issubclass(cls, Detector)
    assert cls.modality == "bathymetry" and cls.source == DetectionSource.MAP
    sender = DetectionsSender(None)  # the default: the relief detector
    assert [type(d) for d in sender.detectors] == [ReliefDetector]

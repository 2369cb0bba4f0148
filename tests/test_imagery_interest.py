"""Images on a low link (issue 41): the vehicle's interest measure (a frame against the running
background of the frames before it), the previews as spare work with the most interesting first,
and at most two copies of a requested image's bytes before an ack. The operator can still ask
for any frame by time."""

from __future__ import annotations

import numpy as np

from coex_core.messages import ImageAnnounce, ImageByTimeRequest, ImageFragment, TimeDirection
from coex_core.timefmt import to_stamp
from coex_plugins.imagery import ImageInput, ImageryModality
from coex_plugins.imagery.sender import LOW_COPIES, interest
from coex_plugins.imagery.synth import seafloor


def _frame(k: int, hull: bool = False) -> np.ndarray:
    """The camera moving over the same sand (the scene shifted a little each frame, sensor
    noise); with ``hull``, a dark hull over about a sixth of the frame."""
    rng = np.random.default_rng(k)
    img = np.roll(seafloor(96, 128, seed=1).astype(float), 3 * k, axis=0) + rng.normal(0, 4, (96, 128))
    if hull:
        img[30:70, 40:90] *= 0.35
    return np.clip(img, 0, 255).astype(np.uint8)


def test_a_dark_hull_stands_out_from_the_running_background_and_sand_does_not() -> None:
    backdrop = None
    sand = []
    for k in range(6):
        score, backdrop = interest(_frame(k), backdrop)
        sand.append(score)
    hull, _ = interest(_frame(7, hull=True), backdrop)
    assert hull > 2 * max(sand[1:]), (hull, sand)
    assert interest(np.zeros((2, 2)), None)[0] == 0.0  # nothing to judge


def test_a_colour_frame_scores_the_same_as_its_float_copy() -> None:
    """A uint8 colour frame takes a path in integers (issue 55): the same score and background,
    to the bit, as the same frame in float64 (the mean of its channels)."""
    rng = np.random.default_rng(3)
    backdrop = fbackdrop = None
    for _ in range(4):
        img = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
        img[..., 2] = 255 - img[..., 0] // 3  # sums of all kinds, not only multiples of 3
        score, backdrop = interest(img, backdrop)
        fscore, fbackdrop = interest(img.astype(np.float64), fbackdrop)
        assert score == fscore
        assert backdrop is not None and fbackdrop is not None and backdrop.tobytes() == fbackdrop.tobytes()


def _sender() -> object:
    s = ImageryModality().sender({"layer_bytes": [40, 120, 400, 1200], "default_goal": "layer:1",
                                  "request_goal": "layer:3"})
    for k in range(6):
        s.ingest(ImageInput(_frame(k, hull=k == 4), time=100.0 + 6 * k, x=1.0 * k, y=0.0), 100.0 + 6 * k)
    return s


def test_on_a_low_link_the_previews_are_spare_work_the_most_interesting_first() -> None:
    """Normal link: previews to the default set-point go with ``fill`` in capture order. Low
    link: ``fill`` carries only announcements and answers; ``spare`` sends the previews, the
    frame with the hull first."""
    s = _sender()
    s.throughput(300.0, False, 200.0)
    normal = [m for m in s.fill(2000, 200.0) if isinstance(m, ImageFragment)]
    assert [m.image_id for m in normal][:2] == [0, 1]
    s = _sender()
    s.throughput(16.0, True, 200.0)
    got = s.fill(2000, 200.0)
    assert any(isinstance(m, ImageAnnounce) for m in got)
    assert not [m for m in got if isinstance(m, ImageFragment)]
    spare = [m for m in s.spare(120, 201.0) if isinstance(m, ImageFragment)]
    assert spare and spare[0].image_id == 4
    for k in range(60):  # every preview goes; no layer beyond the set-point unasked
        spare += [m for m in s.spare(120, 202.0 + k) if isinstance(m, ImageFragment)]
    assert {m.image_id for m in spare} == set(range(6))
    assert all(m.offset + len(m.data) <= s.images[m.image_id].goal for m in spare)


def test_a_requested_image_goes_at_most_twice_before_an_ack_on_a_low_link() -> None:
    """Under 60 % measured loss a requested image's bytes go up to 6 times at once on a normal
    link; on a low one twice, then only what the channel reports lost."""
    for low, most in ((False, 6), (True, LOW_COPIES)):
        s = _sender()
        for _ in range(40):  # the channel's verdicts on fragments sent once
            s._fates.append(0 if len(s._fates) % 5 < 3 else 1)
        s.throughput(16.0 if low else 300.0, low, 200.0)
        s.handle(ImageByTimeRequest(1, to_stamp(112.0), TimeDirection.NEAREST), 200.0)
        sent: dict[int, int] = {}
        for k in range(60):
            for m in s.fill(200, 201.0 + k):
                if isinstance(m, ImageFragment) and m.image_id == 2:
                    for b in range(m.offset, m.offset + len(m.data)):
                        sent[b] = sent.get(b, 0) + 1
        assert sent and max(sent.values()) == most, (low, max(sent.values()))

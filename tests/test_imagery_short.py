"""Short fragments (``ImageShortFragment``, type 40; spec/payloads.md 3.3): the image named by
its slot is the last one announced in that slot; the vehicle sends them only for bytes sent the
first time of an image topside heard that took its slot cleanly, and never lands bytes in the
wrong image, with many images sharing slots and under loss."""

from __future__ import annotations

import numpy as np
import pytest

from coex import ConfigError, wire
from coex.messages import ImageAnnounce, ImageFragment, ImageShortFragment
from coex_plugins.imagery import ImageInput, ImageryModality, ImageryReceiver, ImagerySender
from coex_plugins.imagery.sender import SHORT_HEAD, SHORT_HORIZON, SHORT_SLOTS
from coex_plugins.imagery.sim import Bernoulli, Transfer
from coex_plugins.imagery.synth import seafloor

CFG = {"layer_bytes": [40, 120, 400, 900], "default_goal": "layer:3", "rto": 15.0, "progress_interval": 1e9}


def _announce(image_id: int, total: int = 900) -> ImageAnnounce:
    return ImageAnnounce(image_id, 0, None, None, 64, 48, True, total, 0x0208)


def test_a_short_fragment_is_of_the_last_image_announced_in_its_slot() -> None:
    r = ImageryReceiver()
    r.receive(_announce(5), 0.0)
    r.receive(ImageShortFragment(5, 0, b"abc"), 1.0)
    assert bytes(r.images[5].buf[:3]) == b"abc"
    # image 37 takes slot 5 (37 % 32): the same slot now names it
    r.receive(_announce(37), 2.0)
    r.receive(ImageShortFragment(5, 10, b"xyz"), 3.0)
    assert bytes(r.images[37].buf[10:13]) == b"xyz" and not r.images[5].have[10:13].any()
    # an announcement the receiver refuses (colour params with grey set) takes the slot too:
    # the vehicle counts on it, and the image is not held, so its short fragments are ignored
    rejected = r.rejected_fragments
    r.receive(ImageAnnounce(69, 0, None, None, 64, 48, True, 900, 0x0209), 4.0)
    assert r.rejected_announces == 1 and 69 not in r.images
    r.receive(ImageShortFragment(5, 20, b"no"), 5.0)
    assert not r.images[37].have[20:22].any() and r.rejected_fragments == rejected + 1
    # a slot no announcement named yet
    r.receive(ImageShortFragment(6, 0, b"?"), 6.0)
    assert r.rejected_fragments == rejected + 2


def _sender(**cfg: object) -> ImagerySender:
    return ImageryModality().sender({**CFG, **cfg})


def _frames(s: ImagerySender, n: int, t0: float, mtu: int = 64, deliver: bool = True) -> list[object]:
    """``n`` fills of one ``mtu``-byte frame each, every message reported delivered."""
    out: list[object] = []
    for k in range(n):
        msgs = s.fill(mtu - wire.header_size(), t0 + k)
        for m in msgs:
            if deliver:
                s.acked(m, t0 + k)
        out += msgs
    return out


def test_the_vehicle_sends_short_fragments_only_once_topside_heard_the_image() -> None:
    s = _sender()
    s.ingest(ImageInput(seafloor(48, 64, seed=1), time=0.0), 0.0)
    first = s.fill(61, 1.0)  # announcement + a fragment: not heard yet
    assert isinstance(first[0], ImageAnnounce)
    assert all(not isinstance(m, ImageShortFragment) for m in first)
    for m in first:
        s.acked(m, 1.0)
    shorts = [m for m in _frames(s, 3, 2.0) if isinstance(m, ImageShortFragment)]
    assert len(shorts) == 3
    for f in shorts:
        assert f.slot == 0 and s.image_of(f) == 0 and wire.encoded_size(f) == SHORT_HEAD + len(f.data)
        # it carries one byte more than an ImageFragment in a 64-byte frame
        assert len(f.data) == 64 - wire.header_size() - SHORT_HEAD
        assert f.data == s.images[0].enc.body[f.offset:f.offset + len(f.data)]


def test_bytes_sent_again_and_large_frames_go_in_image_fragments() -> None:
    s = _sender(rto=5.0)
    s.ingest(ImageInput(seafloor(48, 64, seed=2), time=0.0), 0.0)
    for m in s.fill(61, 1.0):
        s.acked(m, 1.0)
    lost = [m for m in _frames(s, 2, 2.0, deliver=False) if isinstance(m, ImageShortFragment)]
    assert lost
    for m in lost:
        s.lost(m, 4.0)  # the channel says their frames were lost: due again at once
    again = [m for m in s.fill(61, 5.0) if isinstance(m, ImageFragment | ImageShortFragment)]
    assert again and isinstance(again[0], ImageFragment) and again[0].offset == lost[0].offset
    # a 256-byte frame: an ImageFragment carries more than a short one could
    big = [m for m in s.fill(253, 6.0) if isinstance(m, ImageFragment | ImageShortFragment)]
    assert big and all(isinstance(m, ImageFragment) for m in big if len(m.data) > 64)


def test_no_short_fragments_when_the_option_is_off_or_the_slot_was_not_taken_cleanly() -> None:
    with pytest.raises(ConfigError):
        _sender(short_fragments="yes")
    s = _sender(short_fragments=False)
    s.ingest(ImageInput(seafloor(48, 64, seed=3), time=0.0), 0.0)
    assert not [m for m in _frames(s, 6, 1.0) if isinstance(m, ImageShortFragment)]
    # images 0 and 32 share slot 0: 32's announcement follows 0's within SHORT_HORIZON, so a
    # late copy of 0's could still arrive after it: 32 sends no short fragments
    s = _sender(max_images=64)
    for i in range(33):
        s.ingest(ImageInput(seafloor(48, 64, seed=i), time=float(i)), float(i))
    msgs = _frames(s, 400, 40.0)
    taken = next(i for i, m in enumerate(msgs) if isinstance(m, ImageAnnounce) and m.image_id == 32)
    shorts = [(i, s.image_of(m)) for i, m in enumerate(msgs) if isinstance(m, ImageShortFragment)]
    assert {image_id for _i, image_id in shorts} >= {1, 2, 31}  # others did
    assert 32 not in {image_id for _i, image_id in shorts}
    # image 0 lost slot 0 to image 32: none after that
    assert all(i < taken for i, image_id in shorts if image_id == 0)
    # with SHORT_HORIZON between the two announcements, the newer image takes the slot cleanly,
    # and the older one sends no more short fragments
    s = _sender(max_images=64)
    s.ingest(ImageInput(seafloor(48, 64, seed=0), time=0.0), 0.0)
    _frames(s, 3, 1.0)
    for i in range(1, 33):
        s.ingest(ImageInput(seafloor(48, 64, seed=i), time=float(i)), float(i))
    msgs = _frames(s, 800, 10.0 + SHORT_HORIZON)
    ids = {s.image_of(m) for m in msgs if isinstance(m, ImageShortFragment)}
    assert 32 in ids and 0 not in ids


def test_many_images_sharing_slots_under_loss_land_every_byte_in_its_own_image() -> None:
    """40 images (slots wrap) over 64-byte frames with 30 % loss both ways: topside holds each
    image's own bytes, and short fragments carried most of them."""
    m = ImageryModality()
    s = m.sender({**CFG, "max_images": 64, "rto": 20.0})
    r = m.receiver({"max_ack_bytes": 61, "retry": 30.0, "max_tries": 100})
    for i in range(40):
        s.ingest(ImageInput(seafloor(48, 64, seed=100 + i), time=3.0 * i), 3.0 * i)
    t = Transfer(s, r, mtu=64, down=Bernoulli(0.3, 5), up=Bernoulli(0.3, 6), now=120.0)
    t.run(lambda: not s.order() and all(i in r.images for i in s.images), 20000)
    assert len(s.images) == 40
    for image_id, tx in s.images.items():
        rx = r.images[image_id]
        held = np.flatnonzero(rx.have)
        assert rx.contiguous() >= tx.goal
        assert bytes(rx.buf[i] for i in held) == bytes(tx.enc.body[i] for i in held), image_id
    sent = [e.message for e in t.events if e.direction == "down"]
    short = sum(len(f.data) for f in sent if isinstance(f, ImageShortFragment))
    plain = sum(len(f.data) for f in sent if isinstance(f, ImageFragment))
    assert short > plain
    assert {s.image_of(f) for f in sent if isinstance(f, ImageShortFragment)} >= {10, 20, 30}
    assert SHORT_SLOTS == 32

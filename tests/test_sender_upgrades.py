"""The bathymetry and imagery senders saved by version 1 (0.1.0 and early 0.2 work, in the
shapes they had before detections, spare work, frame fates and standing requests) load through
their ``upgrade=`` hooks as version 2 senders that work."""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from coex_core.state import dumps, loads

from .test_tracker import _edit, _walk


def _to_v1(name: str, drop: tuple[str, ...]) -> Any:
    def change(doc: dict[str, Any]) -> None:
        doc["classes"][name] = 1

        def strip(o: dict[str, Any]) -> None:
            if o["$o"] == name:
                for k in drop:
                    o["f"].pop(k, None)
        _walk(doc, strip)
    return change


def _floor(n: int = 400) -> np.ndarray:
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 64, (n, 2))
    return np.column_stack([xy, -30.0 + 0.05 * xy[:, 0]])


def test_a_bathymetry_sender_saved_before_detections_and_spare_work_loads() -> None:
    from coex_plugins.bathymetry.sender import SENDER_DEFAULTS, BathymetrySender

    s = BathymetrySender()
    s.ingest(_floor(), 10.0)
    drop = ("_focused", "_low", "focus_bytes", "_resend", "_confirmed", "_standing", "_standing_checked",
            "standing_expiry", "max_standing")
    old = loads(_edit(dumps(s), _to_v1("bathymetry.Sender", drop)))
    assert isinstance(old, BathymetrySender)
    assert (old._focused, old._low, old.focus_bytes, old._resend, old._confirmed, old._standing) == ({}, False, 0, {}, {}, {})
    assert old._standing_checked == -math.inf
    assert (old.standing_expiry, old.max_standing) == (float(SENDER_DEFAULTS["standing_expiry"]),
                                                      int(SENDER_DEFAULTS["max_standing"]))
    assert old.fill(200, 20.0), "the upgraded sender sends its map"


def test_a_bathymetry_sender_of_version_1_with_spare_work_keeps_it() -> None:
    from coex_plugins.bathymetry.sender import BathymetrySender

    s = BathymetrySender({"standing_expiry": 99.0})
    s._resend[(0, 1, 2)] = 5.0
    old = loads(_edit(dumps(s), _to_v1("bathymetry.Sender", ("_focused", "_low", "focus_bytes"))))
    assert old._resend == {(0, 1, 2): 5.0} and old.standing_expiry == 99.0 and old._focused == {}


def test_an_imagery_sender_saved_before_issue_41_fates_and_standing_requests_loads() -> None:
    from coex_plugins.imagery.sender import SENDER_DEFAULTS, ImageInput, ImagerySender

    s = ImagerySender()
    pixels = (np.arange(64 * 96) % 251).astype(np.uint8).reshape(64, 96)
    s.ingest(ImageInput(pixels, time=5.0), 5.0)
    drop = ("_backdrop", "_low", "_fates", "_standing", "_answers", "standing_expiry", "max_standing")
    old = loads(_edit(dumps(s), _to_v1("imagery.Sender", drop)))
    assert isinstance(old, ImagerySender)
    assert old._backdrop is None and old._low is False and old._standing == {} and old._answers == []
    assert isinstance(old._fates, deque) and old._fates.maxlen == 64
    assert (old.standing_expiry, old.max_standing) == (float(SENDER_DEFAULTS["standing_expiry"]),
                                                      int(SENDER_DEFAULTS["max_standing"]))
    assert old.fill(200, 10.0), "the upgraded sender announces and sends its image"


def test_an_imagery_sender_of_version_1_with_fates_keeps_them() -> None:
    from coex_plugins.imagery.sender import ImagerySender

    s = ImagerySender()
    s._fates.extend([1, 0, 1])
    old = loads(_edit(dumps(s), _to_v1("imagery.Sender", ("_standing", "_answers"))))
    assert list(old._fates) == [1, 0, 1] and old._standing == {}


def test_an_imagery_sender_of_version_2_loads_with_no_announcement_copies_counted() -> None:
    from coex_plugins.imagery.sender import ImagerySender

    s = ImagerySender()
    s._fates.extend([0, 0, 1])

    def v2(doc: dict[str, Any]) -> None:
        doc["classes"]["imagery.Sender"] = 2

        def strip(o: dict[str, Any]) -> None:
            if o["$o"] == "imagery.Sender":
                o["f"].pop("_announce_sends", None)
        _walk(doc, strip)
    old = loads(_edit(dumps(s), v2))
    assert old._announce_sends == {} and list(old._fates) == [0, 0, 1]

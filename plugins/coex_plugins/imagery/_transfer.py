"""One image in the vehicle's hands (:class:`_Tx`: its coded body, what topside acknowledged, when
each byte went, its goal and requested regions), what a crop is (:class:`CropOf`) and the sizes of
the fragments that carry it (:func:`fragment_size`). Used by :mod:`.sender`, which re-exports the
public names."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import persistent, to_stamp
from coex.messages import ImageAnnounce, ImageCrop, ImageFragment
from coex.wire import (
    FRAGMENT_MAX_DATA,
    FRAGMENT_MAX_MARKS,
    FRAGMENT_NEAR_OFFSET_BITS,
    encoded_size,
)

from .codec import Encoded

MAX_FRAGMENT_DATA = FRAGMENT_MAX_DATA
MAX_MARKS = FRAGMENT_MAX_MARKS
#: offsets from here on take the fragment header's long form
_FAR_OFFSET = 1 << FRAGMENT_NEAR_OFFSET_BITS


@persistent("imagery.CropOf")
@dataclass(frozen=True)
class CropOf:
    """What a crop (an image coded from a rectangle of another, answering a region request) is:
    its ``parent`` image, the ``box`` (x0, y0, x1, y1) in the parent's pixels, the region request
    ``command_id``, the parent packets ``base`` (from the first) whose decode it refines, the
    parent layers ``cover`` it is at least as good as inside the box, and the PSNR it brings the
    box to (``psnr``, dB, against the vehicle's image) from ``base_psnr``."""

    parent: int
    box: tuple[int, int, int, int]
    command_id: int
    base: int
    cover: int
    psnr: float
    base_psnr: float


@functools.cache
def _fragment_head(n_marks: int, far: bool) -> int:
    """Bytes of a fragment's type id, header and marks, as the codec counts them: the data bytes
    follow the header's bits, so every data byte adds exactly one byte to the message."""
    probe = ImageFragment(0, _FAR_OFFSET if far else 0, 0 if n_marks else None, tuple(range(n_marks)),
                          bytes(n_marks))
    return encoded_size(probe) - n_marks


def fragment_size(n_marks: int, n_data: int, offset: int = 0) -> int:
    """Encoded bytes of an ``ImageFragment`` at ``offset`` with ``n_marks`` packet marks and
    ``n_data`` data bytes (type id included; spec/wire-format.md, type 33)."""
    return _fragment_head(n_marks, offset >= _FAR_OFFSET) + n_data


def _upgrade_tx(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (0.1.0 and early 0.2 work) was saved in the shapes it had before region requests
    (no ``region``), crops (no ``crop``), repeated bytes (no ``sends``) and frame interest (no
    ``interest``). Version 2 always has them: an older transfer loads with no region requested,
    as an image (not a crop), every byte counted as sent no time yet, and interest 0."""
    out = dict(fields)
    out.setdefault("region", None)
    out.setdefault("crop", None)
    out.setdefault("interest", 0.0)
    if out.get("sends") is None:
        out["sends"] = np.zeros(len(out["enc"].body), np.uint8)
    return out


@persistent("imagery.Tx", version=2, upgrade=_upgrade_tx)
class _Tx:
    __slots__ = (
        "acked",
        "announced_at",
        "crop",
        "default_goal",
        "enc",
        "explicit",
        "goal",
        "heard",
        "image_id",
        "interest",
        "region",
        "sends",
        "sent_at",
        "time",
        "x",
        "y",
    )

    def __init__(self, image_id: int, enc: Encoded, time: float, x: float | None, y: float | None,
                 default_goal: int) -> None:
        self.image_id = image_id
        self.enc = enc
        self.time = time
        self.x = x
        self.y = y
        self.announced_at: float | None = None
        self.heard = False
        n = len(enc.body)
        self.acked: npt.NDArray[np.bool_] = np.zeros(n, bool)
        self.sent_at: npt.NDArray[np.float64] = np.full(n, -np.inf)
        #: how often each byte was sent (a requested image's bytes are repeated under loss)
        self.sends: npt.NDArray[np.uint8] = np.zeros(n, np.uint8)
        self.default_goal = default_goal
        self.goal = default_goal
        self.explicit: int | None = None
        #: bytes wanted beyond the goal prefix: the packets of requested regions (None: none)
        self.region: npt.NDArray[np.bool_] | None = None
        #: a crop of another image (answering a region request), or None for an image
        self.crop: CropOf | None = None
        #: how much the frame stands out from the frames before it (:func:`interest`)
        self.interest = 0.0

    @property
    def total(self) -> int:
        return len(self.enc.body)

    def wanted(self, goal: int | None = None) -> npt.NDArray[np.bool_]:
        """Bytes to deliver: the prefix up to ``goal`` (default: the image's goal) and the
        packets of requested regions."""
        m = np.zeros(self.total, bool)
        m[: self.goal if goal is None else goal] = True
        if self.region is not None:
            m |= self.region
        return m

    def needs(self) -> bool:
        if self.goal > 0 and not bool(self.acked[: self.goal].all()):
            return True
        return self.region is not None and bool((self.region & ~self.acked).any())

    def unacked(self) -> int:
        return int(np.count_nonzero(self.wanted() & ~self.acked))

    def announce(self) -> ImageAnnounce | ImageCrop:
        crop = self.crop
        if crop is not None:
            x0, y0, x1, y1 = crop.box
            return ImageCrop(self.image_id, crop.parent, crop.command_id, x0, y0, x1, y1, self.total,
                             self.enc.params, crop.base, crop.cover)
        return ImageAnnounce(self.image_id, to_stamp(self.time), self.x, self.y, self.enc.width,
                             self.enc.height, self.enc.grey, self.total, self.enc.params)


def packet_layers(enc: Encoded) -> npt.NDArray[np.int64]:
    """The quality layer of each packet of ``enc``, in codestream order."""
    from .codec import packet_order

    out: npt.NDArray[np.int64] = packet_order(enc.stream, enc.width, enc.height)[:, 0]
    return out


def _packets(enc: Encoded) -> list[bytes | None]:
    """Every packet of ``enc``'s body."""
    from .codec import split_packets

    return split_packets(enc.body, enc.packet_starts)


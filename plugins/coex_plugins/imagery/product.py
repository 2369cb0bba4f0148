"""The imagery receiver's products: an image, a crop (a region of one coded on its own) and the
vehicle's progress."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from coex import TypedProduct

__all__ = ["CropProduct", "ImageProduct", "ProgressProduct"]


@dataclass(frozen=True, kw_only=True)
class _ImageFields(TypedProduct):
    """What an image and a crop both say: its announcement and what topside holds of it."""

    image_id: int
    #: the vehicle's stamp (wrapped) and the time it stands for
    stamp: int
    time: float
    #: where it was taken (metres east/north; None when the vehicle did not say)
    x: float | None
    y: float | None
    width: int
    height: int
    grey: bool
    total_bytes: int
    held_bytes: int
    #: bytes held from the start without a gap
    contiguous: int
    packets_used: int
    packets: int
    bytes_used: int
    layers_complete: int
    layers: int
    complete: bool
    precincts: int


@dataclass(frozen=True, kw_only=True)
class ImageProduct(_ImageFields):
    """An image (kind ``image``, key its id). ``data``: its pixels as topside shows them (its
    crops pasted over it), None before any decode."""

    #: its region requests: command_id, box, kind, value, state, served, bytes,
    #: layers_complete and, for one served by a crop, ``crop`` (a dict)
    regions: list[dict[str, Any]]
    #: the image ids of its crops
    crops: list[int]


@dataclass(frozen=True, kw_only=True)
class CropProduct(_ImageFields):
    """A crop (kind ``image-crop``, key its image id): a region of ``parent`` coded on its own.
    ``data``: its pixels, None before any decode."""

    parent: int
    #: [x0, y0, x1, y1] in the parent's pixels (x1, y1 exclusive)
    box: list[int]
    command_id: int
    base: int
    cover: int
    #: drawn over its parent
    shown: bool


@dataclass(frozen=True, kw_only=True)
class ProgressProduct(TypedProduct):
    """The vehicle's imagery progress (kind ``image-progress``, key ``vehicle``)."""

    stamp: int
    pending: int
    current: int | None
    unacked_fragments: int
    next_images: list[int]

"""Bathymetry modality: a real-time quadtree seafloor map sent as compact subgrids.

Subsea, :class:`BathymetrySender` ingests multibeam soundings (``N x 3`` arrays, ``.npy``, ``.csv``
or ROS bags) into a :class:`QuadtreeMap` and streams changed subgrids coarsest level first, each
predicted from the coarser level topside already holds where frame acks say it does
(:class:`~coex_core.messages.PredictedSubgrid`), on its own otherwise;
topside, :class:`BathymetryReceiver` assembles every level, tracks what it holds and how old it
is, and asks for regions or gaps (:class:`~coex_core.messages.MapRoiRequest`). See
``docs/bathymetry.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from coex import Modality, decode_subgrid, decode_subgrid_units, encode_subgrid, subgrid_bits
from coex.messages import (
    MapMetadata,
    MapRoiReply,
    MapRoiRequest,
    Message,
    PredictedSubgrid,
    Subgrid,
)

from .baseline import size_2022
from .export import (
    Candidate,
    find_targets,
    hillshade,
    write_geotiff,
    write_geotiff_tiled,
    write_level_geotiff,
    write_png,
)
from .points import iter_points, load_points, pointcloud2_xyz, write_pointcloud_bag
from .quadtree import InputError, LevelBlock, QuadtreeMap
from .receiver import RECEIVER_DEFAULTS, BathymetryReceiver, Region
from .sender import SENDER_DEFAULTS, BathymetrySender

__all__ = [
    "BathymetryModality",
    "BathymetryReceiver",
    "BathymetrySender",
    "Candidate",
    "InputError",
    "LevelBlock",
    "QuadtreeMap",
    "RECEIVER_DEFAULTS",
    "Region",
    "SENDER_DEFAULTS",
    "decode_subgrid",
    "decode_subgrid_units",
    "encode_subgrid",
    "find_targets",
    "hillshade",
    "iter_points",
    "load_points",
    "pointcloud2_xyz",
    "size_2022",
    "subgrid_bits",
    "write_geotiff",
    "write_geotiff_tiled",
    "write_level_geotiff",
    "write_png",
    "write_pointcloud_bag",
]


class BathymetryModality(Modality):
    """The ``bathymetry`` modality plugin (entry point ``coex.modalities``)."""

    name: ClassVar[str] = "bathymetry"
    version: ClassVar[str] = "1"
    messages: ClassVar[tuple[type[Message], ...]] = (MapMetadata, Subgrid, PredictedSubgrid, MapRoiReply)
    requests: ClassVar[tuple[type[Message], ...]] = (MapRoiRequest,)
    #: map metadata once a minute (23 B) while the dive goes on, after every subgrid is held
    keepalive_bytes_per_hour: ClassVar[int] = 1500

    @staticmethod
    def decode_subgrid(sg: Subgrid) -> Any:
        """Elevations of one subgrid (NaN = empty): what layers below the plugins (the LCM
        transport's map summaries) reach through the registry, never by importing it."""
        return decode_subgrid(sg)

    def sender(self, config: Mapping[str, Any] | None = None) -> BathymetrySender:
        return BathymetrySender(config)

    def receiver(self, config: Mapping[str, Any] | None = None) -> BathymetryReceiver:
        return BathymetryReceiver(config)

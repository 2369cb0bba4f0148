"""Detection messages: what a detector on the vehicle found in the vehicle's own data (a relief
anomaly of its full-resolution map, an object in one of its frames), sent as a suggestion."""

from __future__ import annotations

import construct as cs

from ..messages import Detection, DetectionSource
from ._primitives import Body, Bounded, Enum, Rule, Stamp, When
from ._registry import MessageSpec, register

XY = dict(lo=-50000, hi=50000, res=0.1, unit="m")
#: the largest length or width a detection reports (m)
MAX_EXTENT = 50.8
#: the largest footprint a detection reports (m²)
MAX_FOOTPRINT = 1022


def _is_image(ctx: cs.Container) -> bool:
    return int(ctx.source) == DetectionSource.IMAGE


DETECTION = Body(
    "detection_id" / Bounded(0, 1023) * "Detection id (the vehicle's; wraps at 1024): a detection sent "
    "again under its id with a newer stamp replaces the older one",
    "source" / Enum(DetectionSource) * "What it was found in",
    "stamp" / Stamp() * "Time of the newest data it was found in",
    "x" / Bounded(**XY) * "Position east of the origin",  # type: ignore[arg-type]
    "y" / Bounded(**XY) * "Position north of the origin",  # type: ignore[arg-type]
    "score" / Bounded(0, 1, 0.01) * "How well it matches what the detector looks for (ranks detections)",
    "height" / Bounded(0, 25.4, 0.1, optional=True, unit="m") * "Height above the local background",
    "length" / Bounded(0, MAX_EXTENT, 0.2, optional=True, unit="m") * "Length of its footprint (the long axis)",
    "width" / Bounded(0, MAX_EXTENT, 0.2, optional=True, unit="m") * "Width of its footprint (across the long axis)",
    "orientation" / Bounded(0, 179, 1, optional=True, unit="deg")
    * "Direction of the long axis, clockwise from north (an axis: 0..179)",
    "footprint" / Bounded(0, MAX_FOOTPRINT, 1, optional=True, unit="m^2") * "Area that stands out",
    "image_id" / When("`source` = IMAGE", _is_image, Bounded(0, 1023)) * "The frame it was found in",
    Rule(lambda ctx: ctx.length is None or ctx.width is None or ctx.width <= ctx.length,
         "`width` is above `length`, both given (the length is the long axis; either alone is valid)", "width above length"),
    Rule(lambda ctx: ctx.image_id is None or _is_image(ctx),
         "`image_id` is given and `source` is not IMAGE", encode_only=True),
)

_LARGEST = Detection(1023, DetectionSource.IMAGE, 2**18 - 1, 50000.0, 50000.0, 1.0, 25.4, MAX_EXTENT, MAX_EXTENT,
                     179.0, MAX_FOOTPRINT, 1023)

register(MessageSpec(
    14, Detection, DETECTION, False, "detections",
    "Vehicle report: something a detector on the vehicle found in its own data (a suggestion).",
    largest=lambda: _LARGEST,
    cases=lambda: [
        ("car_in_map", Detection(0, DetectionSource.MAP, 1500, 102.3, 145.1, 0.87, 1.5, 4.6, 1.8, 30.0, 9)),
        ("bare", Detection(17, DetectionSource.OTHER, 0, -50000.0, -50000.0, 0.0)),
        ("round", Detection(5, DetectionSource.MAP, 77, 0.0, -12.5, 0.05, 0.0, 3.0, 3.0, 0.0, 0)),
        ("in_a_frame", Detection(1022, DetectionSource.IMAGE, 4321, 57.4, 104.2, 0.42, image_id=9)),
        ("width_without_length", Detection(6, DetectionSource.OTHER, 90, 1.0, 2.0, 0.5, width=2.2)),
        ("largest", _LARGEST),
    ],
))

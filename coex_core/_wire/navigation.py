"""Navigation aiding (issue 56): topside tells the vehicle where it truly was (a USBL fix, or
topside's estimate of its drift applied to its track), for a vehicle whose navigation accepts
aiding."""

from __future__ import annotations

from ..messages import PositionFix, PositionSource
from ._primitives import Body, Bounded, Enum, Stamp
from ._registry import MessageSpec, register

XY = dict(lo=-50000, hi=50000, res=0.1, unit="m")

POSITION_FIX = Body(
    "command_id" / Bounded(0, 255) * "Command id, echoed in the CommandAck",
    "source" / Enum(PositionSource) * "What the position comes from",
    "stamp" / Stamp() * "When the vehicle was there",
    "x" / Bounded(**XY) * "True position east of the origin",  # type: ignore[arg-type]
    "y" / Bounded(**XY) * "True position north of the origin",  # type: ignore[arg-type]
    "sigma" / Bounded(0, 102.3, 0.1, unit="m") * "1-sigma horizontal uncertainty of the position",
    "depth" / Bounded(0, 6000, 0.1, optional=True, unit="m") * "Depth below the surface, if known",
)

_LARGEST = PositionFix(255, PositionSource.OTHER, 2**18 - 1, -50000.0, 50000.0, 102.3, 6000.0)

register(MessageSpec(
    15, PositionFix, POSITION_FIX, False, "navigation",
    "Topside command: where the vehicle truly was (for a vehicle that accepts aiding); answered by a "
    "CommandAck.",
    largest=lambda: _LARGEST,
    cases=lambda: [
        ("usbl_fix", PositionFix(3, PositionSource.USBL, 7200, 102.3, -45.6, 5.3, 471.2)),
        ("estimate", PositionFix(0, PositionSource.ESTIMATE, 0, 0.0, 0.0, 0.0)),
        ("far", PositionFix(200, PositionSource.OTHER, 100, 50000.0, -50000.0, 12.5)),
        ("largest", _LARGEST),
    ],
))

"""CoEx over LCM: the ``lcm`` transport, the ``coex.frame_t`` codec and decoded product types.

* :class:`LcmTransport` (URI ``lcm:udpm://239.255.76.67:7667?ttl=0&channel=COEX``, any LCM
  provider URL, per-direction channels ``tx=``/``rx=``) carries CoEx frames as ``coex.frame_t``.
* :func:`encode_frame` / :func:`decode_frame` / :func:`unpack_event`: pure codec functions.
* :mod:`~coex_transports.lcm.products`: ``coex.vehicle_status_t`` and ``coex.map_level_t``
  for LCM tools (lcm-spy, consoles).
* ``coex.points_t`` and ``coex.nav_t``: what the vehicle's ``lcm`` input reads (soundings and
  the vehicle's position) from an LCM vehicle; ``coex.survey_request_t`` and
  ``coex.survey_state_t``: what its ``lcm`` autonomy output publishes and reads.
* :mod:`~coex_transports.lcm.replay`: offline re-analysis of an ``lcm-logger`` log
  (``coex replay --lcm-log FILE``).

The LCM types are defined in ``spec/bindings/coex.lcm`` and generated into ``_types/`` by
``regen.py`` with the ``lcm-gen`` of the ``lcm`` wheel.
"""

from __future__ import annotations

from ._codec import (
    FRAME_T_FINGERPRINT,
    FRAME_T_OVERHEAD,
    LcmFrame,
    decode_frame,
    encode_frame,
    is_frame_t,
    unpack_event,
)
from ._transport import DEFAULT_URL, LcmConfig, LcmTransport, check_provider_url, parse_lcm_uri
from ._types import (
    frame_t,
    map_level_t,
    nav_t,
    points_t,
    survey_request_t,
    survey_state_t,
    vehicle_status_t,
)

__all__ = [
    "DEFAULT_URL",
    "FRAME_T_FINGERPRINT",
    "FRAME_T_OVERHEAD",
    "LcmConfig",
    "LcmFrame",
    "LcmTransport",
    "check_provider_url",
    "decode_frame",
    "encode_frame",
    "frame_t",
    "is_frame_t",
    "map_level_t",
    "nav_t",
    "parse_lcm_uri",
    "points_t",
    "survey_request_t",
    "survey_state_t",
    "unpack_event",
    "vehicle_status_t",
]

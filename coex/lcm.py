"""What an input or autonomy output on LCM needs from the ``lcm`` transport: its default provider
URL, the check of a provider URL (:func:`check_provider_url`: address, port, options, as LCM
will need them) and the CoEx LCM types (``spec/bindings/coex.lcm``). Imported on demand (``import coex`` does
not load it); the ``lcm`` library itself is needed only to open an LCM instance."""

from __future__ import annotations

from coex_transports.lcm import (
    DEFAULT_URL,
    check_provider_url,
    nav_t,
    points_t,
    survey_request_t,
    survey_state_t,
)

__all__ = ["DEFAULT_URL", "check_provider_url", "nav_t", "points_t", "survey_request_t", "survey_state_t"]

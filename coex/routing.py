"""What a node routes to a modality: the type ids it declares (``messages`` / ``message_ids``,
``requests`` / ``request_ids``), which of its requests are routine, and the type id of a message.

For tools that check a plugin's declarations (the conformance kit); a plugin declares its ids as
class attributes of its :class:`coex.Modality` and never needs these.

The public face of :mod:`coex_core.routing` (``from coex.routing import ...``); the names are the
core's (the same objects).
"""

from __future__ import annotations

from coex_core.routing import declared_ids, routine_ids, type_id

__all__ = ["declared_ids", "routine_ids", "type_id"]

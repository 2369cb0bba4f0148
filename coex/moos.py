"""What an input or autonomy output on MOOS needs from the ``moos`` transport: its pure-Python
client of the MOOS wire protocol. Imported on demand (``import coex`` does not load it)."""

from __future__ import annotations

from coex_transports.moos import MAX_TIME_WARP, MoosClient, MoosMessage

__all__ = ["MAX_TIME_WARP", "MoosClient", "MoosMessage"]

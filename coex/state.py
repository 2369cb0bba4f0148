"""Explicit, versioned state (never pickle): what a node store saves of a sender or a receiver.

``@persistent("yourname.Thing")`` registers a class under a stable name (``docs/plugins.md``
section 3.1); ``dumps`` / ``loads`` write and read a state document as a store does, so that a
plugin's own tests (and the conformance kit's restart test) can save and restore its sender and
receiver exactly as a node does.

The public face of :mod:`coex_core.state` (``from coex.state import ...``); the names are the
core's (the same objects).
"""

from __future__ import annotations

from coex_core.state import StateError, dumps, loads, persistent

__all__ = ["StateError", "dumps", "loads", "persistent"]

"""The CoEx runtime: what runs a node over its transports, apart from the transports' protocol code.

* :mod:`.runner`: :class:`~coex_runtime.runner.Runner` (one node's loop over its transports, on a
  real or simulated clock) and :class:`~coex_runtime.runner.SimNetwork` (nodes in simulated time);
* :mod:`.store`: :class:`~coex_runtime.store.NodeStore`, a node's state and journal in SQLite.

Import these names from the :mod:`coex` facade; this package may move.
"""

"""The topside web console: one page for the map, images, time series, link and queues.

``coex topside --transport URI [--http 127.0.0.1:8080]`` runs a topside node over a transport
and serves the console; ``coex demo --gui`` serves it against the simulated dive. In code::

    server = serve(node, "127.0.0.1", 8080)   # a hub attached to a topside node
    ...  # in the loop that drives the node, under server.hub.lock:
    server.hub.pump(node, now)                # node events -> console
    server.close()

See ``docs/console.md``.
"""

from __future__ import annotations

from .actions import CallSink, CommandSink, ConsoleActions
from .node import NodeCommands, attach, drive_simulation, pump, tap_receiver
from .render import elevation_rgb, png_bytes
from .server import ConsoleHub, ConsoleServer, serve
from .state import SECTIONS, ConsoleState

__all__ = [
    "SECTIONS",
    "CallSink",
    "CommandSink",
    "ConsoleActions",
    "ConsoleHub",
    "ConsoleServer",
    "ConsoleState",
    "NodeCommands",
    "attach",
    "drive_simulation",
    "elevation_rgb",
    "png_bytes",
    "pump",
    "serve",
    "tap_receiver",
]

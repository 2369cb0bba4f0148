"""The topside web console: one page for the map, images, time series, link and queues.

``coex topside --transport URI [--http 127.0.0.1:8080]`` runs a topside node over a transport
and serves the console; ``coex demo --gui`` serves it against the simulated dive. In code::

    state = ConsoleState(schedules={0: schedule})
    hub = ConsoleHub(state, NodeCommands(node, clock), clock)   # actions -> node commands
    node.add_receiver(BathymetryModality, tap_receiver(receiver, hub))  # raw messages too
    server = serve(hub, "127.0.0.1", 8080)                      # background thread
    ...  # in the loop that drives the node, under hub.lock:
    hub.pump(node, now)                                         # node events -> console
    server.close()

See ``docs/console.md``.
"""

from __future__ import annotations

from .node import NodeCommands, TapReceiver, attach, drive_simulation, pump, tap_receiver
from .server import ConsoleHub, ConsoleServer, serve
from .state import SECTIONS, ConsoleActions, ConsoleState, elevation_rgb, png_bytes

__all__ = [
    "SECTIONS",
    "ConsoleActions",
    "ConsoleHub",
    "ConsoleServer",
    "ConsoleState",
    "NodeCommands",
    "TapReceiver",
    "attach",
    "drive_simulation",
    "elevation_rgb",
    "png_bytes",
    "pump",
    "serve",
    "tap_receiver",
]

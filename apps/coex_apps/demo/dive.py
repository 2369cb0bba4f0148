"""The demo dive: a time-compressed re-enactment of NUI dive 040's nested survey.

Two CoEx nodes (vehicle 2, topside 1), each a channel manager with the built-in modalities, talk
through two simulated WHOI Micromodems (:class:`~coex_transports.micromodem.simulator.ModemNetwork`):
the bytes between each node and its modem are the NMEA sentences of the real driver
(:class:`~coex_transports.micromodem.MicromodemTransport`), so the demo runs the same code path
as a vehicle with real hardware. The scenario (:mod:`coex_apps.demo.scenario`: a preset or a
TOML file) sets the site, the survey, the modem rate, the TDMA slots, the loss model and where
the ship is. Everything runs on one simulated clock that jumps from event to event, so a
two-hour dive takes well under a minute.

The dive: descent; a lawnmower multibeam survey over a seafloor with ripples, cars (the targets)
and possibly car-sized boulders (decoys) that the operator does not know about; camera transects
at low altitude over the candidates the operator ranked in the received 1 m map, most car-like
first, while camera time remains; then the vehicle holds until the end of the dive. The scripted
operator (:mod:`coex_apps.demo.operator`) decides only from what reached topside. The goals
are judged against the simulation's truth (:mod:`coex_apps.demo.truth`), never against the
operator's belief.
"""

from __future__ import annotations

from .config import DEMO_COMMAND_KEY, EPOCH, TOPSIDE, VEHICLE, Decision, DemoConfig, DemoResult
from .outcome import iter_decisions
from .run import run_demo
from .world import Leg, Track, build_nodes, dive_schedule, nui_schedule

__all__ = ["DEMO_COMMAND_KEY", "EPOCH", "TOPSIDE", "VEHICLE", "Decision", "DemoConfig",
           "DemoResult", "Leg", "Track", "build_nodes", "dive_schedule", "iter_decisions",
           "nui_schedule", "run_demo"]

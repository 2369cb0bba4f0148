"""Sample data for the console's tests and for a look at the page without a vehicle.

Everything is made by the real plugins from generated data (no files, fixed seeds):
:func:`survey_points` (a simulated multibeam survey over a seafloor with two car-sized targets),
:func:`feed_sample` (runs the bathymetry, time-series and imagery senders and receivers and puts
their real messages and products into a :class:`~.state.ConsoleState`, with a vehicle track,
queue and link status), and :class:`RecordingSender` (a vehicle-side sender wrapper that records
the requests it handled, to check a console action reached the vehicle).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from coex import ModalitySender, to_stamp
from coex import messages as m

from .state import ConsoleState

__all__ = ["RecordingSender", "feed_sample", "survey_points", "drain"]


class RecordingSender(ModalitySender):
    """Wraps a vehicle-side sender; ``handled`` lists every request it was given."""

    def __init__(self, inner: ModalitySender) -> None:
        self.inner = inner
        self.handled: list[m.Message] = []

    def ingest(self, data: Any, now: float) -> None:
        self.inner.ingest(data, now)

    def fill(self, max_bytes: int, now: float) -> list[m.Message]:
        return self.inner.fill(max_bytes, now)

    def handle(self, message: m.Message, now: float) -> list[m.Message]:
        self.handled.append(message)
        return self.inner.handle(message, now)

    def pending_bytes(self) -> int:
        return self.inner.pending_bytes()


def survey_points(size: float = 96.0, seed: int = 0) -> npt.NDArray[np.float64]:
    """Soundings (N x 3) of a short simulated survey over ``size`` x ``size`` metres."""
    from coex_plugins.bathymetry.sim import Seafloor, simulate_survey

    floor = Seafloor.default(size=size, seed=seed, depth=60.0)
    # dense enough for a sounding in every 1 m cell (a sparser survey leaves the finest level striped)
    survey = simulate_survey(floor, altitude=20.0, beams=128, ping_rate=2.0, speed=1.5, seed=seed)
    return np.asarray(survey.points, float)


def drain(sender: ModalitySender, now: float, budget: int = 240,
          limit: int = 10000) -> list[m.Message]:
    """Everything a sender has to send at ``now`` (``budget`` bytes per call)."""
    out: list[m.Message] = []
    for _ in range(limit):
        got = sender.fill(budget, now)
        if not got:
            break
        out.extend(got)
    return out


def feed_sample(state: ConsoleState, *, t0: float = 36000.0, seed: int = 0,
                images: int = 3, series: bool = True) -> dict[str, Any]:
    """Fill ``state`` with a sample dive made by the real plugins. Returns what was made
    (``subgrids``, ``series_receiver``, ``image_receiver`` ...)."""
    from coex_plugins.bathymetry import BathymetrySender

    made: dict[str, Any] = {}
    now = t0
    # vehicle track: a lawnmower over the survey area
    xs = np.concatenate([np.linspace(0, 90, 30), np.full(5, 90.0), np.linspace(90, 0, 30)])
    ys = np.concatenate([np.full(30, 20.0), np.linspace(20, 60, 5), np.full(30, 60.0)])
    for k, (x, y) in enumerate(zip(xs, ys)):
        st = m.VehicleStatus(to_stamp(now - 600 + 9 * k), float(round(x, 1)), float(round(y, 1)),
                             60.0 - 20.0, 20.0, 90.0 if k < 30 else 270.0, 1.5, 80,
                             m.VehicleMode.SURVEY, 0)
        state.apply_message(st, now - 600 + 9 * k)
    # bathymetry: a survey through the real sender (send delay 0), every subgrid to the state
    sender = BathymetrySender({"send_delay": 0.0, "levels": 4})
    sender.ingest(survey_points(seed=seed), now - 300)
    msgs = drain(sender, now)
    subgrids = [x for x in msgs if isinstance(x, m.SubgridMessage)]
    state.apply_messages(msgs, now)
    made["subgrids"] = subgrids
    made["bathymetry_sender"] = sender
    # queue and link status
    state.apply_message(m.QueueStatus(to_stamp(now), (
        m.StreamStatus(0, True, 0, 127, 1, 64, 0, 0),
        m.StreamStatus(3, True, 1, 30, 12, 2880, 96, 2),
        m.StreamStatus(4, True, 1, 30, 4, 960, 32, 0),
        m.StreamStatus(5, False, 1, 45, 0, 0, 0, 0))), now)
    state.apply_message(m.LinkStatus(to_stamp(now - 20), 0, 8, 2, 11.5, -0.3), now)
    if series:
        made.update(_series(state, now, seed))
    if images:
        made.update(_images(state, now, images, seed))
    return made


def _series(state: ConsoleState, now: float, seed: int) -> dict[str, Any]:
    from coex_plugins.timeseries import TimeSeriesModality
    from coex_plugins.timeseries.synth import dataset

    data = dataset(duration=1800.0, period=1.0, seed=seed, t0=now - 1800.0)
    mod = TimeSeriesModality()
    tx = mod.sender({"channels": [s.channel() for s in data], "block_samples": 512,
                     "max_latency": 60.0})
    rx = mod.receiver()
    tx.ingest({s.name: (s.times, s.values) for s in data}, now)
    for msg in drain(tx, now):
        for p in rx.receive(msg, now):
            state.apply_product("timeseries", p, now)
    return {"series_sender": tx, "series_receiver": rx}


def _images(state: ConsoleState, now: float, n: int, seed: int) -> dict[str, Any]:
    from coex_plugins.imagery import ImageryModality
    from coex_plugins.imagery.sender import ImageInput
    from coex_plugins.imagery.synth import seafloor

    mod = ImageryModality()
    tx = mod.sender()
    rx = mod.receiver()
    for k in range(n):
        tx.ingest(ImageInput(seafloor(120, 160, seed=seed + k), now - 200 + 60 * k,
                             30.0 + 10 * k, 40.0), now)
    for msg in drain(tx, now)[:40]:  # part of the transfer: thumbnails still refining
        for p in rx.receive(msg, now):
            state.apply_product("imagery", p, now)
    return {"image_sender": tx, "image_receiver": rx}

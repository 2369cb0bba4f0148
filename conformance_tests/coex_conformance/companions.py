"""The plugins the suite runs beside the plugin under test: every built-in modality that is
installed (bathymetry, imagery, time series) and the sample third-party plugin
(:mod:`coex_conformance.sample`), each with small inputs and a test of convergence.

The built-in modalities' own conformance tests use the same inputs (one source of truth).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from coex_core.modality import Modality, ModalityReceiver, ModalitySender

__all__ = ["Companion", "companions"]

BATHY_LEVELS = 3
TS_T0 = 1_700_000_000.0
TS_WINDOW_ERROR = 0.03


@dataclass(frozen=True)
class Companion:
    name: str
    modality: Callable[[], Modality]
    sample_inputs: Callable[[], list[tuple[float, Any]]]
    converged: Callable[[ModalitySender, ModalityReceiver], bool]
    sender_config: Callable[[], Any] = lambda: None
    receiver_config: Callable[[], Any] = lambda: None
    start_requests: Callable[[ModalityReceiver, float], None] | None = None


# ------------------------------------------------------------------------- bathymetry
@lru_cache(maxsize=1)
def _survey() -> Any:
    from coex_plugins.bathymetry.sim import Seafloor, simulate_survey

    floor = Seafloor.default(size=48.0, seed=1, relief=0.5)
    return simulate_survey(floor, beams=64, ping_rate=2.0, seed=2, outlier_fraction=0.004)


def bathy_inputs() -> list[tuple[float, Any]]:
    return list(_survey().pings(batch=20))


def bathy_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every subgrid version the sender's quadtree holds."""
    from coex_plugins.bathymetry import BathymetryReceiver, BathymetrySender

    assert isinstance(sender, BathymetrySender) and isinstance(receiver, BathymetryReceiver)
    held = {level: receiver.holdings(level) for level in range(BATHY_LEVELS)}
    return all(held[lv].get((ix, iy)) == st for (lv, ix, iy), st in sender.inventory().items())


def _bathy() -> Companion:
    from coex_plugins.bathymetry import BathymetryModality

    return Companion("bathymetry", BathymetryModality, bathy_inputs, bathy_converged,
                     lambda: {"levels": BATHY_LEVELS}, lambda: {"levels": BATHY_LEVELS})


# ---------------------------------------------------------------------------- imagery
def imagery_inputs() -> list[tuple[float, Any]]:
    from coex_plugins.imagery import ImageInput
    from coex_plugins.imagery.synth import seafloor

    return [(10.0 * (i + 1), ImageInput(seafloor(48, 64, seed=i), x=1.5 * i, y=-2.0)) for i in range(3)]


def imagery_config() -> dict[str, Any]:
    return {"layer_bytes": [30, 60, 120, 240, 480, 900], "default_goal": "layer:4", "rto": 12.0}


def imagery_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every image up to its goal, decodable."""
    from coex_plugins.imagery import ImageryReceiver, ImagerySender

    assert isinstance(sender, ImagerySender) and isinstance(receiver, ImageryReceiver)
    for image_id, tx in sender.images.items():
        rx = receiver.images.get(image_id)
        if rx is None or rx.contiguous() < tx.goal or rx.image is None:
            return False
    return bool(sender.images)


def _imagery() -> Companion:
    from coex_plugins.imagery import ImageryModality

    return Companion("imagery", ImageryModality, imagery_inputs, imagery_converged, imagery_config)


# ------------------------------------------------------------------------ time series
def ts_config() -> dict[str, Any]:
    from coex_plugins.timeseries import synth

    m, t = synth.dataset(duration=2400.0, t0=TS_T0, jitter=0.2)
    return {"channels": [m.channel(), t.channel()], "block_samples": 1024, "max_latency": 600.0}


def ts_inputs() -> list[tuple[float, Any]]:
    from coex_plugins.timeseries import synth

    m, t = synth.dataset(duration=2400.0, t0=TS_T0, jitter=0.2)
    step = 120
    return [(float(m.times[min(i + step, m.times.size) - 1]),
             {"methane": (m.times[i:i + step], m.values[i:i + step]),
              "temperature": (t.times[i:i + step], t.values[i:i + step])})
            for i in range(0, m.times.size, step)]


def ts_start(receiver: ModalityReceiver, now: float) -> None:
    from coex_plugins.timeseries import TimeSeriesReceiver

    assert isinstance(receiver, TimeSeriesReceiver)
    receiver.request(0, TS_T0 + 600.0, TS_T0 + 1200.0, TS_WINDOW_ERROR)


def ts_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every block of both channels, and the requested window to its bound."""
    import numpy as np

    from coex_plugins.timeseries import TimeSeriesReceiver, TimeSeriesSender

    assert isinstance(sender, TimeSeriesSender) and isinstance(receiver, TimeSeriesReceiver)
    for name in ("methane", "temperature"):
        want = sender.blocks(name)
        try:
            held = receiver.bounds(name)
        except Exception:
            return False
        if len(held) != len(want) or not all(np.isfinite(b) for _, _, b in held):
            return False
    window = [b for s, e, b in receiver.bounds("methane") if e >= TS_T0 + 600 and s <= TS_T0 + 1200]
    return bool(window) and max(window) <= TS_WINDOW_ERROR and sender.unacked() == 0


def _timeseries() -> Companion:
    from coex_plugins.timeseries import TimeSeriesModality

    return Companion("timeseries", TimeSeriesModality, ts_inputs, ts_converged, ts_config,
                     start_requests=ts_start)


def _sample() -> Companion:
    from .sample import SampleModality, sample_converged, sample_inputs

    return Companion(SampleModality.name, SampleModality, sample_inputs, sample_converged)


def companions() -> list[Companion]:
    """The sample third-party plugin and every built-in modality installed (a built-in whose
    plugin cannot be imported, e.g. imagery without glymur, is left out)."""
    out = [_sample()]
    for make, module in ((_bathy, "coex_plugins.bathymetry"), (_imagery, "coex_plugins.imagery"),
                         (_timeseries, "coex_plugins.timeseries")):
        try:
            importlib.import_module(module)
        except ImportError:
            continue
        out.append(make())
    return out

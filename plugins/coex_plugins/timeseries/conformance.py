"""The timeseries modality's conformance inputs (entry point ``coex.conformance: timeseries``):
what ``coex plugins check timeseries`` and the suite's two-node tests run it on, and what its own
conformance tests use (one source of truth)."""

from __future__ import annotations

from typing import Any

from coex import ModalityReceiver, ModalitySender
from coex_conformance.companions import Companion

TS_T0 = 1_700_000_000.0
TS_WINDOW_ERROR = 0.03


def ts_config() -> dict[str, Any]:
    from . import synth

    m, t = synth.dataset(duration=2400.0, t0=TS_T0, jitter=0.2)
    return {"channels": [m.channel(), t.channel()], "block_samples": 1024, "max_latency": 600.0}


def ts_inputs() -> list[tuple[float, Any]]:
    from . import synth

    m, t = synth.dataset(duration=2400.0, t0=TS_T0, jitter=0.2)
    step = 120
    return [(float(m.times[min(i + step, m.times.size) - 1]),
             {"methane": (m.times[i:i + step], m.values[i:i + step]),
              "temperature": (t.times[i:i + step], t.values[i:i + step])})
            for i in range(0, m.times.size, step)]


def ts_start(receiver: ModalityReceiver, now: float) -> None:
    from . import TimeSeriesReceiver

    assert isinstance(receiver, TimeSeriesReceiver)
    receiver.request(0, TS_T0 + 600.0, TS_T0 + 1200.0, TS_WINDOW_ERROR)


def ts_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds every block of both channels, and the requested window to its bound."""
    import numpy as np

    from . import TimeSeriesReceiver, TimeSeriesSender

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


def companion() -> Companion:
    """Entry point ``coex.conformance: timeseries``."""
    from . import TimeSeriesModality

    return Companion("timeseries", TimeSeriesModality, ts_inputs, ts_converged, ts_config,
                     start_requests=ts_start)

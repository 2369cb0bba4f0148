"""The time-series modality passes the CoEx modality conformance suite."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest

from coex_conformance import ModalityFixtures, ModalityTests
from coex_core.modality import Modality, ModalityReceiver, ModalitySender
from coex_plugins.timeseries import TimeSeriesModality, TimeSeriesReceiver, TimeSeriesSender, synth

T0 = 1_700_000_000.0
WINDOW_ERROR = 0.03


class TimeSeriesFixtures(ModalityFixtures):
    @pytest.fixture
    def modality(self) -> Modality:
        return TimeSeriesModality()

    @pytest.fixture
    def sender_config(self) -> dict[str, Any]:
        m, t = synth.dataset(duration=2400.0, t0=T0, jitter=0.2)
        return {"channels": [m.channel(), t.channel()], "block_samples": 1024, "max_latency": 600.0}

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        m, t = synth.dataset(duration=2400.0, t0=T0, jitter=0.2)
        step = 120
        return [
            (float(m.times[min(i + step, m.times.size) - 1]),
             {"methane": (m.times[i:i + step], m.values[i:i + step]),
              "temperature": (t.times[i:i + step], t.values[i:i + step])})
            for i in range(0, m.times.size, step)
        ]

    @pytest.fixture
    def start_requests(self) -> Callable[[ModalityReceiver, float], None]:
        def start(receiver: ModalityReceiver, now: float) -> None:
            assert isinstance(receiver, TimeSeriesReceiver)
            receiver.request(0, T0 + 600.0, T0 + 1200.0, WINDOW_ERROR)

        return start

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        def done(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
            assert isinstance(sender, TimeSeriesSender) and isinstance(receiver, TimeSeriesReceiver)
            for name in ("methane", "temperature"):
                want = sender.blocks(name)
                try:
                    held = receiver.bounds(name)
                except Exception:
                    return False
                if len(held) != len(want) or not all(np.isfinite(b) for _, _, b in held):
                    return False
            window = [b for s, e, b in receiver.bounds("methane") if e >= T0 + 600 and s <= T0 + 1200]
            return bool(window) and max(window) <= WINDOW_ERROR and sender.unacked() == 0

        return done


class TestTimeSeriesModality(ModalityTests, TimeSeriesFixtures):
    pass

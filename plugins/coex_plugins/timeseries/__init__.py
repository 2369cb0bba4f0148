"""The time-series modality: progressive, outlier-preserving telemetry of scalar sensor channels.

Channels (name, unit, range, resolution) are sampled at possibly irregular times. The vehicle
cuts each channel into blocks on a regular grid, wavelet-transforms them (PyWavelets) and sends
for every block a coarse overview first (approximation plus the largest detail coefficients,
which carry the spikes), then, on topside request, residual refinement passes down to a maximum
absolute error. Every chunk decodes on its own; each pass states the error bound it achieves.
See ``docs/timeseries.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from coex import Modality
from coex.messages import (
    Message,
    TimeSeriesAck,
    TimeSeriesChannel,
    TimeSeriesChunk,
    TimeSeriesRequest,
)

from .product import SeriesProduct
from .receiver import Series, TimeSeriesReceiver
from .sender import ChannelConfig, InvalidSamples, Samples, TimeSeriesSender

__all__ = [
    "ChannelConfig",
    "InvalidSamples",
    "Samples",
    "Series",
    "SeriesProduct",
    "TimeSeriesModality",
    "TimeSeriesReceiver",
    "TimeSeriesSender",
]


class TimeSeriesModality(Modality):
    """Entry point ``timeseries`` of the ``coex.modalities`` group."""

    name: ClassVar[str] = "timeseries"
    version: ClassVar[str] = "1"
    messages: ClassVar[tuple[type[Message], ...]] = (TimeSeriesChannel, TimeSeriesChunk)
    requests: ClassVar[tuple[type[Message], ...]] = (TimeSeriesRequest, TimeSeriesAck)
    #: acks of data: handled without expediting the stream
    routine: ClassVar[tuple[type[Message] | int, ...]] = (TimeSeriesAck,)

    def sender(self, config: Mapping[str, Any] | None = None) -> TimeSeriesSender:
        return TimeSeriesSender(config)

    def receiver(self, config: Mapping[str, Any] | None = None) -> TimeSeriesReceiver:
        return TimeSeriesReceiver(config)

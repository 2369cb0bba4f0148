"""Time-series messages: channel registration, wavelet chunks, refinement requests."""

from __future__ import annotations

from ..messages import TimeSeriesChannel, TimeSeriesChunk, TimeSeriesRequest
from ._primitives import Align8, Body, Bounded, Float32, RawBytes, Stamp, Text
from ._registry import MessageSpec, register

CHANNEL = Bounded(0, 31) * "Channel id"
MAX_CHUNK_DATA = 224

TS_CHANNEL = Body(
    "channel" / CHANNEL,
    Align8(),
    "lo" / Float32() * "Lowest valid value",
    "hi" / Float32() * "Highest valid value",
    "resolution" / Float32() * "Resolution of the sensor",
    "name" / Text(32) * "Channel name",
    "unit" / Text(16) * "Unit (UDUNITS spelling)",
)

TS_CHUNK = Body(
    "channel" / CHANNEL,
    "start" / Stamp() * "Time of the block's first sample",
    "period" / Bounded(0.1, 409.5, 0.1, unit="s") * "Sample period of the block",
    "count" / Bounded(1, 4096, unit="samples") * "Samples in the block",
    "level" / Bounded(0, 15) * "Refinement pass (0 = coarse overview)",
    "step" / Bounded(0, 255) * "Quantisation step code of this pass",
    "data" / RawBytes(max_len=MAX_CHUNK_DATA) * "Coded coefficients",
)

TS_REQUEST = Body(
    "command_id" / Bounded(0, 255) * "Command id",
    "channel" / CHANNEL,
    "start" / Stamp() * "Window start",
    "end" / Stamp() * "Window end",
    Align8(),
    "max_error" / Float32() * "Maximum absolute error wanted, in the channel's unit",
)

_BIG_CHUNK = TimeSeriesChunk(31, 2**18 - 1, 409.5, 4096, 15, 255, b"\xff" * MAX_CHUNK_DATA)

register(MessageSpec(
    48, TimeSeriesChannel, TS_CHANNEL, True, "timeseries", "A channel's name, unit, range and resolution.",
    largest=lambda: TimeSeriesChannel(31, "n" * 32, "u" * 16, -1.0, 1.0, 0.5),
    cases=lambda: [
        ("empty_strings", TimeSeriesChannel(0, "", "", 0.0, 0.0, 0.0)),
        ("methane", TimeSeriesChannel(3, "methane", "nmol/L", 0.0, 1000.0, 0.5)),
        ("largest", TimeSeriesChannel(31, "n" * 32, "u" * 16, -3.4028234663852886e+38, 3.4028234663852886e+38, 0.0009765625)),
    ],
))
register(MessageSpec(
    49, TimeSeriesChunk, TS_CHUNK, True, "timeseries", "A self-contained piece of a channel's wavelet code.",
    largest=lambda: _BIG_CHUNK,
    cases=lambda: [
        ("empty", TimeSeriesChunk(0, 0, 0.1, 1, 0, 0, b"")),
        ("overview", TimeSeriesChunk(2, 3600, 1.0, 1024, 0, 17, bytes.fromhex("deadbeef0102"))),
        ("largest", _BIG_CHUNK),
    ],
))
register(MessageSpec(
    50, TimeSeriesRequest, TS_REQUEST, False, "timeseries", "Topside request to refine a window.",
    largest=lambda: TimeSeriesRequest(0, 0, 0, 0, 0.0),
    cases=lambda: [
        ("zero", TimeSeriesRequest(0, 0, 0, 0, 0.0)),
        ("window", TimeSeriesRequest(9, 3, 3600, 4200, 0.05000000074505806)),
        ("max", TimeSeriesRequest(255, 31, 2**18 - 1, 2**18 - 1, 1000.0)),
    ],
))

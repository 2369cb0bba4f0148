"""Time-series messages: channel registration, wavelet chunks, acks, refinement requests.

The meaning of ``step``/``error`` codes and of a chunk's ``data`` bytes (the coefficient code)
is specified in ``docs/timeseries.md``; both are log-scale codes ``2 ** ((code - 160) / 8)``
in the channel's unit.
"""

from __future__ import annotations

import construct as cs

from ..messages import (
    TimeSeriesAck,
    TimeSeriesChannel,
    TimeSeriesChunk,
    TimeSeriesPart,
    TimeSeriesRequest,
    Wavelet,
)
from ._primitives import (
    Align8,
    Body,
    Bool,
    Bounded,
    Count,
    Enum,
    Float32,
    RawBytes,
    Stamp,
    Text,
    When,
)
from ._registry import MessageSpec, register

CHANNEL = Bounded(0, 31) * "Channel id"
#: Largest ``data`` of a chunk: a chunk with every optional field stays within 251 bytes.
MAX_CHUNK_DATA = 232
#: Flat coefficient indices of a block (a 4096-sample block has fewer than 4200 coefficients).
MAX_COEFFICIENT = 8191
MAX_ACK_PARTS = 40


def _offset() -> cs.Construct:
    return Bounded(0, 0.99, 0.01, unit="s")


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
    "start" / Stamp() * "Whole seconds of the time of the block's first sample",
    "offset" / _offset() * "Fraction of a second of the time of the block's first sample",
    "period" / Bounded(0.01, 655.35, 0.01, unit="s") * "Sample period of the block's grid",
    "count" / Bounded(1, 4096, unit="samples") * "Samples in the block",
    "wavelet" / Enum(Wavelet) * "Wavelet of the block's transform",
    "level" / Bounded(0, 15) * "Refinement pass (0 = coarse overview)",
    "samples" / Bool() * "1: the pass codes residual samples, not wavelet coefficients",
    "step" / Bounded(0, 255) * "Quantisation step of this pass: 2^((code-160)/8)",
    "error" / Bounded(0, 255) * "Max abs error once passes 0..level are held: at most 2^((code-160)/8)",
    "partial" / cs.Rebuild(Bool(), lambda ctx: ctx.first is not None or ctx.end is not None)
    * "1 if the chunk holds only coefficients [first, end) of the pass (derived)",
    "first" / When("`partial` = 1", cs.this.partial, Bounded(0, MAX_COEFFICIENT)) * "First coefficient held",
    "end" / When("`partial` = 1", cs.this.partial, Bounded(1, MAX_COEFFICIENT + 1))
    * "One past the last coefficient held (the code is `end` minus 1)",
    Align8(),
    "data" / RawBytes(max_len=MAX_CHUNK_DATA) * "Coded coefficients",
)

TS_PART = cs.Struct(
    "start" / Stamp() * "Block start (whole seconds)",
    "offset" / _offset() * "Block start (fraction of a second)",
    "level" / Bounded(0, 15) * "Refinement pass",
    "first" / Bounded(0, MAX_COEFFICIENT) * "First coefficient of the chunk (0 for a whole pass)",
)

TS_ACK = Body(
    "channel" / CHANNEL,
    "registered" / Bool() * "Topside holds the channel's registration",
    "n_parts" / Count(0, MAX_ACK_PARTS, "parts"),
    "parts" / cs.Array(cs.this.n_parts, TS_PART) * "Chunks topside holds",
)

TS_REQUEST = Body(
    "command_id" / Bounded(0, 255) * "Command id",
    "channel" / CHANNEL,
    "start" / Stamp() * "Window start",
    "end" / Stamp() * "Window end",
    Align8(),
    "max_error" / Float32() * "Maximum absolute error wanted, in the channel's unit",
)


def _big_chunk() -> TimeSeriesChunk:
    return TimeSeriesChunk(31, 2**18 - 1, 0.99, 655.35, 4096, Wavelet.DB4, 15, True, 255, 255,
                           MAX_COEFFICIENT, MAX_COEFFICIENT + 1, b"\xff" * MAX_CHUNK_DATA)


def _big_ack() -> TimeSeriesAck:
    part = TimeSeriesPart(2**18 - 1, 0.99, 15, MAX_COEFFICIENT)
    return TimeSeriesAck(31, True, (part,) * MAX_ACK_PARTS)


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
    49, TimeSeriesChunk, TS_CHUNK, True, "timeseries",
    "A self-contained piece of one refinement pass of one block of a channel's wavelet code.",
    largest=_big_chunk,
    cases=lambda: [
        ("empty", TimeSeriesChunk(0, 0, 0.0, 0.01, 1, Wavelet.HAAR, 0, False, 0, 0, None, None, b"")),
        ("overview", TimeSeriesChunk(2, 3600, 0.25, 1.0, 1024, Wavelet.BIOR22, 0, False, 137, 141, None, None,
                                     bytes.fromhex("deadbeef0102"))),
        ("part", TimeSeriesChunk(5, 7200, 0.5, 0.25, 4000, Wavelet.BIOR44, 3, False, 100, 101, 17, 2051,
                                 bytes.fromhex("0011"))),
        ("samples", TimeSeriesChunk(1, 100, 0.0, 2.0, 300, Wavelet.BIOR44, 2, True, 90, 90, None, None,
                                    bytes.fromhex("8000"))),
        ("largest", _big_chunk()),
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
register(MessageSpec(
    51, TimeSeriesAck, TS_ACK, False, "timeseries",
    "Topside ack of a channel's registration and of the chunks it holds.",
    largest=_big_ack,
    cases=lambda: [
        ("registration_only", TimeSeriesAck(0, True, ())),
        ("two_parts", TimeSeriesAck(3, False, (TimeSeriesPart(3600, 0.0, 0, 0),
                                               TimeSeriesPart(3600, 0.0, 2, 311)))),
        ("largest", _big_ack()),
    ],
))

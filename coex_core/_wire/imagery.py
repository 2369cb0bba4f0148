"""Imagery messages: announce, fragments, selective acks, goals, time requests, progress."""

from __future__ import annotations

import construct as cs

from ..messages import (
    ByteRange,
    GoalKind,
    ImageAck,
    ImageAnnounce,
    ImageByTimeRequest,
    ImageCrop,
    ImageFragment,
    ImageGoal,
    ImageRegionRequest,
    ImageShortFragment,
    RegionGoal,
    TimeDirection,
    TransferProgress,
)
from ._primitives import (
    Bits,
    Body,
    Bool,
    Bounded,
    Count,
    Entries,
    Enum,
    FarFlag,
    Flag,
    NearFar,
    RawBytes,
    Rule,
    Stamp,
    When,
)
from ._registry import MessageSpec, register

IMAGE_ID = Bounded(0, 1023) * "Image id (wraps at 1024)"
OFFSET_MAX = 2**20 - 1
#: Largest fragment payload. A fragment with many packet marks carries less data: the whole
#: message must still fit in 251 bytes (a 256-byte sub-frame with header and CRC); encoding a
#: larger one raises EncodeError and decoding one raises DecodeError.
MAX_FRAGMENT_DATA = 244
MAX_PACKET_MARKS = 31
#: Packets in one codestream: at most 32 layers x 8 resolutions x 3 components.
MAX_PACKET_INDEX = 1023
MAX_ACK_RANGES = 15
MAX_NEXT_IMAGES = 8

IMAGE_ANNOUNCE = Body(
    "image_id" / IMAGE_ID,
    "stamp" / Stamp() * "Capture time",
    "x" / Bounded(-50000, 50000, 0.1, optional=True, unit="m") * "Position east, if known",
    "y" / Bounded(-50000, 50000, 0.1, optional=True, unit="m") * "Position north, if known",
    "width" / Bounded(1, 4096, unit="px") * "Image width",
    "height" / Bounded(1, 4096, unit="px") * "Image height",
    "grey" / Bool() * "Grey (1) or colour (0)",
    "total_bytes" / Bounded(0, OFFSET_MAX, unit="B") * "Codestream body size",
    "params" / Bits(15) * "Coding parameter code (progression, resolutions, layers, wavelet)",
)

#: Offsets below 2**NEAR_OFFSET_BITS (4 KiB, where the first quality layers of an image lie) take
#: the short form: the fragment header is then 4 bytes.
NEAR_OFFSET_BITS = 12

IMAGE_FRAGMENT = Body(
    "image_id" / IMAGE_ID,
    "marked" / Flag("packets"),
    "far" / FarFlag("offset", NEAR_OFFSET_BITS),
    "offset" / NearFar(NEAR_OFFSET_BITS, 20, "far", unit="B") * "Offset of data in the codestream body",
    "n_packets" / When("`marked` = 1", cs.this.marked, Count(1, MAX_PACKET_MARKS, "packets")),
    "packet" / When("`marked` = 1", cs.this.marked, Bounded(0, MAX_PACKET_INDEX))
    * "Index of the JPEG 2000 packet holding the first data byte",
    "packets" / Entries("`n_packets` entries (none when `marked` = 0)", lambda ctx: ctx.n_packets or 0,
                        Bounded(0, 255, unit="B"))
    * "Offsets in data where a packet starts, increasing, at most len(data) (0 = data starts packet "
    "`packet`; len(data) = the next packet starts right after data)",
    "n_data" / Count(0, MAX_FRAGMENT_DATA, "data"),
    "data" / RawBytes(max_len=MAX_FRAGMENT_DATA, count="n_data") * "Codestream bytes",
    Rule(lambda ctx: bool(ctx.far) == (ctx.offset >= 1 << NEAR_OFFSET_BITS),
         f"`far` is 1 while `offset` is below {1 << NEAR_OFFSET_BITS} (the long form of a short offset: "
         "one encoding per offset)", "canonical"),
    Rule(lambda ctx: (ctx.packet is None) == (not ctx.packets),
         "`packet` is given without packet marks, or packet marks without `packet`", encode_only=True),
    Rule(lambda ctx: all(a < b for a, b in zip(ctx.packets, ctx.packets[1:]))
         and all(p <= len(ctx.data) for p in ctx.packets),
         "the `packets` entries are not strictly increasing, or one is above the number of `data` bytes",
         "out of order"),
)

#: The short fragment (type 40): the image by its id modulo 2**SHORT_SLOT_BITS among the newest
#: ids announced, offsets below 2**SHORT_OFFSET_BITS, at most SHORT_MAX_DATA bytes; 3 header bytes.
SHORT_SLOT_BITS = 5
SHORT_OFFSET_BITS = 13
SHORT_MAX_DATA = 64

IMAGE_SHORT_FRAGMENT = Body(
    "slot" / Bounded(0, 2**SHORT_SLOT_BITS - 1)
    * f"The image: its id modulo {2**SHORT_SLOT_BITS}, among the {2**SHORT_SLOT_BITS} newest ids announced "
    "(spec/payloads.md 3.3)",
    "offset" / Bounded(0, 2**SHORT_OFFSET_BITS - 1, unit="B") * "Offset of data in the codestream body",
    "n_data" / Count(1, SHORT_MAX_DATA, "data"),
    "data" / RawBytes(max_len=SHORT_MAX_DATA, count="n_data") * "Codestream bytes",
)

BYTE_RANGE = cs.Struct(
    "start" / Bounded(0, OFFSET_MAX, unit="B") * "First byte held",
    "end" / Bounded(0, OFFSET_MAX, unit="B") * "One past the last byte held",
)

IMAGE_ACK = Body(
    "image_id" / IMAGE_ID,
    "contiguous" / Bounded(0, OFFSET_MAX, unit="B") * "Every byte below this is held",
    "n_ranges" / Count(0, MAX_ACK_RANGES, "ranges"),
    "ranges" / cs.Array(cs.this.n_ranges, BYTE_RANGE) * "Further ranges held (see ByteRange)",
)

IMAGE_GOAL = Body(
    "command_id" / Bounded(0, 255) * "Command id",
    "image_id" / IMAGE_ID,
    "kind" / Enum(GoalKind) * "Goal kind",
    "value" / Bounded(0, 255) * "Percent of the image (FRACTION) or number of layers (LAYER)",
)

IMAGE_REGION = Body(
    "command_id" / Bounded(0, 255) * "Command id",
    "image_id" / IMAGE_ID,
    "x0" / Bounded(0, 4095, unit="px") * "Left edge (first column in the region)",
    "y0" / Bounded(0, 4095, unit="px") * "Top edge (first row in the region)",
    "x1" / Bounded(1, 4096, unit="px") * "Right edge (one past the last column)",
    "y1" / Bounded(1, 4096, unit="px") * "Bottom edge (one past the last row)",
    "kind" / Enum(RegionGoal) * "Goal kind",
    "value" / Bounded(0, 65535) * "QUALITY: PSNR in the region, 0.1 dB; LAYER: layers; BYTES: body bytes",
    Rule(lambda ctx: ctx.x0 < ctx.x1 and ctx.y0 < ctx.y1, "`x0` >= `x1` or `y0` >= `y1` (no pixel in the region)",
         "empty region"),
)

IMAGE_CROP = Body(
    "image_id" / Bounded(0, 1023) * "The crop's own image id (the same sequence as images'; wraps at 1024)",
    "parent" / Bounded(0, 1023) * "The image it is cut from",
    "command_id" / Bounded(0, 255) * "The region request it answers",
    "x0" / Bounded(0, 4095, unit="px") * "Left edge in the parent (first column of the crop)",
    "y0" / Bounded(0, 4095, unit="px") * "Top edge in the parent (first row of the crop)",
    "x1" / Bounded(1, 4096, unit="px") * "Right edge in the parent (one past the last column)",
    "y1" / Bounded(1, 4096, unit="px") * "Bottom edge in the parent (one past the last row)",
    "total_bytes" / Bounded(0, OFFSET_MAX, unit="B") * "The crop's codestream body size",
    "params" / Bits(15) * "The crop's coding parameter code (as ImageAnnounce.params)",
    "base" / Bounded(0, MAX_PACKET_INDEX + 1)
    * "Packets of the parent, from its first, whose decode the crop refines (0: none, mid-grey)",
    "cover" / Bounded(0, 32) * "Quality layers of the parent the whole crop is at least as good as inside the box",
    Rule(lambda ctx: ctx.x0 < ctx.x1 and ctx.y0 < ctx.y1, "`x0` >= `x1` or `y0` >= `y1` (no pixel in the crop)",
         "empty region"),
)

IMAGE_BY_TIME = Body(
    "command_id" / Bounded(0, 255) * "Command id",
    "stamp" / Stamp() * "Time of interest",
    "direction" / Enum(TimeDirection) * "Nearest, or the image before / after",
)

TRANSFER_PROGRESS = Body(
    "stamp" / Stamp() * "Time of the report",
    "pending" / Bounded(0, 1023, saturating=True) * "Images announced but not at their goal",
    "current" / Bounded(0, 1023, optional=True) * "Image being sent",
    "unacked_fragments" / Bounded(0, 255, saturating=True) * "Fragments sent but not acked",
    "n_next" / Count(0, MAX_NEXT_IMAGES, "next_images"),
    "next_images" / cs.Array(cs.this.n_next, Bounded(0, 1023)) * "Images to be sent next, in order",
)

#: The largest fragment: every mark, and as much data as still fits in 251 bytes.
_BIG_FRAG = ImageFragment(
    1023, OFFSET_MAX, MAX_PACKET_INDEX, tuple(range(MAX_PACKET_MARKS)), b"\xff" * 212
)
_BIG_PLAIN = ImageFragment(1023, OFFSET_MAX, None, (), b"\xff" * MAX_FRAGMENT_DATA)
_BIG_ACK = ImageAck(1023, OFFSET_MAX, (ByteRange(OFFSET_MAX, OFFSET_MAX),) * MAX_ACK_RANGES)

register(MessageSpec(
    32, ImageAnnounce, IMAGE_ANNOUNCE, False, "imagery", "A new image exists on the vehicle.",
    largest=lambda: ImageAnnounce(0, 0, None, None, 1, 1, True, 0, 0),
    cases=lambda: [
        ("minimum", ImageAnnounce(0, 0, None, None, 1, 1, False, 0, 0)),
        ("nui_640x480", ImageAnnounce(17, 5123, 12.3, -45.6, 640, 480, True, 20366, 0x1234)),
        ("maximum", ImageAnnounce(1023, 2**18 - 1, 50000.0, -50000.0, 4096, 4096, True, OFFSET_MAX, 2**15 - 1)),
    ],
))
register(MessageSpec(
    33, ImageFragment, IMAGE_FRAGMENT, False, "imagery", "Bytes of an image's codestream body.",
    largest=lambda: _BIG_FRAG,
    cases=lambda: [
        ("empty", ImageFragment(0, 0, None, (), b"")),
        ("first_packet", ImageFragment(5, 0, 0, (0, 37), bytes(range(60)))),
        ("inside_packet", ImageFragment(17, 3120, None, (), bytes(range(200)))),
        ("last_near_offset", ImageFragment(17, 4095, None, (), bytes(range(50)))),
        ("first_far_offset", ImageFragment(17, 4096, 40, (3,), bytes(range(50)))),
        ("largest", _BIG_FRAG),
        ("largest_plain", _BIG_PLAIN),
    ],
))
register(MessageSpec(
    40, ImageShortFragment, IMAGE_SHORT_FRAGMENT, False, "imagery",
    "Bytes of the codestream body of one of the newest images, for small frames (no packet marks).",
    largest=lambda: ImageShortFragment(31, 2**SHORT_OFFSET_BITS - 1, b"\xff" * SHORT_MAX_DATA),
    cases=lambda: [
        ("one_byte", ImageShortFragment(0, 0, b"\x00")),
        ("mtu_64", ImageShortFragment(17, 1140, bytes(range(57)))),
        ("largest", ImageShortFragment(31, 2**SHORT_OFFSET_BITS - 1, b"\xff" * SHORT_MAX_DATA)),
    ],
))
register(MessageSpec(
    34, ImageAck, IMAGE_ACK, False, "imagery", "Selective ack of an image's bytes.",
    largest=lambda: _BIG_ACK,
    cases=lambda: [
        ("nothing", ImageAck(0, 0, ())),
        ("gaps", ImageAck(17, 450, (ByteRange(675, 900), ByteRange(1125, 2000)))),
        ("largest", _BIG_ACK),
    ],
))
register(MessageSpec(
    35, ImageGoal, IMAGE_GOAL, False, "imagery", "Topside command: an image's goal.",
    largest=lambda: ImageGoal(255, 1023, GoalKind.FULL, 255),
    cases=lambda: [
        ("skip", ImageGoal(0, 0, GoalKind.SKIP, 0)),
        ("fraction_50", ImageGoal(3, 694, GoalKind.FRACTION, 50)),
        ("full_max", ImageGoal(255, 1023, GoalKind.FULL, 255)),
    ],
))
register(MessageSpec(
    36, ImageByTimeRequest, IMAGE_BY_TIME, False, "imagery", "Topside request for an image by time.",
    largest=lambda: ImageByTimeRequest(255, 2**18 - 1, TimeDirection.AFTER),
    cases=lambda: [
        ("nearest_0", ImageByTimeRequest(0, 0, TimeDirection.NEAREST)),
        ("before", ImageByTimeRequest(4, 6100, TimeDirection.BEFORE)),
        ("after_max", ImageByTimeRequest(255, 2**18 - 1, TimeDirection.AFTER)),
    ],
))
register(MessageSpec(
    38, ImageRegionRequest, IMAGE_REGION, False, "imagery",
    "Topside command: bring a rectangle of an image to a goal (JPEG 2000 precincts).",
    largest=lambda: ImageRegionRequest(255, 1023, 4095, 4095, 4096, 4096, RegionGoal.BYTES, 65535),
    cases=lambda: [
        ("quarter_30db", ImageRegionRequest(7, 17, 0, 0, 320, 240, RegionGoal.QUALITY, 300)),
        ("layers", ImageRegionRequest(8, 17, 400, 300, 640, 480, RegionGoal.LAYER, 12)),
        ("bytes_max", ImageRegionRequest(255, 1023, 4095, 4095, 4096, 4096, RegionGoal.BYTES, 65535)),
    ],
))
register(MessageSpec(
    39, ImageCrop, IMAGE_CROP, False, "imagery",
    "A region of an image coded on its own (a crop answering a region request).",
    largest=lambda: ImageCrop(1023, 1023, 255, 4095, 4095, 4096, 4096, OFFSET_MAX, 2**15 - 1, 1024, 32),
    cases=lambda: [
        ("minimum", ImageCrop(0, 0, 0, 0, 0, 1, 1, 0, 0, 0, 0)),
        ("quarter_from_nothing", ImageCrop(18, 17, 7, 0, 0, 320, 240, 612, 0x0302, 0, 3)),
        ("eighth_over_30db", ImageCrop(19, 17, 8, 480, 240, 640, 480, 1437, 0x0302, 26, 4)),
        ("maximum", ImageCrop(1023, 1023, 255, 4095, 4095, 4096, 4096, OFFSET_MAX, 2**15 - 1, 1024, 32)),
    ],
))
register(MessageSpec(
    37, TransferProgress, TRANSFER_PROGRESS, False, "imagery", "What the image sender is doing.",
    largest=lambda: TransferProgress(0, 0, 1023, 0, (1023,) * MAX_NEXT_IMAGES),
    cases=lambda: [
        ("idle", TransferProgress(0, 0, None, 0, ())),
        ("busy", TransferProgress(7000, 12, 694, 9, (695, 696, 697))),
        ("largest", TransferProgress(2**18 - 1, 1023, 1023, 255, (1023,) * MAX_NEXT_IMAGES)),
    ],
))

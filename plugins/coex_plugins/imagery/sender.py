"""The subsea side of the imagery modality: announce, goals, selective repeat.

Memory and queue bounds (documented in ``docs/imagery.md``):

* at most ``max_images`` images are kept (default 64). Each keeps its body (at most the last
  layer target, 20,480 B by default), a byte map of what topside acknowledged (1 B per body
  byte) and the last send time of each byte (8 B per body byte): about 0.2 MB per image,
  13 MB for 64 images. When full, ingesting evicts the oldest image that needs nothing more,
  else the oldest without an operator goal, else the oldest image.
* the list of fragments sent but not yet acknowledged (for ``TransferProgress``) holds at most
  1024 entries.
* an image with an operator goal is served before every default transfer and is never evicted
  while another image can go instead; retransmission only resends bytes that were sent at least
  ``rto`` seconds ago and are still unacknowledged, so a lost ack costs one resend, never a stall.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import (
    CoexError,
    ConfigError,
    ModalitySender,
    Options,
    RequestRejected,
    merged_config,
    persistent,
    to_stamp,
    unwrap,
)
from coex.messages import (
    AckStatus,
    CommandAck,
    GoalKind,
    ImageAck,
    ImageAnnounce,
    ImageByTimeRequest,
    ImageCrop,
    ImageFragment,
    ImageGoal,
    ImageRegionRequest,
    ImageShortFragment,
    Message,
    RegionGoal,
    TimeDirection,
    TransferProgress,
)
from coex.options import anything, flag, integer, number, text
from coex.wire import (
    SHORT_FRAGMENT_MAX_DATA,
    SHORT_FRAGMENT_OFFSET_BITS,
    SHORT_FRAGMENT_SLOT_BITS,
    encoded_size,
)

from ._regions import BRIDGE_BYTES, _bridge, _within, box_psnr, decoded, fewest, held_packets, way
from ._transfer import (
    MAX_FRAGMENT_DATA,
    MAX_MARKS,
    CropOf,
    _packets,
    _Tx,
    fragment_size,
    packet_layers,
)
from .codec import (
    CodingParams,
    Encoded,
    add_residual,
    decode_packets,
    encode_image,
    encode_residual,
    psnr,
    region_packets,
)
from .goals import Goal, parse_goal
from .interest import interest

__all__ = ["CropOf", "Frame", "ImageInput", "ImagerySender", "SENDER_OPTIONS", "fragment_size", "interest",
           "BRIDGE_BYTES", "MAX_FRAGMENT_DATA", "MAX_MARKS", "packet_layers"]

#: A fragment message never exceeds this (the wire maximum).
MAX_MESSAGE = 251
MAX_NEXT = 8
#: on a low link a requested image's bytes go at most this many times before an ack
LOW_COPIES = 2
#: ``ImageShortFragment``: slots (image id modulo this), offsets below this, data at most this
SHORT_SLOTS = 1 << SHORT_FRAGMENT_SLOT_BITS
SHORT_OFFSETS = 1 << SHORT_FRAGMENT_OFFSET_BITS
SHORT_MAX_DATA = SHORT_FRAGMENT_MAX_DATA
#: a short fragment's type id and header
SHORT_HEAD = encoded_size(ImageShortFragment(0, 0, b"\0")) - 1
#: seconds a frame may still be on its way (across links) after the sender made it: an image
#: takes its slot for short fragments cleanly only this long after another image's announcement
#: in that slot was last sent (spec/payloads.md 3.3)
SHORT_HORIZON = 60.0
#: short fragments remembered with their image, for the channel's acked / lost
SHORT_RECORDS = 1024


@persistent("imagery.ImageInput")
@dataclass(frozen=True)
class ImageInput:
    """An image to ingest with its capture time (default: ``now``) and position (metres, local)."""

    image: Any
    time: float | None = None
    x: float | None = None
    y: float | None = None


@dataclass(frozen=True)
class Frame:
    """A frame the vehicle holds (:meth:`ImagerySender.frames`): its id, capture time, position
    (None when unknown), pixels (as coded) and interest (:func:`interest`)."""

    image_id: int
    time: float
    x: float | None
    y: float | None
    image: Any
    interest: float


#: coding options (:class:`~coex_plugins.imagery.codec.CodingParams` fields)
CODING_KEYS = ("progression", "resolutions", "layer_bytes", "irreversible", "grey", "max_size", "precincts",
               "layer_psnr", "tighten")
#: the imagery sender's options: the one declaration of their types, ranges and units (the
#: coding options, None by default, take CodingParams' defaults and are checked there too)
SENDER_OPTIONS = Options(
    progression=text(None, "JPEG 2000 progression order (CodingParams)", none=True),
    resolutions=integer(None, "wavelet resolutions (CodingParams)", lo=1, none=True),
    layer_bytes=anything(None, "bytes of each quality layer (CodingParams)"),
    irreversible=flag(None, "the irreversible 9/7 wavelet (CodingParams)"),
    grey=flag(None, "code images in grey (CodingParams)"),
    max_size=integer(None, "largest image side, in pixels (CodingParams)", lo=1, none=True),
    precincts=integer(None, "precinct size, 0: none (CodingParams)", lo=0, none=True),
    layer_psnr=anything(None, "the quality layers' PSNR targets (CodingParams)"),
    tighten=flag(None, "quality layers tightened to their marks (CodingParams)"),
    default_goal=anything("layer:2", "how far each image is sent unasked (a goal: layer:N, psnr:DB ...)"),
    request_goal=anything(None, "how far a requested image is sent (None: default_goal)"),
    max_images=integer(64, "images held", lo=1, hi=512),
    rto=number(60.0, "an unacknowledged fragment is sent again after", unit="s", above=0),
    progress_interval=number(60.0, "between two progress reports", unit="s", above=0),
    max_announces=integer(2, "sends of an image's announcement", lo=1),
    min_fragment=integer(16, "smallest fragment worth sending", unit="B", lo=1),
    standing_expiry=number(1800.0, "a standing request lasts", unit="s", lo=0),
    max_standing=integer(8, "standing requests kept", lo=0),
    marks=text("auto", "mark detections on the images", choices=("auto", "always")),
    crops=text("auto", "send crops around detections", choices=("auto", "never", "always")),
    short_fragments=flag(True, "bytes first sent of an image topside heard go in ImageShortFragment (type 40)"),
)
#: their defaults (a name kept for 0.x code)
SENDER_DEFAULTS: dict[str, Any] = SENDER_OPTIONS.defaults()


def _upgrade_sender(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (0.1.0 and early 0.2 work) was saved in three shapes: before issue 41 (no
    running background, no low-link flag), before frame fates were kept, before by-time requests
    could stand. Version 2 always has them. Version 3 counts the copies of requested images'
    announcements (none counted in an older save). Version 4 keeps the slots of short fragments
    (an older save has none: its images take their slots afresh, with their next announcement,
    and until then send ImageFragments)."""
    out = dict(fields)
    out.setdefault("_announce_sends", {})
    out.setdefault("short_fragments", True)
    out.setdefault("_slot_owner", {})
    out.setdefault("_slot_last", {})
    out.setdefault("_announced", set())
    out.setdefault("_shorts", deque(maxlen=SHORT_RECORDS))
    if "_low" not in out:
        out.setdefault("_backdrop", None)
        out["_low"] = False
    if out.get("_fates") is None:
        out["_fates"] = deque(maxlen=64)
    if out.get("_standing") is None:
        out["_standing"] = {}
        out["_answers"] = []
        out.setdefault("standing_expiry", float(SENDER_DEFAULTS["standing_expiry"]))
        out.setdefault("max_standing", int(SENDER_DEFAULTS["max_standing"]))
    return out


@persistent("imagery.Sender", version=4, upgrade=_upgrade_sender)
class ImagerySender(ModalitySender):
    _last_now: float = float("-inf")

    """Subsea side. Configuration keys (all optional):

    * coding: ``progression``, ``resolutions``, ``layer_psnr`` (quality marks, dB: 25, 30, 35,
      40; each image's layers end where it first reaches each), ``layer_bytes`` (fixed
      byte layers, used when given without ``layer_psnr`` or when ``layer_psnr`` is empty),
      ``irreversible``, ``grey``, ``max_size``, ``precincts`` (256; 0 = none, then region
      requests are refused; see :class:`~coex_plugins.imagery.codec.CodingParams`);
    * ``default_goal`` (``"layer:2"``, 30 dB with the default quality marks): the set-point every new image is sent to, in capture order;
    * ``request_goal`` (same as ``default_goal``): the goal given to an image found by an
      ``ImageByTimeRequest`` (it is then served first, like an operator goal);
    * ``max_images`` (64), ``rto`` (60 s: resend unacked bytes after this long; keep it above the
      ack round trip of the TDMA schedule),
      ``progress_interval`` (60 s), ``max_announces`` (2 per fill), ``min_fragment`` (16: a second
      fragment squeezed into what is left of a packet must carry at least this many bytes),
      ``standing_expiry`` (1800 s) and ``max_standing`` (8): an ``ImageByTimeRequest`` (nearest
      or after) for a time later than the newest image stands (answered ``PENDING``) until an
      image of that time is captured (then ``ACCEPTED`` and served like any request) or it
      expires (then ``REJECTED``);
    * ``marks`` (``"auto"``): when fragments carry packet marks. ``auto``: only where topside
      cannot find the packets by parsing their headers, i.e. after bytes that will never be sent
      (the packets of a region), and under loss (measured frame loss of 20 % or more: a lost
      fragment then does not hold back the packets after it); ``always``: every fragment.
    * ``short_fragments`` (true): bytes sent the first time, of an image whose announcement
      topside heard, go in ``ImageShortFragment`` (3 header bytes instead of 4 or 5) where it
      carries as much as an ``ImageFragment`` would (frames of up to about 70 bytes), when that
      image holds its slot (spec/payloads.md 3.3); false: ``ImageFragment`` only.
    """

    options = SENDER_OPTIONS

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, self.options, "imagery sender")
        self.coding = CodingParams.from_config({k: cfg[k] for k in CODING_KEYS if cfg[k] is not None})
        self.default_goal: Goal = parse_goal(cfg["default_goal"])
        self.request_goal: Goal = parse_goal(cfg["request_goal"] if cfg["request_goal"] is not None
                                             else self.default_goal)
        self.max_images = int(cfg["max_images"])
        self.rto = float(cfg["rto"])
        self.progress_interval = float(cfg["progress_interval"])
        self.max_announces = int(cfg["max_announces"])
        self.min_fragment = int(cfg["min_fragment"])
        self.standing_expiry = float(cfg["standing_expiry"])
        self.max_standing = int(cfg["max_standing"])
        self.marks = str(cfg["marks"])
        self.crops = str(cfg["crops"])
        self.short_fragments = bool(cfg["short_fragments"])
        self.images: dict[int, _Tx] = {}
        self._next_id = 0
        self._request_counter = 0
        self._inflight: deque[tuple[int, int, int]] = deque(maxlen=1024)
        self._current: int | None = None
        self._progress_at: float | None = None
        self._progress_dirty = False
        self._last_progress: tuple[Any, ...] | None = None
        self.evicted = 0
        #: the newest ``now`` seen (for :meth:`spare_bytes`, which has none)
        self._last_now = float("-inf")
        #: fates of recent fragments (1 delivered, 0 lost), from the channel's frame acks
        self._fates: deque[int] = deque(maxlen=64)
        #: the running background of the frames (:func:`interest`), and whether the channel
        #: finds the link low
        self._backdrop: npt.NDArray[np.float64] | None = None
        self._low = False
        #: command id -> (by-time request for a time not captured yet, expiry time)
        self._standing: dict[int, tuple[ImageByTimeRequest, float]] = {}
        #: final CommandAcks of served or expired standing requests, to send
        self._answers: list[Message] = []
        #: image id -> copies of a requested image's announcement sent since it was last due
        self._announce_sends: dict[int, int] = {}
        #: short fragments (spec/payloads.md 3.3): slot -> (image id of the last announcement
        #: sent in it, whether that image took the slot cleanly: its first announcement, at
        #: least SHORT_HORIZON after another image's in that slot); slot -> when an announcement
        #: was last sent in it; the ids announced (an id leaves when a new image takes it)
        self._slot_owner: dict[int, tuple[int, bool]] = {}
        self._slot_last: dict[int, float] = {}
        self._announced: set[int] = set()
        #: the short fragments sent lately, (slot, offset, data bytes, image id), for acked / lost
        self._shorts: deque[tuple[int, int, int, int]] = deque(maxlen=SHORT_RECORDS)

    # ------------------------------------------------------------------ ingest

    def ingest(self, data: Any, now: float) -> None:
        item = data if isinstance(data, ImageInput) else ImageInput(data)
        t = float(now if item.time is None else item.time)
        for v in (item.x, item.y):
            if v is not None and not (isinstance(v, int | float) and -50000 <= v <= 50000):
                raise ConfigError(f"position {v!r} outside +-50 km")
        enc = encode_image(item.image, self.coding)  # raises ConfigError, nothing changed yet
        image_id = self._new_id()
        tx = _Tx(image_id, enc, t, item.x, item.y, self.default_goal.bytes_for(enc))
        tx.interest, self._backdrop = interest(item.image, self._backdrop)
        self.images[image_id] = tx

    def _new_id(self) -> int:
        """The next free image id (images and crops share one sequence), making room first."""
        if len(self.images) >= self.max_images:
            self._evict()
        image_id = self._next_id
        while image_id in self.images:
            image_id = (image_id + 1) % 1024
        self._next_id = (image_id + 1) % 1024
        self._announced.discard(image_id)  # a new image under this id: never announced
        return image_id

    def _evict(self) -> None:
        by_age = sorted(self.images.values(), key=lambda tx: tx.time)
        rules: tuple[Callable[[_Tx], bool], ...] = (
            lambda tx: not tx.needs(), lambda tx: tx.explicit is None, lambda tx: True
        )
        for pick in rules:
            victims = [tx for tx in by_age if pick(tx)]
            if victims:
                del self.images[victims[0].image_id]
                self._announce_sends.pop(victims[0].image_id, None)
                self.evicted += 1
                return

    # ------------------------------------------------------------------ order

    def order(self) -> list[_Tx]:
        """Images that still need bytes: operator goals (latest first), then capture order (on a
        low link: the most interesting first, :func:`interest`)."""
        explicit = [tx for tx in self.images.values() if tx.explicit is not None and tx.needs()]
        explicit.sort(key=lambda tx: -(tx.explicit or 0))
        return explicit + self._previews()

    def _previews(self) -> list[_Tx]:
        """Images without an operator goal that still need bytes to their default set-point:
        capture order, or on a low link (it cannot send them all) the most interesting first."""
        default = [tx for tx in self.images.values() if tx.explicit is None and tx.needs()]
        if self._low:
            default.sort(key=lambda tx: (-tx.interest, tx.time))
        else:
            default.sort(key=lambda tx: tx.time)
        return default

    def frames(self, since: float = -math.inf) -> list[Frame]:
        """The frames the vehicle holds captured after ``since`` (capture order): what an
        onboard detector looks at (``coex.detectors``), the image as coded (grey, reduced like
        the body sent), never what topside received."""
        txs = sorted((tx for tx in self.images.values() if tx.time > since), key=lambda tx: tx.time)
        return [Frame(tx.image_id, tx.time, tx.x, tx.y, tx.enc.image, tx.interest) for tx in txs]

    def detector_view(self) -> ImagerySender:
        """Detectors look at the frames through :meth:`frames` (a ``coex.ImageFrames``)."""
        return self

    def pending_bytes(self) -> int:
        return sum(tx.unacked() for tx in self.images.values())

    def ready_bytes(self, now: float) -> int:
        """Bytes up to the goals, and beyond them (spare work), not held topside and not in
        flight (sent within ``rto`` and not found lost)."""
        n = 0
        for tx in self.images.values():
            due = ~tx.acked & (tx.sent_at <= now - self.rto)
            if tx.goal > 0 and not tx.needs():
                n += int(np.count_nonzero(due))
            else:
                n += int(np.count_nonzero(due & tx.wanted()))
        return n

    def unacked_fragments(self) -> int:
        n = 0
        for image_id, start, end in self._inflight:
            tx = self.images.get(image_id)
            if tx is not None and not tx.acked[start:end].all():
                n += 1
        return n

    def progress(self, now: float) -> TransferProgress:
        order = self.order()
        current = order[0].image_id if order else None
        nxt = tuple(tx.image_id for tx in order if tx.image_id != current)[:MAX_NEXT]
        return TransferProgress(to_stamp(now), min(len(order), 1023), current,
                                min(self.unacked_fragments(), 255), nxt)

    # ------------------------------------------------------------------ fill

    def fill(self, max_bytes: int, now: float) -> list[Message]:
        out: list[Message] = []
        left = int(max_bytes)
        self._last_now = now
        if self._standing:
            self._answers.extend(self._serve_standing(now))
        while self._answers and encoded_size(self._answers[0]) <= left:
            left -= encoded_size(self._answers[0])
            out.append(self._answers.pop(0))
        if left <= 0:
            return out
        # 1. progress report, when due and changed
        if self._progress_at is None:
            self._progress_at = now  # the first report goes out one interval after the first fill
        if self.images and (self._progress_dirty or now - self._progress_at >= self.progress_interval):
            prog = self.progress(now)
            key = (prog.pending, prog.current, prog.unacked_fragments, prog.next_images)
            size = encoded_size(prog)
            if (self._progress_dirty or key != self._last_progress) and size <= left:
                out.append(prog)
                left -= size
                self._progress_at = now
                self._progress_dirty = False
                self._last_progress = key
        # 2. announcements, capture order
        announces = 0
        for tx in sorted(self.images.values(), key=lambda t: (t.crop is None, t.time)):
            if announces >= self.max_announces:
                break
            due = tx.announced_at is None or (not tx.heard and now - tx.announced_at >= self.rto)
            # a requested image's announcement goes in later packets too, as many times as its
            # bytes (copies()): without it topside can decode none of them
            again = (not due and tx.explicit is not None and not tx.heard and tx.announced_at is not None
                     and tx.announced_at < now and self._announce_sends.get(tx.image_id, 0) < self.copies())
            if not (due or again):
                continue
            msg = tx.announce()
            size = encoded_size(msg)
            if size > left:
                break
            out.append(msg)
            left -= size
            tx.announced_at = now
            self._claim_slot(tx.image_id, now)
            self._announce_sends[tx.image_id] = self._announce_sends.get(tx.image_id, 0) + 1 if again else 1
            announces += 1
        # 3. data: goals first, then the default set-point in capture order (on a low link the
        # previews are spare work: only the answers to requests go here)
        for tx in self.order() if not self._low else [tx for tx in self.order() if tx.explicit is not None]:
            if tx.announced_at is None:
                continue
            while left >= fragment_size(0, 1):
                frag = self._fragment(tx, left, now, trailing=bool(out))
                if frag is None:
                    break
                out.append(frag)
                left -= encoded_size(frag)
                self._current = tx.image_id
            if left < fragment_size(0, 1):
                break
        return out

    def frame_loss(self) -> float | None:
        """The share of this sender's fragments whose frames were lost, over the last 64 whose
        fate the channel told (:meth:`acked`, :meth:`lost`); None before 8 are known."""
        seen = self._fates
        return 1.0 - sum(seen) / len(seen) if len(seen) >= 8 else None

    def copies(self) -> int:
        """How many times a requested image's bytes go out before topside could have answered
        (each in a later packet): enough that all copies are lost with probability at most 5 %
        at the measured loss, at most 8 (:data:`LOW_COPIES` on a low link); 1 when no loss is
        measured."""
        p = self.frame_loss()
        if p is None or p <= 0.05:
            return 1
        k = 8 if p >= 0.99 else max(1, min(8, math.ceil(math.log(0.05) / math.log(p))))
        # a low link has no bytes to spare: at most LOW_COPIES before an ack, then selective repeat
        return min(k, LOW_COPIES) if self._low else k

    def throughput(self, bytes_per_second: float, low: bool, now: float) -> None:
        """On a low link only the answers to requests are sent ahead of spare work, a requested
        image's bytes at most :data:`LOW_COPIES` times before an ack; the previews are spare
        work, the most interesting frames first, and layers beyond the goals are not sent
        unasked (docs/channel.md)."""
        self._low = bool(low)

    def _fate(self, frag: ImageFragment | ImageShortFragment, ok: int) -> None:
        """Count a fragment sent once (a repeated one says little about a frame's loss)."""
        tx = self.images.get(self._whose(frag))
        if tx is not None and frag.offset < len(tx.sends) and tx.sends[frag.offset] <= 1:
            self._fates.append(ok)

    def image_of(self, frag: ImageFragment | ImageShortFragment) -> int | None:
        """The id of the image a fragment this sender made is of: an ``ImageFragment`` names it, a
        short fragment's is remembered for the last SHORT_RECORDS sent (None: not remembered)."""
        if isinstance(frag, ImageFragment):
            return frag.image_id
        key = (frag.slot, frag.offset, len(frag.data))
        return next((rec[3] for rec in reversed(self._shorts) if rec[:3] == key), None)

    def _whose(self, frag: ImageFragment | ImageShortFragment) -> int:
        image_id = self.image_of(frag)
        return -1 if image_id is None else image_id

    def _claim_slot(self, image_id: int, now: float) -> None:
        """An announcement of ``image_id`` was sent: it holds its slot from now on (topside takes
        the last announcement it receives in a slot as the slot's image). It took the slot cleanly
        when it is the image's first announcement and no other image's in that slot was sent in
        the last SHORT_HORIZON seconds (that one cannot arrive after it); only then may its bytes
        go in short fragments."""
        slot = image_id % SHORT_SLOTS
        owner = self._slot_owner.get(slot)
        if owner is None or owner[0] != image_id:
            last = self._slot_last.get(slot)
            clean = image_id not in self._announced and (last is None or now - last >= SHORT_HORIZON)
            self._slot_owner[slot] = (image_id, clean)
            if owner is not None:  # the short fragments of the image it held are not its now
                kept = [rec for rec in self._shorts if rec[3] != owner[0]]
                self._shorts.clear()
                self._shorts.extend(kept)
        self._slot_last[slot] = now
        self._announced.add(image_id)

    def _short_ok(self, tx: _Tx) -> bool:
        """Whether ``tx``'s bytes may go in short fragments: the option is on, topside heard its
        announcement and it holds its slot, taken cleanly (:meth:`_claim_slot`)."""
        owner = self._slot_owner.get(tx.image_id % SHORT_SLOTS)
        return self.short_fragments and tx.heard and owner == (tx.image_id, True)

    def acked(self, message: Message, now: float) -> None:
        """A frame that carried a fragment arrived: its bytes are held topside (the ImageAck
        that follows says the same; this is only sooner). An announcement that arrived is heard."""
        if isinstance(message, ImageAnnounce | ImageCrop):
            tx = self.images.get(message.image_id)
            if tx is not None:
                tx.heard = True
            self._announce_sends.pop(message.image_id, None)
            return
        if isinstance(message, ImageFragment | ImageShortFragment):
            self._fate(message, 1)
            held = self._span(message)
            if held is not None:
                tx, span = held
                tx.acked[span] = True

    def lost(self, message: Message, now: float) -> None:
        """No frame that carried a fragment arrived: its bytes not held are due again at once
        (instead of after ``rto``). A lost announcement goes again at once."""
        if isinstance(message, ImageAnnounce | ImageCrop):
            tx = self.images.get(message.image_id)
            if tx is not None and not tx.heard:
                tx.announced_at = None
            return
        if isinstance(message, ImageFragment | ImageShortFragment):
            self._fate(message, 0)
            held = self._span(message)
            if held is not None:
                tx, span = held
                tx.sent_at[span] = np.where(tx.acked[span], tx.sent_at[span], -np.inf)
                if tx.explicit is not None:
                    # every copy of these bytes was lost: a requested image's missing bytes get
                    # their repeats again, or each ack round would carry a single copy
                    sends = tx.sends
                    sends[span] = np.where(tx.acked[span], sends[span], 0)

    def _span(self, frag: ImageFragment | ImageShortFragment) -> tuple[_Tx, slice] | None:
        """The image a fragment belongs to and the bytes it carried (None: an image no longer
        held, a short fragment not remembered, or bytes outside it)."""
        tx = self.images.get(self._whose(frag))
        end = frag.offset + len(frag.data)
        return None if tx is None or end > tx.total else (tx, slice(frag.offset, end))

    def spare(self, max_bytes: int, now: float) -> list[Message]:
        """Further quality layers, beyond each image's goal up to its whole codestream: the
        requested images first (latest request first), then the others newest first. On a low
        link only the previews (images to their default set-point), the most interesting first:
        layers beyond the goals go only when asked for. Bytes sent and not acknowledged go again
        after ``rto``, as in :meth:`fill`."""
        out: list[Message] = []
        left = int(max_bytes)
        self._last_now = now
        # a low link: the previews only, the most interesting first (layers beyond the goals
        # would take the spare bytes the finest map needs)
        for tx in self._previews() if self._low else self._spare_order():
            while left >= fragment_size(0, 1):
                frag = self._fragment(tx, left, now, trailing=bool(out), goal=tx.goal if self._low else tx.total)
                if frag is None:
                    break
                out.append(frag)
                left -= encoded_size(frag)
            if left < fragment_size(0, 1):
                break
        return out

    def _spare_order(self) -> list[_Tx]:
        txs = [tx for tx in self.images.values()
               if tx.announced_at is not None and tx.goal > 0 and not tx.needs()]
        txs.sort(key=lambda tx: (tx.explicit is None, -(tx.explicit or 0), -tx.time))
        return txs

    def spare_bytes(self) -> int:
        """Bytes beyond the goals (on a low link: of the previews) not held topside and not in
        flight (sent within ``rto``)."""
        now = self._last_now
        if self._low:
            return sum(int(np.count_nonzero(tx.wanted() & ~tx.acked & (tx.sent_at <= now - self.rto)))
                       for tx in self._previews())
        return sum(int(np.count_nonzero(~tx.acked & (tx.sent_at <= now - self.rto))) for tx in self._spare_order())

    def _marked(self, tx: _Tx, pos: int, goal: int | None) -> bool:
        """Whether a fragment starting at ``pos`` carries packet marks (see ``marks``)."""
        if self.marks == "always":
            return True
        loss = self.frame_loss()
        if loss is not None and loss >= 0.2:
            return True
        # topside parses packet headers in order: bytes after a gap that is never filled (bytes
        # neither held nor to be sent) can only be placed with marks
        before = tx.acked[:pos] | tx.wanted(goal)[:pos]
        return not bool(before.all())

    def _fragment(self, tx: _Tx, left: int, now: float, trailing: bool = False,
                  goal: int | None = None) -> ImageFragment | ImageShortFragment | None:
        want = tx.wanted(goal) & ~tx.acked
        # the bytes wanted lie in [a, b): what is ready is looked for there only (an image mostly
        # held topside, or one whose goal is a short prefix, has few of them)
        a = int(np.argmax(want)) if want.size else 0
        if not want.size or not want[a]:
            return None
        b = tx.total if want[-1] else tx.total - int(np.argmax(want[::-1]))  # mostly a tail
        want = want[a:b]
        sent_at = tx.sent_at[a:b]
        ready = want & (sent_at <= now - self.rto)
        sends = tx.sends
        copies = self.copies() if tx.explicit is not None else 1
        if copies > 1:
            # a requested image under loss: its bytes go again in the next packet, up to
            # ``copies`` times, without waiting for an ack that takes a TDMA cycle to come
            ready |= want & (sends[a:b] < copies) & (sent_at < now)
        if not ready.any():
            return None
        first = int(np.argmax(ready))
        pos = a + first
        stop_rel = np.flatnonzero(~ready[first:])
        run = int(stop_rel[0]) if len(stop_rel) else b - pos  # want (so ready) is False from b on
        starts = tx.enc.packet_starts
        marked = self._marked(tx, pos, goal)
        left = min(left, MAX_MESSAGE)
        top = min(run, MAX_FRAGMENT_DATA, left - fragment_size(0, 0, pos))

        def marks_for(k: int) -> npt.NDArray[np.int64]:
            if not marked:
                return starts[:0]
            lo = int(np.searchsorted(starts, pos, side="left"))
            hi = int(np.searchsorted(starts, pos + k, side="right"))  # a start at pos + k ends a packet
            out: npt.NDArray[np.int64] = starts[lo:hi] - pos
            return out

        def fits(k: int) -> bool:
            m = len(marks_for(k))
            return m <= MAX_MARKS and fragment_size(m, k, pos) <= left

        # the most data that fits with its marks (the size only grows with the data)
        lo_k, hi_k = 0, max(top, 0)
        while lo_k < hi_k:
            mid = (lo_k + hi_k + 1) // 2
            if fits(mid):
                lo_k = mid
            else:
                hi_k = mid - 1
        n = lo_k
        marks = marks_for(n)
        frag: ImageFragment | ImageShortFragment
        # a short fragment where it carries as much: bytes sent the first time, of an image
        # topside heard announced that holds its slot, no marks (spec/payloads.md 3.3)
        short = 0
        if not marked and pos < SHORT_OFFSETS and self._short_ok(tx):
            fresh = np.flatnonzero(sends[pos:pos + min(run, SHORT_MAX_DATA)] != 0)
            short = min(int(fresh[0]) if len(fresh) else min(run, SHORT_MAX_DATA), left - SHORT_HEAD)
        if short > 0 and short >= n:
            squeezed = short < min(run, SHORT_MAX_DATA)
            if trailing and squeezed and short < self.min_fragment:
                return None
            n = short
            frag = ImageShortFragment(tx.image_id % SHORT_SLOTS, pos, tx.enc.body[pos:pos + n])
            self._shorts.append((frag.slot, pos, n, tx.image_id))
        else:
            squeezed = n < min(run, MAX_FRAGMENT_DATA)  # the budget, not the data, limits this fragment
            if n <= 0 or (trailing and squeezed and n < self.min_fragment):
                return None  # a tiny fragment at the end of a packet costs more than it carries
            packet = int(np.searchsorted(starts, pos, side="right")) - 1 if len(marks) else None
            frag = ImageFragment(tx.image_id, pos, packet, tuple(int(m) for m in marks), tx.enc.body[pos:pos + n])
        tx.sent_at[pos:pos + n] = now
        sends[pos:pos + n] = np.minimum(sends[pos:pos + n], 254) + 1
        self._inflight.append((tx.image_id, pos, pos + n))
        return frag

    # ------------------------------------------------------------------ requests

    def handle(self, message: Message, now: float) -> list[Message]:
        if isinstance(message, ImageAck):
            self._ack(message)
            return []
        if isinstance(message, ImageGoal):
            return self._goal(message)
        if isinstance(message, ImageByTimeRequest):
            return self._by_time(message, now)
        if isinstance(message, ImageRegionRequest):
            return self._region(message, now)
        raise RequestRejected(f"imagery sender does not handle {type(message).__name__}")

    def _tx(self, image_id: int) -> _Tx:
        tx = self.images.get(image_id)
        if tx is None:
            raise RequestRejected(f"no image {image_id} on the vehicle")
        return tx

    def _ack(self, ack: ImageAck) -> None:
        tx = self._tx(ack.image_id)
        spans = [(0, ack.contiguous)] + [(r.start, r.end) for r in ack.ranges]
        for s, e in spans:
            if not 0 <= s <= e <= tx.total:
                raise RequestRejected(f"ack range {s}..{e} outside image {ack.image_id} ({tx.total} B)")
        for s, e in spans:
            tx.acked[s:e] = True
        tx.heard = True
        self._announce_sends.pop(ack.image_id, None)

    def _goal(self, msg: ImageGoal) -> list[Message]:
        tx = self._tx(msg.image_id)
        layers = tx.enc.stream.layers
        if msg.kind == GoalKind.FRACTION and not 1 <= msg.value <= 100:
            raise RequestRejected(f"fraction {msg.value} % outside 1..100")
        if msg.kind == GoalKind.LAYER and not 1 <= msg.value <= layers:
            raise RequestRejected(f"layer {msg.value} outside 1..{layers}")
        if msg.kind == GoalKind.SKIP:
            tx.goal = 0
            tx.explicit = None
        else:
            goal = {GoalKind.FRACTION: Goal("fraction", msg.value), GoalKind.LAYER: Goal("layer", msg.value),
                    GoalKind.FULL: Goal("full")}[GoalKind(msg.kind)]
            new = goal.bytes_for(tx.enc)
            if tx.explicit is None or new != tx.goal:
                self._request_counter += 1
                tx.explicit = self._request_counter
            tx.goal = new
        self._progress_dirty = True
        return [CommandAck(msg.command_id, AckStatus.ACCEPTED)]

    def _region(self, msg: ImageRegionRequest, now: float) -> list[Message]:
        """Serve a region request first, the cheaper of two ways (option ``crops``): the packets
        of the precincts covering the region, up to its goal, beyond what topside holds; or a
        crop, the region coded on its own as the difference to what topside shows of it
        (:meth:`_crop_for`), sent as an image of its own (``ImageCrop``)."""
        tx = self._tx(msg.image_id)
        crop_of = tx.crop
        if crop_of is not None:
            raise RequestRejected(f"image {msg.image_id} is a crop of image {crop_of.parent}: ask for a region of "
                                  "that image")
        enc = tx.enc
        sp = enc.stream
        if not sp.precincts:
            raise RequestRejected(f"image {msg.image_id} was coded without precincts: ask for more of the "
                                  "whole image instead")
        if msg.x1 > enc.width or msg.y1 > enc.height or msg.x0 >= msg.x1 or msg.y0 >= msg.y1:
            raise RequestRejected(f"region x {msg.x0}..{msg.x1}, y {msg.y0}..{msg.y1} is empty or outside the "
                                  f"{enc.width} x {enc.height} image {msg.image_id}")
        box = (msg.x0, msg.y0, msg.x1, msg.y1)
        inside = region_packets(sp, enc.width, enc.height, box)
        layer = packet_layers(enc)
        starts = enc.packet_starts
        sizes = np.append(starts[1:], tx.total) - starts
        held = held_packets(tx)
        kind = RegionGoal(msg.kind)
        target: float | None = None  # the PSNR the region is to reach (None: a byte budget)
        everything = np.ones(len(held), bool)
        if kind == RegionGoal.LAYER:
            if not 1 <= msg.value <= sp.layers:
                raise RequestRejected(f"layer {msg.value} outside 1..{sp.layers}")
            chosen = inside & (layer < msg.value)
            target = box_psnr(tx, layer < msg.value, box)
            prefix = fewest(tx, everything, held, box, target)
        elif kind == RegionGoal.BYTES:
            if msg.value < 1:
                raise RequestRejected("a byte budget of 0")
            chosen = _within(inside, held, sizes, msg.value)
            prefix = _within(everything, held, sizes, msg.value)
        else:
            if not 100 <= msg.value <= 600:
                raise RequestRejected(f"quality {msg.value / 10:.1f} dB outside 10..60 dB")
            target = msg.value / 10
            chosen = fewest(tx, inside, held, box, target)
            prefix = fewest(tx, everything, held, box, target)
        # the region's packets (small gaps bridged), or the image's next packets in codestream
        # order until the region is there: on a soft image these cost less than the region's
        # own packets with their fragment headers and packet marks
        ways = [way(tx, _bridge(chosen, held, sizes), held, box)]
        if self.crops != "never":
            ways.append(way(tx, prefix, held, box))
        mask, reached, cost = min(ways, key=lambda w: (
            (w[1] < target, w[2]) if target is not None else (-w[1], w[2])))  # reach the goal, fewest bytes
        crop = None
        if self.crops != "never" and (mask.any() or (target is not None and reached < target)):
            crop = self._crop_for(tx, box, msg, target, cost, reached)
        self._request_counter += 1
        if crop is not None:
            crop_enc, crop_of = crop
            ctx = _Tx(self._new_id(), crop_enc, now, tx.x, tx.y, len(crop_enc.body))
            ctx.crop = crop_of
            ctx.explicit = self._request_counter
            self.images[ctx.image_id] = ctx
        else:
            tx.region = mask if tx.region is None else (tx.region | mask)
            sends = tx.sends
            sends[mask] = np.where(tx.acked[mask], sends[mask], 0)
            tx.explicit = self._request_counter
            tx.announced_at = None if not tx.heard else tx.announced_at
        self._progress_dirty = True
        return [CommandAck(msg.command_id, AckStatus.ACCEPTED)]

    def _crop_for(self, tx: _Tx, box: tuple[int, int, int, int], msg: ImageRegionRequest, target: float | None,
                  packets_cost: int, reached: float) -> tuple[Encoded, CropOf] | None:
        """A crop of ``box`` for this request when it is the cheaper way (or when ``crops`` is
        ``always``), else None. The crop codes the box's difference to what topside shows of it
        from the longest prefix of the image's packets it acknowledged (``base``; nothing: mid-
        grey), so that nothing topside holds is sent again (spec/payloads.md 3.7), to
        ``target`` dB inside the box, or within the byte budget. The packets' way (``mask``,
        reaching ``reached`` dB) and the crop's are compared by their bytes on the wire (body,
        fragment headers and packet marks; the crop's announcement), or for a budget by the
        quality each brings."""
        enc = tx.enc
        x0, y0, x1, y1 = box
        if min(x1 - x0, y1 - y0) < 8:
            return None  # too small to be coded on its own
        original = enc.image[y0:y1, x0:x1]
        held = held_packets(tx)
        prefix = int(np.argmin(held)) if not held.all() else len(held)
        if target is not None:
            cp = CodingParams(progression="LRCP", resolutions=self.coding.resolutions,
                              irreversible=self.coding.irreversible, grey=enc.grey, precincts=0,
                              layer_psnr=(float(target),))
        else:
            cp = CodingParams(progression="LRCP", resolutions=self.coding.resolutions,
                              irreversible=self.coding.irreversible, grey=enc.grey, precincts=0,
                              layer_bytes=(int(msg.value),), layer_psnr=())
        # the difference to what topside holds (the acknowledged prefix of the image's packets),
        # and the region from nothing: what topside holds does not always make the region
        # cheaper (the base's own coding errors are detail to code again), so both are measured
        best: tuple[tuple[float, float], Encoded, int, float, float] | None = None
        for base in sorted({prefix, 0}, reverse=True):
            base_box = decoded(tx, np.arange(len(held)) < base)[y0:y1, x0:x1]
            try:
                cenc = encode_residual(original, base_box, cp)
                shown = add_residual(base_box, decode_packets(cenc.params, cenc.width, cenc.height, _packets(cenc)))
            except CoexError:
                continue
            q = psnr(shown, original)
            if target is not None and q < target:
                continue  # this way cannot reach the goal (beyond the quality cap)
            # a goal in dB: the fewest bytes; a budget: the most quality
            key = (float(len(cenc.body)), -q) if target is not None else (-q, float(len(cenc.body)))
            if best is None or key < best[0]:
                best = (key, cenc, base, q, psnr(base_box, original))
        if best is None:
            return None
        _key, cenc, base, q, base_psnr = best
        if self.crops == "auto":
            if target is None:
                if q <= reached:
                    return None  # within the budget, the packets bring more
            elif reached >= target:
                crop_bytes = len(cenc.body) + encoded_size(self._crop_message(tx, cenc, box, msg, base, 0)) + \
                    fragment_size(0, 0)
                if crop_bytes >= packets_cost:
                    return None
        layer = packet_layers(enc)
        cover = 0
        for k in range(1, enc.stream.layers + 1):
            if box_psnr(tx, layer < k, box) <= q:
                cover = k
        return cenc, CropOf(tx.image_id, box, msg.command_id, base, cover, round(q, 3), round(base_psnr, 3))

    @staticmethod
    def _crop_message(tx: _Tx, cenc: Encoded, box: tuple[int, int, int, int], msg: ImageRegionRequest,
                      base: int, cover: int) -> ImageCrop:
        return ImageCrop(0, tx.image_id, msg.command_id, *box, len(cenc.body), cenc.params, base, cover)

    def _pictures(self) -> list[_Tx]:
        """The images captured (not the crops made of them)."""
        return [tx for tx in self.images.values() if tx.crop is None]

    def find(self, stamp: int, direction: TimeDirection, now: float) -> _Tx | None:
        """The image nearest the time of ``stamp``, or the last one before / first one after it."""
        txs = self._pictures()
        if not txs:
            return None
        t = unwrap(stamp, now)
        times = np.array([tx.time for tx in txs])
        if direction == TimeDirection.NEAREST:
            return txs[int(np.argmin(np.abs(times - t)))]
        if direction == TimeDirection.BEFORE:
            idx = np.flatnonzero(times < t - 0.5)
            return txs[int(idx[np.argmax(times[idx])])] if len(idx) else None
        idx = np.flatnonzero(times > t + 0.5)
        return txs[int(idx[np.argmin(times[idx])])] if len(idx) else None

    def _by_time(self, msg: ImageByTimeRequest, now: float) -> list[Message]:
        direction = TimeDirection(msg.direction)
        t = unwrap(msg.stamp, now)
        newest = max((tx.time for tx in self._pictures()), default=-math.inf)
        if direction != TimeDirection.BEFORE and t > newest + 0.5:
            # a time not captured yet: the request stands until an image of that time exists
            if len(self._standing) >= self.max_standing:
                raise RequestRejected(f"{self.max_standing} image requests already wait for images")
            self._standing[msg.command_id] = (msg, now + self.standing_expiry)
            return [CommandAck(msg.command_id, AckStatus.PENDING)]
        tx = self.find(msg.stamp, direction, now)
        if tx is None:
            raise RequestRejected(f"no image {direction.name.lower()} stamp {msg.stamp}")
        self._serve(tx)
        return [CommandAck(msg.command_id, AckStatus.ACCEPTED)]

    def standing(self) -> list[tuple[ImageByTimeRequest, float]]:
        """Image requests waiting for an image of their time: ``(request, expiry time)``."""
        return list(self._standing.values())

    def _serve_standing(self, now: float) -> list[Message]:
        """Answer the standing requests an image now exists for (the first image captured at or
        after their time), and reject the expired ones; returns their final CommandAcks."""
        out: list[Message] = []
        for cid, (msg, expires) in list(self._standing.items()):
            t = unwrap(msg.stamp, now)
            later = [tx for tx in self._pictures()
                     if tx.time >= t - 0.5 and (msg.direction != TimeDirection.AFTER or tx.time > t + 0.5)]
            if later:
                self._serve(min(later, key=lambda tx: tx.time))
                out.append(CommandAck(cid, AckStatus.ACCEPTED))
                del self._standing[cid]
            elif now > expires:
                out.append(CommandAck(cid, AckStatus.REJECTED))
                del self._standing[cid]
        return out

    def _serve(self, tx: _Tx) -> None:
        """Give ``tx`` the request goal and serve it first."""
        want = max(self.request_goal.bytes_for(tx.enc), tx.goal)
        # bytes sent before the request (as the default set-point) count for nothing now: the
        # requested ones get their full repeats
        sends = tx.sends
        sends[:want] = np.where(tx.acked[:want], sends[:want], 0)
        if tx.explicit is None or want != tx.goal:
            self._request_counter += 1
            tx.explicit = self._request_counter
        tx.goal = want
        tx.announced_at = None if not tx.heard else tx.announced_at  # re-announce if never heard
        self._progress_dirty = True



"""The topside side of the imagery modality: reassembly, whole-packet decoding, acks, requests.

Memory bounds: at most ``max_images`` images (default 256; the oldest is forgotten first), each
holding its body buffer and a byte map (2 B per body byte) and the latest decoded image;
fragments that arrive before their image's announcement wait in a buffer of at most
``max_early`` fragments (default 256, oldest dropped first: the sender resends them).
"""

from __future__ import annotations

import logging
import warnings
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import (
    CoexError,
    ConfigError,
    DecodeError,
    ModalityReceiver,
    Options,
    Product,
    RequestTracker,
    merged_config,
    persistent,
    to_stamp,
    unwrap,
    wire,
)
from coex.messages import (
    AckStatus,
    ByteRange,
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
from coex.options import anything, integer, number

from .codec import (
    StreamParams,
    add_residual,
    decode_packets,
    packet_order,
    parse_params,
    region_packets,
)
from .goals import region_fields
from .packets import PacketParser
from .product import CropProduct, ImageProduct, ProgressProduct

log = logging.getLogger("coex.imagery")

__all__ = ["RECEIVER_OPTIONS", "ImageryReceiver"]

MAX_ACK_RANGES = 15
#: Ids ahead of a new announcement whose older images are forgotten (previous id cycle).
REUSE_WINDOW = 16
#: ``ImageShortFragment.slot`` names an image by its id modulo this (spec/payloads.md 3.3)
SHORT_SLOTS = 1 << wire.SHORT_FRAGMENT_SLOT_BITS


def _upgrade_rx(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (CoEx 0.1) had one packet per resolution (no precincts), no region requests
    and no crops."""
    if saved < 2:
        order = fields.get("order")
        if order is not None and order.shape[1] == 3:
            fields["order"] = packet_order(fields["sp"], fields["ann"].width, fields["ann"].height)
        for k, v in (("regions", []), ("crop", None), ("base", None), ("shown", None), ("ack_from", 0)):
            fields.setdefault(k, v)
    return fields


@persistent("imagery.Rx", version=2, upgrade=_upgrade_rx)
class _Rx:
    def __init__(self, ann: ImageAnnounce, sp: StreamParams, now: float) -> None:
        self.ann = ann
        self.sp = sp
        self.time = unwrap(ann.stamp, now)
        n = ann.total_bytes
        self.buf = bytearray(n)
        self.have: npt.NDArray[np.bool_] = np.zeros(n, bool)
        self.order = packet_order(sp, ann.width, ann.height)
        self.starts: npt.NDArray[np.int64] = np.full(self.n_packets, -1, np.int64)
        if self.n_packets:
            self.starts[0] = 0
        self.version = 0
        self.used = 0
        self.signature: tuple[int, ...] = ()
        self.image: npt.NDArray[np.uint8] | None = None
        self.bytes_used = 0
        #: region requests of this image: dicts with command_id, box, kind, value, state
        self.regions: list[dict[str, Any]] = []
        #: for a crop: its announcement (None for an image)
        self.crop: ImageCrop | None = None
        #: for a crop: the parent's pixels in the box it refines (None until known)
        self.base: npt.NDArray[np.uint8] | None = None
        #: for an image: what topside shows, its crops pasted over it (None: its own decode)
        self.shown: npt.NDArray[np.uint8] | None = None
        #: where the next ack's ranges start (acks take turns over a long list of held ranges)
        self.ack_from = 0

    @property
    def n_packets(self) -> int:
        return len(self.order)

    def contiguous(self) -> int:
        miss = np.flatnonzero(~self.have)
        return int(miss[0]) if len(miss) else len(self.have)

    def ranges(self) -> list[tuple[int, int]]:
        """Held ranges beyond the contiguous prefix."""
        edges = np.diff(self.have.astype(np.int8), prepend=0, append=0)
        s = np.flatnonzero(edges == 1)
        e = np.flatnonzero(edges == -1)
        return [(int(a), int(b)) for a, b in zip(s, e, strict=True) if a > 0]

    def packets(self) -> list[bytes | None]:
        """Every complete packet (``None`` for missing ones), up to the last complete one."""
        n = self.n_packets
        starts = self.starts
        ends = np.append(starts[1:], len(self.have))
        known = (starts >= 0) & (ends >= 0)
        known[:-1] &= starts[1:] >= 0
        cum = np.concatenate([[0], np.cumsum(self.have, dtype=np.int64)])
        s = np.where(known, starts, 0)
        e = np.where(known, ends, 0)
        complete = known & (cum[e] - cum[s] == e - s) & (e > s)
        out: list[bytes | None] = [None] * n
        for i in np.flatnonzero(complete):
            out[int(i)] = bytes(self.buf[int(s[i]):int(e[i])])
        while out and out[-1] is None:
            out.pop()
        return out

    def usable(self, packets: list[bytes | None]) -> tuple[int, ...]:
        """Indices of packets a decode really uses (after the same-resolution repair rule)."""
        poisoned: set[tuple[int, int, int]] = set()
        used = []
        for i, p in enumerate(packets):
            key = (int(self.order[i, 1]), int(self.order[i, 2]), int(self.order[i, 3]))
            if p is None or key in poisoned:
                poisoned.add(key)
            else:
                used.append(i)
        return tuple(used)


#: the imagery receiver's options: the one declaration of their types, ranges and units
RECEIVER_OPTIONS = Options(
    max_images=integer(256, "images held", lo=1),
    max_early=integer(256, "fragments held before their image's announcement", lo=0),
    ack_limit=integer(4, "acks per poll", lo=1),
    retry=number(60.0, "between request retries", unit="s", above=0),
    max_tries=integer(10, "sends of a request before it is given up", lo=1),
    max_ack_bytes=integer(81, "largest ack (at least 6: an ack without ranges; lower it to fit a small "
                              "uplink MTU, e.g. MTU - 3)", unit="B", lo=6),
    out_dir=anything(None, "a folder: write image_<id>.tiff and .png after every useful fragment"),
)
#: their defaults (a name kept for 0.x code)
RECEIVER_DEFAULTS: dict[str, Any] = RECEIVER_OPTIONS.defaults()


def _upgrade_receiver(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 (CoEx 0.1): no standing requests, no count of refused announcements. Version 2
    (before issue 54): no slots of short fragments (none known: short fragments are ignored
    until the next announcement of their slot, and the vehicle sends their bytes again in
    ImageFragments)."""
    if saved < 2:
        fields.setdefault("_waiting", {})
        fields.setdefault("rejected_announces", 0)
    if saved < 3:
        fields.setdefault("_slots", {})
    return fields


@persistent("imagery.Receiver", version=3, upgrade=_upgrade_receiver, transient=("listeners", "_parsers"))
class ImageryReceiver(ModalityReceiver):
    """Topside side. Configuration keys (all optional): ``max_images`` (256), ``max_early``
    (256), ``ack_limit`` (acks per poll, 4), ``retry`` (seconds between request retries, 60),
    ``max_tries`` (10), ``max_ack_bytes`` (81: at most 15 ranges; lower it to fit a small uplink
    MTU, e.g. MTU - 3), ``out_dir`` (write ``image_<id>.tiff`` and ``.png`` after every useful
    fragment, see :class:`~coex_plugins.imagery.output.ImageWriter`)."""

    options = RECEIVER_OPTIONS

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, self.options, "imagery receiver")
        self.max_images = int(cfg["max_images"])
        self.max_early = int(cfg["max_early"])
        self.ack_limit = int(cfg["ack_limit"])
        self.retry = float(cfg["retry"])
        self.max_tries = int(cfg["max_tries"])
        self.max_ack_bytes = int(cfg["max_ack_bytes"])
        #: ranges per ack: type id + ceil((34 + 40 k) / 8) bytes must fit max_ack_bytes
        self.ack_ranges = min(MAX_ACK_RANGES, (8 * (self.max_ack_bytes - 1) - 34) // 40)
        self.images: OrderedDict[int, _Rx] = OrderedDict()
        self._early: deque[ImageFragment] = deque(maxlen=self.max_early)
        self._ack_due: OrderedDict[int, None] = OrderedDict()
        self._requests: RequestTracker[Message] = RequestTracker(self.retry, self.max_tries)
        self.progress: TransferProgress | None = None
        self._progress_version = 0
        self.rejected_fragments = 0
        self.rejected_announces = 0
        #: standing by-time requests: command id -> (request, when it was answered PENDING)
        self._waiting: dict[int, tuple[Message, float]] = {}
        #: slot (image id modulo 32) -> the id of the last announcement received in it (every
        #: ImageAnnounce and ImageCrop, refused ones too): the image its short fragments are of
        self._slots: dict[int, int] = {}
        self.out_dir = cfg.get("out_dir")
        self._after_restore()

    def _after_restore(self) -> None:
        """The listeners (not saved state): the image writer of ``out_dir``."""
        self.listeners: list[Callable[[Product], None]] = []
        #: image id -> packet-header parser (rebuilt from the held bytes after a restart)
        self._parsers: dict[int, PacketParser | None] = {}
        out_dir = self.out_dir
        if out_dir:
            from .output import ImageWriter

            self.listeners.append(ImageWriter(str(out_dir)))

    # ------------------------------------------------------------------ receive

    def receive(self, message: Message, now: float) -> list[Product]:
        changed: list[Product] = []
        if isinstance(message, ImageAnnounce):
            changed += self._announce(message, now)
        elif isinstance(message, ImageCrop):
            changed += self._crop(message, now)
        elif isinstance(message, ImageFragment):
            changed += self._fragment(message, now)
        elif isinstance(message, ImageShortFragment):
            changed += self._short_fragment(message, now)
        elif isinstance(message, TransferProgress):
            self.progress = message
            self._progress_version += 1
            changed.append(self._progress_product())
        elif isinstance(message, CommandAck):
            changed += self._region_answer(message)
            done = self._requests.answered(message.command_id, now, message.status.name)
            if message.status == AckStatus.PENDING:
                # it stands on the vehicle (an image of that time is not captured yet): waiting,
                # not answered; the final CommandAck follows
                if done is not None:
                    self._waiting[message.command_id] = (done.message, now)
            else:
                self._waiting.pop(message.command_id, None)
        for p in changed:
            for listener in self.listeners:
                listener(p)
        return changed

    def _announce(self, ann: ImageAnnounce, now: float, crop: ImageCrop | None = None) -> list[Product]:
        # every announcement takes its slot, a refused one too (spec/payloads.md 3.3): the
        # vehicle counts on the last one it sent in a slot being the last topside received
        self._slots[ann.image_id % SHORT_SLOTS] = ann.image_id
        self._ack_due[ann.image_id] = None
        old = self.images.get(ann.image_id)
        if old is not None and (old.ann == ann if crop is None else old.crop == crop):
            return []
        try:
            sp = parse_params(ann.params)
            if sp.colour == ann.grey:
                raise DecodeError(f"the grey flag ({ann.grey}) disagrees with params (colour={sp.colour})")
        except CoexError as exc:
            # spec/payloads.md 3.1: such an image is not decoded; said, not silent
            self.rejected_announces += 1
            log.warning("image %d announced with unusable coding parameters %#x: %s", ann.image_id,
                        ann.params, exc)
            return []
        if old is not None:  # the id wrapped round: a new image replaces the old one
            self._forget(ann.image_id)
        # ids are given in sequence (mod 1024): an older image held under one of the next few ids
        # is from the previous cycle; forget it before its id is reused, so that fragments of the
        # new image arriving before their (lost) announcement never land in the old buffer
        t = unwrap(ann.stamp, now)
        for stale in [i for i, h in self.images.items()
                      if 0 < (i - ann.image_id) % 1024 <= REUSE_WINDOW and h.time < t]:
            self._forget(stale)
        rx = _Rx(ann, sp, now)
        rx.crop = crop
        self.images[ann.image_id] = rx
        while len(self.images) > self.max_images:
            self._forget(next(iter(self.images)))
        early = [f for f in self._early if f.image_id == ann.image_id]
        for f in early:
            self._early.remove(f)
        out: list[Product] = [self._product(rx)]
        if crop is not None:
            out += self._parent_products(rx)
        for f in early:
            out += self._fragment(f, now)
        return out

    def _crop(self, msg: ImageCrop, now: float) -> list[Product]:
        """A crop's announcement (spec/payloads.md 3.7): an image of its own (its fragments and
        acks like any image's), ``x1 - x0`` by ``y1 - y0`` pixels, shown over its parent."""
        parent = self.images.get(msg.parent)
        sp_colour = bool(msg.params & 1)
        ann = ImageAnnounce(msg.image_id, to_stamp(now), None if parent is None else parent.ann.x,
                            None if parent is None else parent.ann.y, msg.x1 - msg.x0, msg.y1 - msg.y0,
                            not sp_colour, msg.total_bytes, msg.params)
        return self._announce(ann, now, msg)

    def _forget(self, image_id: int) -> None:
        """Forget an image (and the crops made of it: they refine an image that is gone)."""
        rx = self.images.pop(image_id, None)
        self._parsers.pop(image_id, None)
        if rx is None or rx.crop is not None:
            return
        for cid in [i for i, c in self.images.items()
                    if (o := c.crop) is not None and o.parent == image_id and c.time >= rx.time]:
            self.images.pop(cid, None)
            self._parsers.pop(cid, None)

    def _fragment(self, frag: ImageFragment, now: float) -> list[Product]:
        rx = self.images.get(frag.image_id)
        if rx is None:
            self._early.append(frag)
            return []
        n = len(frag.data)
        marks = np.asarray(frag.packets, np.int64)
        first = (frag.packet or 0) + (0 if len(marks) and marks[0] == 0 else 1)
        idx = first + np.arange(len(marks))
        ok = (frag.offset + n <= len(rx.have) and n > 0 and (len(marks) == 0 or (
            bool(np.all(np.diff(marks) > 0)) and int(marks[-1]) <= n and int(idx[-1]) < rx.n_packets))
            and (len(marks) == 0 or (frag.packet or 0) < rx.n_packets))
        if ok and len(marks):
            known = rx.starts[idx]
            ok = bool(np.all((known < 0) | (known == frag.offset + marks)))
        if not ok:
            self.rejected_fragments += 1
            return []
        self._ack_due[frag.image_id] = None
        self._ack_due.move_to_end(frag.image_id)
        if rx.have[frag.offset:frag.offset + n].all():
            return []
        rx.buf[frag.offset:frag.offset + n] = frag.data
        rx.have[frag.offset:frag.offset + n] = True
        if len(marks):
            rx.starts[idx] = frag.offset + marks
        self._parse(frag.image_id, rx)
        return self._update(rx)

    def _short_fragment(self, frag: ImageShortFragment, now: float) -> list[Product]:
        """A short fragment (spec/payloads.md 3.3) is of the image of the last announcement
        received in its slot; ignored (and counted) when there is none or it is not held."""
        image_id = self._slots.get(frag.slot)
        if image_id is None or image_id not in self.images:
            self.rejected_fragments += 1
            return []
        return self._fragment(ImageFragment(image_id, frag.offset, None, (), frag.data), now)

    def _parse(self, image_id: int, rx: _Rx) -> None:
        """Packet starts from the packet headers of the held bytes (spec/payloads.md 3.3): data
        sent without marks is placed by them. A body whose headers do not parse, or disagree with
        the marks, is left to the marks (and said)."""
        parser = self._parsers.get(image_id)
        if image_id not in self._parsers or (parser is not None and parser.total != len(rx.have)):
            try:
                parser = PacketParser(rx.ann.params, rx.ann.width, rx.ann.height, len(rx.have))
            except CoexError:
                parser = None
            self._parsers[image_id] = parser
        if parser is None or parser.done:
            return
        try:
            starts = parser.parse(rx.buf, rx.have)
        except CoexError as exc:
            log.warning("image %d: packet headers do not parse (%s); using the fragments' marks only", image_id, exc)
            self._parsers[image_id] = None
            return
        known = starts >= 0
        clash = known & (rx.starts >= 0) & (rx.starts != starts)
        if clash.any():
            log.warning("image %d: packet headers disagree with the fragments' marks at %d packets; "
                        "using the marks only", image_id, int(clash.sum()))
            self._parsers[image_id] = None
            return
        rx.starts[known] = starts[known]

    def _update(self, rx: _Rx) -> list[Product]:
        packets = rx.packets()
        sig = rx.usable(packets)
        if sig == rx.signature:
            return []
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                image = decode_packets(rx.ann.params, rx.ann.width, rx.ann.height, packets)
        except CoexError:
            return []
        rx.signature = sig
        rx.image = image
        rx.used = len(sig)
        rx.bytes_used = sum(len(packets[i] or b"") for i in sig)
        rx.version += 1
        if rx.crop is not None:
            return [self._product(rx), *self._parent_products(rx)]
        self._compose(rx)
        return [self._product(rx)]

    # ------------------------------------------------------------------ crops

    def _crops_of(self, rx: _Rx) -> list[_Rx]:
        """The crops of an image topside holds, oldest first (a newer one is pasted over it)."""
        iid = rx.ann.image_id
        return sorted((c for c in self.images.values()
                       if (o := c.crop) is not None and o.parent == iid and c.time >= rx.time),
                      key=lambda c: c.time)

    def _parent_products(self, crop: _Rx) -> list[Product]:
        """The parent of a crop, shown again with the crop (when it is held)."""
        c = crop.crop
        parent = self.images.get(c.parent) if c is not None else None
        if parent is None or parent.crop is not None:
            return []
        self._compose(parent)
        parent.version += 1
        return [self._product(parent)]

    def _crop_base(self, parent: _Rx, crop: _Rx) -> npt.NDArray[np.uint8] | None:
        """The parent's pixels in the crop's box that the crop refines (spec/payloads.md 3.7): the
        parent decoded from its first ``base`` packets (mid-grey for none); None while topside
        lacks one of them."""
        if crop.base is not None:
            return crop.base
        c = crop.crop
        assert c is not None
        packets = parent.packets()[: c.base]
        if len(packets) < c.base or any(p is None for p in packets):
            return None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                full = decode_packets(parent.ann.params, parent.ann.width, parent.ann.height, packets)
        except CoexError:
            return None
        crop.base = full[c.y0:c.y1, c.x0:c.x1].copy()
        return crop.base

    def _crop_pixels(self, crop: _Rx) -> npt.NDArray[np.uint8] | None:
        """What a crop shows of its box: its base and its decoded difference (None: not yet)."""
        c = crop.crop
        parent = self.images.get(c.parent) if c is not None else None
        if c is None or crop.image is None:
            return None
        if c.base == 0:
            base: npt.NDArray[np.uint8] | None = np.full(crop.image.shape, 128, np.uint8)
        elif parent is None or parent.crop is not None:
            return None
        else:
            base = self._crop_base(parent, crop)
        if base is None or base.shape != crop.image.shape:
            return None
        return add_residual(base, crop.image)

    def _crop_shown(self, parent: _Rx, crop: _Rx) -> bool:
        """Whether a crop is shown over its parent (spec/payloads.md 3.7): it has pixels, fits the
        parent, and the parent holds fewer quality layers inside the box than the crop covers, or
        as many and the crop is complete (``cover`` is what the *whole* crop is at least as good
        as: a crop still arriving over a parent that already holds ``cover`` layers there would
        show less than topside holds)."""
        c = crop.crop
        if c is None or self._crop_pixels(crop) is None:
            return False
        if c.x1 > parent.ann.width or c.y1 > parent.ann.height or bool(c.params & 1) == parent.ann.grey:
            return False
        layers = self._region_layers(parent, (c.x0, c.y0, c.x1, c.y1))
        return layers < c.cover or (layers == c.cover and bool(crop.have.all()))

    def _compose(self, rx: _Rx) -> None:
        """What topside shows of an image: its decode with its crops pasted at their boxes."""
        crops = [c for c in self._crops_of(rx) if self._crop_shown(rx, c)]
        if not crops:
            rx.shown = None
            return
        shape = (rx.ann.height, rx.ann.width) if rx.ann.grey else (rx.ann.height, rx.ann.width, 3)
        out = np.array(rx.image, copy=True) if rx.image is not None else np.full(shape, 128, np.uint8)
        for c in crops:
            pix = self._crop_pixels(c)
            assert c.crop is not None and pix is not None
            out[c.crop.y0:c.crop.y1, c.crop.x0:c.crop.x1] = pix
        rx.shown = out

    # ------------------------------------------------------------------ products

    def _region_answer(self, ack: CommandAck) -> list[Product]:
        """The vehicle's answer to a region request: its state changes (accepted / rejected)."""
        for rx in self.images.values():
            for reg in rx.regions:
                if reg["command_id"] == ack.command_id and reg["state"] == "requested":
                    reg["state"] = ("accepted" if ack.status == AckStatus.ACCEPTED else
                                    "waiting" if ack.status == AckStatus.PENDING else "rejected")
                    rx.version += 1
                    return [self._product(rx)]
        return []

    def _region_layers(self, rx: _Rx, box: tuple[int, int, int, int]) -> int:
        """Quality layers complete (and used by the decode) over every packet of the region."""
        inside = region_packets(rx.sp, rx.ann.width, rx.ann.height, box)
        used = np.zeros(rx.n_packets, bool)
        used[list(rx.signature)] = True
        layers = rx.order[:, 0]
        k = 0
        while k < rx.sp.layers and bool(used[inside & (layers == k)].all()):
            k += 1
        return k

    def _region_bytes(self, rx: _Rx, box: tuple[int, int, int, int]) -> int:
        """Bytes of the complete packets of the region's precincts topside holds."""
        inside = region_packets(rx.sp, rx.ann.width, rx.ann.height, box)
        return sum(len(p) for i, p in enumerate(rx.packets()) if p is not None and inside[i])

    def _layers_complete(self, rx: _Rx) -> int:
        layers = 0
        if rx.used:
            used = set(rx.signature)
            while layers < rx.sp.layers and all(
                int(i) in used for i in np.flatnonzero(rx.order[:, 0] == layers)
            ):
                layers += 1
        return layers

    def _region_meta(self, rx: _Rx, reg: dict[str, Any]) -> dict[str, Any]:
        """A region request as the product lists it: its state, how it is served (``served``:
        ``crop`` once a crop answering it is announced, else ``packets`` once accepted), the
        quality layers complete inside it (a complete crop shown counts as the parent layers it
        covers), its bytes (the crop's body held, or the region's packet bytes that arrived since
        the request) and, for a crop, ``crop`` (its image id, size, bytes held, whether it is
        complete and shown)."""
        box = tuple(int(v) for v in reg["box"])
        layers = self._region_layers(rx, box)  # type: ignore[arg-type]
        crop = next((c for c in reversed(self._crops_of(rx)) if c.crop is not None
                     and c.crop.command_id == reg["command_id"]
                     and (c.crop.x0, c.crop.y0, c.crop.x1, c.crop.y1) == box), None)
        out = {**reg, "box": list(box)}
        if crop is not None and crop.crop is not None:
            shown = self._crop_shown(rx, crop)
            complete = bool(crop.have.all())
            if shown and complete:
                layers = max(layers, crop.crop.cover)
            held = int(np.count_nonzero(crop.have))
            out.update(served="crop", bytes=held, crop={
                "image_id": crop.ann.image_id, "width": crop.ann.width, "height": crop.ann.height,
                "total_bytes": crop.ann.total_bytes, "held_bytes": held, "complete": complete,
                "shown": shown, "base": crop.crop.base, "cover": crop.crop.cover, "version": crop.version})
        else:
            before = int(reg.get("bytes_at_request", 0) or 0)
            out.update(served="packets" if reg.get("state") == "accepted" else None,
                       bytes=max(0, self._region_bytes(rx, box) - before))  # type: ignore[arg-type]
        out["layers_complete"] = layers
        return out

    def _product(self, rx: _Rx) -> ImageProduct | CropProduct:
        a = rx.ann
        held: dict[str, Any] = {
            "image_id": a.image_id, "stamp": a.stamp, "time": rx.time, "x": a.x, "y": a.y,
            "width": a.width, "height": a.height, "grey": a.grey, "total_bytes": a.total_bytes,
            "held_bytes": int(np.count_nonzero(rx.have)), "contiguous": rx.contiguous(),
            "packets_used": rx.used, "packets": rx.n_packets, "bytes_used": rx.bytes_used,
            "layers_complete": self._layers_complete(rx), "layers": rx.sp.layers,
            "complete": bool(rx.have.all()), "precincts": rx.sp.precincts,
        }
        crop = rx.crop
        if crop is not None:
            parent = self.images.get(crop.parent)
            return CropProduct("image-crop", str(a.image_id), rx.version, self._crop_pixels(rx), **held,
                               parent=crop.parent, box=[crop.x0, crop.y0, crop.x1, crop.y1],
                               command_id=crop.command_id, base=crop.base, cover=crop.cover,
                               shown=parent is not None and parent.crop is None
                               and self._crop_shown(parent, rx))
        shown = rx.shown
        return ImageProduct("image", str(a.image_id), rx.version, rx.image if shown is None else shown, **held,
                            regions=[self._region_meta(rx, reg) for reg in rx.regions],
                            crops=[c.ann.image_id for c in self._crops_of(rx)])

    def _progress_product(self) -> ProgressProduct:
        p = self.progress
        assert p is not None
        return ProgressProduct("image-progress", "vehicle", self._progress_version, None, stamp=p.stamp,
                               pending=p.pending, current=p.current, unacked_fragments=p.unacked_fragments,
                               next_images=list(p.next_images))

    def products(self) -> list[Product]:
        out: list[Product] = [self._product(rx) for rx in self.images.values()]
        if self.progress is not None:
            out.append(self._progress_product())
        return out

    def image(self, image_id: int) -> npt.NDArray[np.uint8] | None:
        """What topside shows of an image (its crops pasted over it), or of a crop (its box)."""
        rx = self.images.get(image_id)
        if rx is None:
            return None
        if rx.crop is not None:
            return self._crop_pixels(rx)
        shown = rx.shown
        return rx.image if shown is None else shown

    # ------------------------------------------------------------------ requests

    def _new_command(self, make: Callable[[int], Message], now: float) -> Message:
        cid = self.next_command_id()
        msg = make(cid)
        self._requests.add(cid, msg)
        return msg

    def request_goal(self, image_id: int, kind: GoalKind | str, value: int = 0, now: float = 0.0) -> ImageGoal:
        """Ask the vehicle to bring ``image_id`` to a goal (``FRACTION`` %, ``LAYER`` count, ``FULL``,
        ``SKIP``); it is sent by :meth:`poll` and retried until the vehicle acknowledges it."""
        k = GoalKind[kind.upper()] if isinstance(kind, str) else GoalKind(kind)
        if not 0 <= value <= 255 or not 0 <= image_id <= 1023:
            raise ConfigError("goal value must be in 0..255 and image id in 0..1023")
        msg = self._new_command(lambda c: ImageGoal(c, image_id, k, value), now)
        assert isinstance(msg, ImageGoal)
        return msg

    def request_region(self, image_id: int, box: tuple[int, int, int, int],
                       kind: RegionGoal | str = RegionGoal.QUALITY, value: float = 30.0,
                       now: float = 0.0) -> ImageRegionRequest:
        """Ask the vehicle to bring the rectangle ``box`` = (x0, y0, x1, y1) (pixels, x1 and y1
        exclusive) of an announced image to a goal: ``"quality"`` (``value`` in dB PSNR inside
        the region), ``"layer"`` (quality layers) or ``"bytes"`` (a budget of body bytes). The
        vehicle sends the packets of the precincts covering it, beyond what topside holds; the
        request is retried until acknowledged and listed in the image product's ``regions``.
        Raises :class:`ConfigError` for an unknown image, an empty or outside box, an image
        coded without precincts or an absurd goal."""
        rx = self.images.get(int(image_id))
        if rx is None:
            raise ConfigError(f"no image {image_id} announced")
        crop_of = rx.crop
        if crop_of is not None:
            raise ConfigError(f"image {image_id} is a crop of image {crop_of.parent}: ask for a region of that image")
        try:
            (x0, y0, x1, y1), k, code = region_fields(box, kind, value, rx.ann.width, rx.ann.height,
                                                      rx.sp.layers, rx.sp.precincts)
        except ConfigError as exc:
            raise ConfigError(f"image {image_id}: {exc}") from None
        msg = self._new_command(lambda c: ImageRegionRequest(c, int(image_id), x0, y0, x1, y1, k, code), now)
        assert isinstance(msg, ImageRegionRequest)
        rx.regions = [*rx.regions, {
            "command_id": msg.command_id, "box": (x0, y0, x1, y1), "kind": k.name.lower(),
            "value": float(value) if k == RegionGoal.QUALITY else code, "state": "requested", "time": now,
            "bytes_at_request": self._region_bytes(rx, (x0, y0, x1, y1))}]
        rx.version += 1
        return msg

    def request_by_time(self, t: float, direction: TimeDirection | str = TimeDirection.NEAREST,
                        now: float = 0.0) -> ImageByTimeRequest:
        """Ask for the image nearest absolute time ``t`` (or the one before / after it)."""
        d = TimeDirection[direction.upper()] if isinstance(direction, str) else TimeDirection(direction)
        msg = self._new_command(lambda c: ImageByTimeRequest(c, to_stamp(t), d), now)
        assert isinstance(msg, ImageByTimeRequest)
        return msg

    def poll(self, now: float) -> list[Message]:
        out: list[Message] = self._requests.due(now)
        for _ in range(min(self.ack_limit, len(self._ack_due))):
            image_id, _ = self._ack_due.popitem(last=False)
            rx = self.images.get(image_id)
            if rx is None:
                continue
            ranges = rx.ranges()
            if len(ranges) > self.ack_ranges:
                # more held ranges than one ack carries (a region's packets are scattered): each
                # ack goes on from where the last one stopped, so every range is reported in turn
                start = rx.ack_from
                later = [r for r in ranges if r[0] >= start]
                ranges = (later + [r for r in ranges if r[0] < start])[: self.ack_ranges]
                rx.ack_from = ranges[-1][1]
                ranges.sort()
            out.append(ImageAck(image_id, rx.contiguous(), tuple(ByteRange(s, e) for s, e in ranges)))
        return out

    def supersedes(self, old: Message, new: Message) -> bool:
        """A newer ack of an image replaces an older one still in the channel: it says what
        topside holds now, which includes everything the older one said (bytes held are never
        dropped). Without this, a lossy downlink fills the uplink with stale acks of one image."""
        return (isinstance(old, ImageAck) and isinstance(new, ImageAck)
                and old.image_id == new.image_id)

    def pending_requests(self) -> list[Message]:
        return self._requests.pending()

    def waiting_requests(self) -> list[tuple[Message, float]]:
        """Requests the vehicle keeps standing (answered ``PENDING``: an image of their time
        is not captured yet), with when it said so."""
        return list(self._waiting.values())

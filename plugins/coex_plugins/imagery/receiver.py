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

from coex_core.config import merged_config
from coex_core.errors import CoexError, ConfigError, DecodeError
from coex_core.messages import (
    AckStatus,
    ByteRange,
    CommandAck,
    GoalKind,
    ImageAck,
    ImageAnnounce,
    ImageByTimeRequest,
    ImageFragment,
    ImageGoal,
    Message,
    TimeDirection,
    TransferProgress,
)
from coex_core.modality import ModalityReceiver, Product
from coex_core.requests import RequestTracker
from coex_core.state import persistent
from coex_core.timefmt import to_stamp, unwrap

from .codec import StreamParams, decode_packets, packet_order, parse_params

log = logging.getLogger("coex.imagery")

__all__ = ["ImageryReceiver"]

MAX_ACK_RANGES = 15
#: Ids ahead of a new announcement whose older images are forgotten (previous id cycle).
REUSE_WINDOW = 16


@persistent("imagery.Rx")
class _Rx:
    def __init__(self, ann: ImageAnnounce, sp: StreamParams, now: float) -> None:
        self.ann = ann
        self.sp = sp
        self.time = unwrap(ann.stamp, now)
        n = ann.total_bytes
        self.buf = bytearray(n)
        self.have: npt.NDArray[np.bool_] = np.zeros(n, bool)
        self.starts: npt.NDArray[np.int64] = np.full(sp.n_packets, -1, np.int64)
        if sp.n_packets:
            self.starts[0] = 0
        self.order = packet_order(sp)
        self.version = 0
        self.used = 0
        self.signature: tuple[int, ...] = ()
        self.image: npt.NDArray[np.uint8] | None = None
        self.bytes_used = 0

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
        n = self.sp.n_packets
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
        poisoned: set[tuple[int, int]] = set()
        used = []
        for i, p in enumerate(packets):
            key = (int(self.order[i, 1]), int(self.order[i, 2]))
            if p is None or key in poisoned:
                poisoned.add(key)
            else:
                used.append(i)
        return tuple(used)


#: the imagery receiver's options and their defaults
RECEIVER_DEFAULTS: dict[str, Any] = {"max_images": 256, "max_early": 256, "ack_limit": 4,
                                     "retry": 60.0, "max_tries": 10, "max_ack_bytes": 81,
                                     "out_dir": None}


@persistent("imagery.Receiver", transient=("listeners",))
class ImageryReceiver(ModalityReceiver):
    """Topside side. Configuration keys (all optional): ``max_images`` (256), ``max_early``
    (256), ``ack_limit`` (acks per poll, 4), ``retry`` (seconds between request retries, 60),
    ``max_tries`` (10), ``max_ack_bytes`` (81: at most 15 ranges; lower it to fit a small uplink
    MTU, e.g. MTU - 3), ``out_dir`` (write ``image_<id>.tiff`` and ``.png`` after every useful
    fragment, see :class:`~coex_plugins.imagery.output.ImageWriter`)."""

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = merged_config(config, RECEIVER_DEFAULTS, "imagery receiver")
        try:
            self.max_images = int(cfg.get("max_images", 256))
            self.max_early = int(cfg.get("max_early", 256))
            self.ack_limit = int(cfg.get("ack_limit", 4))
            self.retry = float(cfg.get("retry", 60.0))
            self.max_tries = int(cfg.get("max_tries", 10))
            self.max_ack_bytes = int(cfg.get("max_ack_bytes", 81))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"invalid imagery receiver option: {exc}") from exc
        if self.max_images < 1 or self.max_early < 0 or self.ack_limit < 1 or self.retry <= 0:
            raise ConfigError("invalid imagery receiver limits")
        if self.max_ack_bytes < 6:
            raise ConfigError("max_ack_bytes must be at least 6 (an ack without ranges)")
        #: ranges per ack: type id + ceil((34 + 40 k) / 8) bytes must fit max_ack_bytes
        self.ack_ranges = min(MAX_ACK_RANGES, (8 * (self.max_ack_bytes - 1) - 34) // 40)
        self.images: OrderedDict[int, _Rx] = OrderedDict()
        self._early: deque[ImageFragment] = deque(maxlen=self.max_early)
        self._ack_due: OrderedDict[int, None] = OrderedDict()
        self._requests: RequestTracker[Message] = RequestTracker(self.retry, self.max_tries)
        self.progress: TransferProgress | None = None
        self._progress_version = 0
        self.rejected_fragments = 0
        self.out_dir = cfg.get("out_dir")
        self._after_restore()

    def _after_restore(self) -> None:
        """The listeners (not saved state): the image writer of ``out_dir``."""
        if getattr(self, "_waiting", None) is None:  # saved before requests could stand
            self._waiting: dict[int, tuple[Message, float]] = {}
        self.listeners: list[Callable[[Product], None]] = []
        out_dir = self.out_dir
        if out_dir:
            from .output import ImageWriter

            self.listeners.append(ImageWriter(str(out_dir)))

    # ------------------------------------------------------------------ receive

    def receive(self, message: Message, now: float) -> list[Product]:
        changed: list[Product] = []
        if isinstance(message, ImageAnnounce):
            changed += self._announce(message, now)
        elif isinstance(message, ImageFragment):
            changed += self._fragment(message, now)
        elif isinstance(message, TransferProgress):
            self.progress = message
            self._progress_version += 1
            changed.append(self._progress_product())
        elif isinstance(message, CommandAck):
            done = self._requests.answered(message.command_id)
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

    def _announce(self, ann: ImageAnnounce, now: float) -> list[Product]:
        self._ack_due[ann.image_id] = None
        old = self.images.get(ann.image_id)
        if old is not None and old.ann == ann:
            return []
        try:
            sp = parse_params(ann.params)
            if sp.colour == ann.grey:
                raise DecodeError(f"the grey flag ({ann.grey}) disagrees with params (colour={sp.colour})")
        except CoexError as exc:
            # spec/payloads.md 3.1: such an image is not decoded; said, not silent
            self.rejected_announces = getattr(self, "rejected_announces", 0) + 1
            log.warning("image %d announced with unusable coding parameters %#x: %s", ann.image_id,
                        ann.params, exc)
            return []
        if old is not None:  # the id wrapped round: a new image replaces the old one
            del self.images[ann.image_id]
        # ids are given in sequence (mod 1024): an older image held under one of the next few ids
        # is from the previous cycle; forget it before its id is reused, so that fragments of the
        # new image arriving before their (lost) announcement never land in the old buffer
        t = unwrap(ann.stamp, now)
        for stale in [i for i, h in self.images.items()
                      if 0 < (i - ann.image_id) % 1024 <= REUSE_WINDOW and h.time < t]:
            del self.images[stale]
        rx = _Rx(ann, sp, now)
        self.images[ann.image_id] = rx
        while len(self.images) > self.max_images:
            self.images.popitem(last=False)
        early = [f for f in self._early if f.image_id == ann.image_id]
        for f in early:
            self._early.remove(f)
        out = [self._product(rx)]
        for f in early:
            out += self._fragment(f, now)
        return out

    def _fragment(self, frag: ImageFragment, now: float) -> list[Product]:
        rx = self.images.get(frag.image_id)
        if rx is None:
            self._early.append(frag)
            return []
        n = len(frag.data)
        marks = np.asarray(frag.packets, np.int64)
        first = frag.packet + (0 if len(marks) and marks[0] == 0 else 1)
        idx = first + np.arange(len(marks))
        ok = (frag.offset + n <= len(rx.have) and n > 0 and (len(marks) == 0 or (
            bool(np.all(np.diff(marks) > 0)) and int(marks[-1]) <= n and int(idx[-1]) < rx.sp.n_packets))
            and frag.packet < rx.sp.n_packets)
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
        return self._update(rx)

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
        return [self._product(rx)]

    # ------------------------------------------------------------------ products

    def _product(self, rx: _Rx) -> Product:
        a = rx.ann
        layers = 0
        if rx.used:
            used = set(rx.signature)
            while layers < rx.sp.layers and all(
                int(i) in used for i in np.flatnonzero(rx.order[:, 0] == layers)
            ):
                layers += 1
        meta = {
            "image_id": a.image_id, "stamp": a.stamp, "time": rx.time, "x": a.x, "y": a.y,
            "width": a.width, "height": a.height, "grey": a.grey, "total_bytes": a.total_bytes,
            "held_bytes": int(np.count_nonzero(rx.have)), "contiguous": rx.contiguous(),
            "packets_used": rx.used, "packets": rx.sp.n_packets, "bytes_used": rx.bytes_used,
            "layers_complete": layers, "layers": rx.sp.layers,
            "complete": bool(rx.have.all()),
        }
        return Product("image", str(a.image_id), rx.version, rx.image, meta)

    def _progress_product(self) -> Product:
        p = self.progress
        assert p is not None
        meta = {"stamp": p.stamp, "pending": p.pending, "current": p.current,
                "unacked_fragments": p.unacked_fragments, "next_images": list(p.next_images)}
        return Product("image-progress", "vehicle", self._progress_version, None, meta)

    def products(self) -> list[Product]:
        out = [self._product(rx) for rx in self.images.values()]
        if self.progress is not None:
            out.append(self._progress_product())
        return out

    def image(self, image_id: int) -> npt.NDArray[np.uint8] | None:
        rx = self.images.get(image_id)
        return None if rx is None else rx.image

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
            ranges = rx.ranges()[: self.ack_ranges]
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

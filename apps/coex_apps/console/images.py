"""The console's images: what the imagery receiver holds of each image (its decoded picture,
bytes, layers, footprint on the seafloor), the regions asked of it and its crops, and which image
answered a by-time request.

A part of :class:`~coex_apps.console.state.ConsoleState` (its API is the state's); the images
it keeps and their pictures stay with the state (:meth:`ConsoleState._image`,
:meth:`ConsoleState.image_png`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, cast

from coex import messages as m
from coex import unwrap
from coex_plugins.imagery import CropProduct, ImageProduct

from .model import OPEN_COMMAND_STATES, ConsoleModel
from .records import _Crop, _Image
from .words import _num, ack_reason

__all__ = ["MAX_CROPS", "MAX_IMAGE_REGIONS", "ImagesView"]

#: The regions of an image the images section lists and the page draws (the newest).
MAX_IMAGE_REGIONS = 12
#: Crops (regions coded on their own) kept for the region lists (the newest).
MAX_CROPS = 64


class ImagesView(ConsoleModel):
    """The images part of :class:`~coex_apps.console.state.ConsoleState`."""

    def _image(self, image_id: int) -> _Image:
        img = self.images.get(image_id)
        if img is None:
            img = self.images[image_id] = _Image(image_id)
            while len(self.images) > max(self.max_images, 1):  # the oldest go (those without a time first)
                oldest = min((i for i in self.images.values() if i is not img),
                             key=lambda i: (i.t is not None, i.t or 0.0, i.image_id))
                del self.images[oldest.image_id]
        return img

    def _image_product(self, product: ImageProduct, now: float) -> None:
        """An image's product: its picture, and what the page lists of it (its scalar fields,
        kept as the image's ``decoded_meta``), the regions asked of it, its time."""
        img = self._image(int(product.image_id))
        data = product.data
        if data is not None and hasattr(data, "shape"):
            img.decoded = data
            img.decoded_version = int(product.version)
        img.decoded_meta = {k: v for k, v in product.meta.items()
                            if v is None or isinstance(v, int | float | str | bool)}
        img.regions = [dict(r) for r in product.regions if isinstance(r, Mapping)]
        if img.t is None:
            img.t = float(product.time)
        img.version += 1
        self._touch("images")

    def _crop_product(self, product: CropProduct) -> None:
        """A crop's product: what it shows of its box (drawn in the region list of its image)."""
        cid = int(product.image_id)
        crop = self.crops.pop(cid, None) or _Crop(cid)
        self.crops[cid] = crop  # the newest last
        data = product.data
        if data is not None and hasattr(data, "shape"):
            crop.decoded = data
            crop.decoded_version = int(product.version)
        crop.meta = {k: (list(v) if isinstance(v, list | tuple) else v) for k, v in product.meta.items()
                     if v is None or isinstance(v, int | float | str | bool | list | tuple)}
        while len(self.crops) > MAX_CROPS:
            del self.crops[next(iter(self.crops))]
        self._touch("images")

    def by_time_answer(self, msg: m.ImageByTimeRequest, now: float) -> _Image | None:
        """The image that answered an accepted by-time request: the one the vehicle's rule
        picks (nearest, newest before, oldest after the time) among the images topside knows."""
        t = unwrap(msg.stamp, now)
        known = [i for i in self.images.values() if i.t is not None]
        if msg.direction == m.TimeDirection.BEFORE:
            known = [i for i in known if cast(float, i.t) < t - 0.5]
            return max(known, key=lambda i: cast(float, i.t), default=None)
        if msg.direction == m.TimeDirection.AFTER:
            known = [i for i in known if cast(float, i.t) > t + 0.5]
            return min(known, key=lambda i: cast(float, i.t), default=None)
        return min(known, key=lambda i: abs(cast(float, i.t) - t), default=None)

    def _snap_images(self) -> dict[str, Any]:
        items = []
        for img in sorted(self.images.values(), key=lambda i: (i.t or 0, i.image_id)):
            info = img.decoded_meta
            total = info.get("total_bytes")
            got = int(info.get("held_bytes", 0) or 0)
            items.append({
                "image_id": img.image_id, "t": _num(img.t, 1),
                "stamp": info.get("stamp"), "x": info.get("x"), "y": info.get("y"),
                "width": info.get("width"), "height": info.get("height"),
                "total_bytes": total, "bytes_received": got,
                "fraction": _num(got / total, 3) if total else None,
                "goal": None if img.goal is None else {"kind": img.goal[0], "value": img.goal[1]},
                "thumb": (f"/image/{img.image_id}.png?v={img.decoded_version}"
                          if img.decoded is not None else None),
                "full": (f"/image/{img.image_id}.png?full=1&v={img.decoded_version}"
                         if img.decoded is not None else None),
                "layers": info.get("layers"), "layers_complete": info.get("layers_complete"),
                "packets": info.get("packets"), "packets_used": info.get("packets_used"),
                "bytes_used": info.get("bytes_used"), "complete": info.get("complete"),
                "footprint": self._footprint(img),
                "precincts": info.get("precincts"),
                "regions": self._image_regions(img),
                "meta": img.decoded_meta,
            })
        return {"items": items, "queries": self.image_queries[-10:],
                "progress": self.progress_info}

    def _image_regions(self, img: _Image) -> list[dict[str, Any]]:
        """The regions asked of an image (the newest :data:`MAX_IMAGE_REGIONS`): the ones this
        console sent, with their command's state (and the rejection's reason), and the ones the
        imagery receiver lists (asked through it: by this console on a node, or by a script),
        with the quality layers complete inside each. ``box`` is ``[x0, y0, x1, y1]`` (image
        pixels, x1 and y1 exclusive); ``state`` is ``requested``, ``waiting``, ``accepted`` or
        ``rejected``; ``value`` is in dB for a quality goal."""
        known = {(int(r.get("command_id", -1)), tuple(int(v) for v in r.get("box", ()))): r
                 for r in img.regions}
        layers = img.decoded_meta.get("layers")
        out: list[dict[str, Any]] = []
        for key in self.command_order:
            c = self.commands.get(key)
            msg = c.message if c is not None else None
            if c is None or not isinstance(msg, m.ImageRegionRequest) or msg.image_id != img.image_id:
                continue
            box: tuple[int, ...] = (msg.x0, msg.y0, msg.x1, msg.y1)
            rx_row = known.pop((msg.command_id, box), None)
            state = {"sent": "requested", "queued": "requested", "pending": "waiting",
                     "accepted": "accepted"}.get(c.status, "rejected")
            if c.status in OPEN_COMMAND_STATES and rx_row is not None \
                    and rx_row.get("state") in ("accepted", "rejected", "waiting"):
                state = str(rx_row["state"])  # the receiver heard the answer first
            out.append({"command_id": msg.command_id, "box": list(box),
                        "kind": m.RegionGoal(msg.kind).name.lower(),
                        "value": msg.value / 10 if msg.kind == m.RegionGoal.QUALITY else msg.value,
                        "state": state,
                        "reason": (c.reason or ack_reason(msg, "REJECTED"))
                        if state == "rejected" else "",
                        "time": _num(c.sent, 1), "by": c.by,
                        "layers_complete": None if rx_row is None else rx_row.get("layers_complete"),
                        "layers": layers, **self._served(rx_row)})
        for (cid, box), r in known.items():  # asked through the receiver by someone else
            state = str(r.get("state", "requested"))
            out.append({"command_id": cid, "box": list(box), "kind": str(r.get("kind", "quality")),
                        "value": r.get("value"), "state": state,
                        "reason": "refused by the vehicle" if state == "rejected" else "",
                        "time": _num(r.get("time"), 1), "by": "",
                        "layers_complete": r.get("layers_complete"), "layers": layers, **self._served(r)})
        out.sort(key=lambda r: r["time"] or 0.0)
        return out[-MAX_IMAGE_REGIONS:]

    def _served(self, rx_row: Mapping[str, Any] | None) -> dict[str, Any]:
        """How the vehicle serves a region, from the receiver's row: ``served`` (``crop`` or
        ``packets``; None while unknown), ``bytes`` that arrived for it, and ``crop``: the crop
        (its image id, size, body bytes held and in all, complete, shown over the image, and
        ``png``, the picture of what it shows) or None."""
        if rx_row is None:
            return {"served": None, "bytes": None, "crop": None}
        crop = rx_row.get("crop")
        out: dict[str, Any] = {"served": rx_row.get("served"), "bytes": rx_row.get("bytes"), "crop": None}
        if isinstance(crop, Mapping):
            cid = int(crop.get("image_id", -1))
            held = self.crops.get(cid)
            out["crop"] = {k: crop.get(k) for k in ("image_id", "width", "height", "total_bytes", "held_bytes",
                                                    "complete", "shown")}
            out["crop"]["png"] = (f"/crop/{cid}.png?v={held.decoded_version}"
                                  if held is not None and held.decoded is not None else None)
        return out

    def _footprint(self, img: _Image) -> list[float | None] | None:
        """The seafloor an image covers, ``[width, height]`` in metres: the camera's field of
        view (:attr:`camera_fov`, degrees across and along) at the altitude the vehicle reported
        nearest the image's time. None without a position or an altitude."""
        info = img.decoded_meta
        if info.get("x") is None or img.t is None:
            return None
        alt = None
        best = math.inf
        for t, a in self.altitudes:
            if abs(t - img.t) < best and a is not None:
                best, alt = abs(t - img.t), a
        if alt is None or best > 300:
            return None
        fx, fy = self.camera_fov
        return [_num(2 * alt * math.tan(math.radians(fx) / 2), 2),
                _num(2 * alt * math.tan(math.radians(fy) / 2), 2)]

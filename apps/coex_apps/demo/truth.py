"""What the simulation knows and the operator does not: which pixels of each camera frame show
which object, and how a received image is judged against that truth.

Two different questions are answered here, on purpose by different tests:

* :class:`Eye` is the scripted operator's eye. It looks at the image *as received topside* (the
  JPEG 2000 reconstruction after however many layers arrived) inside the region where the
  simulator says an object lies, and asks what a person would: is there a dark hull with sharp,
  straight edges standing out from the sand (a car), or a pale, soft-edged lump (a boulder), or
  something too blurry to tell? A first layer is usually too blurry: the operator then asks for
  more of that image.
* :func:`judge` is the referee of the report. It decides from the truth whether a received image
  really shows a target: enough of the target's top in frame, and the received detail there
  (shape, edges, markings) faithful to what the camera saw (correlation with the original frame). Only a confirmation that
  passes the referee counts towards a goal; any other confirmation is reported as false.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["Eye", "FrameTruth", "Sight", "judge", "shrink"]

#: frames are kept and judged at a quarter of their size (160 x 120 for the 640 x 480 camera)
SCALE = 4


def shrink(image: npt.ArrayLike, factor: int = SCALE) -> npt.NDArray[np.float32]:
    """Grey, box-filtered by ``factor`` (vectorised)."""
    a = np.asarray(image, np.float32)
    if a.ndim == 3:
        a = a[..., :3].mean(-1)
    h, w = a.shape[0] // factor * factor, a.shape[1] // factor * factor
    small: npt.NDArray[np.float32] = a[:h, :w].reshape(h // factor, factor, w // factor, factor).mean((1, 3))
    return small


def shrink_labels(labels: npt.NDArray[np.uint8], factor: int = SCALE) -> npt.NDArray[np.uint8]:
    """Labels at the reduced size: the most common label of each block (ties to the higher)."""
    h, w = labels.shape[0] // factor * factor, labels.shape[1] // factor * factor
    tiled = labels[:h, :w].reshape(h // factor, factor, w // factor, factor).transpose(0, 2, 1, 3)
    blocks = tiled.reshape(h // factor, w // factor, factor * factor)
    n = int(labels.max()) + 1
    counts = (blocks[..., None] == np.arange(n, dtype=np.uint8)).sum(2)
    return np.asarray(counts.argmax(-1), np.uint8)


@dataclass
class FrameTruth:
    """The truth of one captured frame: when and where, what each label is, and the frame as the
    camera saw it (reduced)."""

    time: float
    x: float
    y: float
    heading: float
    #: label -> ("target", k) or ("decoy", k), k indexing the scenario's targets or decoys
    objects: dict[int, tuple[str, int]]
    labels: npt.NDArray[np.uint8]
    original: npt.NDArray[np.float32]
    #: label -> fraction of that object's top area seen in this frame
    visible: dict[int, float]


def _ring(mask: npt.NDArray[np.bool_], width: int) -> npt.NDArray[np.bool_]:
    """Cells within ``width`` of ``mask`` but outside it (4-neighbour dilation, vectorised)."""
    grown = mask.copy()
    for _ in range(width):
        p = np.pad(grown, 1)
        grown = grown | p[:-2, 1:-1] | p[2:, 1:-1] | p[1:-1, :-2] | p[1:-1, 2:]
    return grown & ~mask


def _outline(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    p = np.pad(mask, 1, mode="edge")
    inner = mask & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return _ring(mask, 1) | (mask & ~inner)


@dataclass(frozen=True)
class Sight:
    """What the eye makes of one object region: ``"car"``, ``"rock"`` or ``"unclear"``."""

    label: int
    kind: str
    share: float  # fraction of the frame
    contrast: float  # (surroundings - object) / spread: positive = darker than the sand
    sharpness: float  # gradient on the outline / gradient on the sand
    ratio: float = 1.0  # object brightness / the sand's around it
    edge_width: float = 0.0  # pixels (quarter size) of the step from the object to the sand


@dataclass(frozen=True)
class Eye:
    """The scripted operator's eye (see the module docstring). An object region must cover
    ``min_share`` of the frame to be noticed. It is a car when it is at most ``car_ratio`` as
    bright as the sand around it (dark paint; and darker by ``min_contrast`` of the sand's
    spread) and its outline is ``min_sharpness`` times sharper than the sand's texture
    (``min_sharpness_settled`` once every layer asked for has arrived) and its edge is at most
    ``max_edge_width`` pixels wide (``max_edge_width_settled``). It is a rock (a boulder,
    not a car) when it is at least ``rock_ratio`` as bright as the sand and the image is clear
    enough to tell. Otherwise it is unclear."""

    min_share: float = 0.1
    #: a car's paint is far darker than sand (the region at most this fraction of the
    #: brightness of the sand around it); a boulder is the sand's colour, only a little darker
    #: where its flank turns away from the light or the light falls off towards the frame's edge
    car_ratio: float = 0.6
    rock_ratio: float = 0.7
    min_contrast: float = 0.4
    min_sharpness: float = 2.3
    #: the outline needed once no more layers are coming (the best image the operator will get):
    #: a dark, fairly sharp hull is then taken for a car
    min_sharpness_settled: float = 1.8
    #: how wide (pixels of the quarter-size image) the step from hull to sand may be: a sharp
    #: edge is about 2, the first layers' smudge 3 to 8 (independent of how flat the sand looks,
    #: which the first layers blur away too)
    max_edge_width: float = 2.5
    max_edge_width_settled: float = 3.0

    def look(self, received: npt.ArrayLike, truth: FrameTruth, *, settled: bool = False) -> list[Sight]:
        """What the eye makes of each object region of ``truth`` in the received image;
        ``settled``: every layer asked for has arrived."""
        need = self.min_sharpness_settled if settled else self.min_sharpness
        widest = self.max_edge_width_settled if settled else self.max_edge_width
        img = shrink(received)
        labels = truth.labels
        if img.shape != labels.shape:
            return []
        gy, gx = np.gradient(img)
        grad = np.hypot(gx, gy)
        sand = labels == 0
        sights = []
        for label in truth.objects:
            mask = labels == label
            share = float(mask.mean())
            if share < self.min_share:
                continue
            around = _ring(mask, 6) & sand
            if around.sum() < 30:
                around = sand if sand.sum() >= 30 else ~mask
            if around.sum() < 10:
                continue
            spread = float(img[around].std()) + 3.0
            sand_level = float(img[around].mean())
            contrast = (sand_level - float(img[mask].mean())) / spread
            ratio = float(img[mask].mean()) / max(sand_level, 1.0)
            edge = _outline(mask)
            on_edge = float(grad[edge].mean())
            sharp = on_edge / (float(grad[around].mean()) + 1e-6)
            width = abs(sand_level - float(img[mask].mean())) / max(on_edge, 1e-6)
            clear = sharp >= need and width <= widest
            if ratio <= self.car_ratio and contrast >= self.min_contrast and clear:
                kind = "car"
            elif ratio >= self.rock_ratio and (settled or clear or contrast <= -self.min_contrast):
                kind = "rock"
            else:
                kind = "unclear"
            sights.append(Sight(label, kind, round(share, 3), round(contrast, 2), round(sharp, 2), round(ratio, 2),
                                round(width, 1)))
        return sights


def _detail(a: npt.NDArray[np.float32], r: int = 4) -> npt.NDArray[np.float64]:
    """``a`` less its local mean over a (2r+1)-square: the detail that shows an object's shape,
    without the lighting (vignetting, fall-off) the first layers carry (vectorised box filter)."""
    p = np.pad(np.asarray(a, np.float64), r, mode="edge")
    c = np.pad(p.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    k = 2 * r + 1
    mean = (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) / (k * k)
    detail: npt.NDArray[np.float64] = np.asarray(a, np.float64) - mean
    return detail


def judge(received: npt.ArrayLike, truth: FrameTruth, *, min_visible: float = 0.15,
          min_correlation: float = 0.75) -> list[tuple[str, int]]:
    """The objects a received image really shows, by the truth: at least ``min_visible`` of the
    object's top in frame, and the received image's detail over the object and a margin around
    it (its shape, edges and markings, without the lighting) correlating with the frame the
    camera took by at least ``min_correlation``. The first layers of an image give about 0.2-0.4,
    a recognisable car 0.75 or more."""
    img = shrink(received)
    if img.shape != truth.labels.shape:
        return []
    got, orig = _detail(img), _detail(truth.original)
    shown = []
    for label, obj in truth.objects.items():
        if truth.visible.get(label, 0.0) < min_visible:
            continue
        mask = truth.labels == label
        region = mask | _ring(mask, 2)
        a, b = got[region], orig[region]
        if a.size < 20 or float(a.std()) < 1e-6 or float(b.std()) < 1e-6:
            continue
        if float(np.corrcoef(a, b)[0, 1]) >= min_correlation:
            shown.append(obj)
    return shown


def frame_truth(time: float, x: float, y: float, heading: float, frame: npt.ArrayLike,
                labels: npt.NDArray[np.uint8], n_targets: int, areas: dict[int, float],
                pixel_area: dict[int, float]) -> FrameTruth | None:
    """The :class:`FrameTruth` of a rendered frame, or ``None`` when no object is in it.
    ``areas`` gives each label's top area (m^2); ``pixel_area`` the area one full-size pixel
    covers on that object's top (m^2)."""
    present = np.bincount(labels.ravel(), minlength=1)
    objs = {int(k): (("target", int(k) - 1) if k <= n_targets else ("decoy", int(k) - n_targets - 1))
            for k in np.flatnonzero(present) if k > 0}
    if not objs:
        return None
    visible = {k: min(1.0, float(present[k]) * pixel_area.get(k, 0.0) / max(areas.get(k, 1.0), 1e-6)) for k in objs}
    return FrameTruth(time, x, y, heading, objs, shrink_labels(labels), shrink(frame), visible)


def describe(obj: tuple[str, int] | None, names: dict[tuple[str, int], str] | None = None) -> str:
    if obj is None:
        return "no object (sand only)"
    if names and obj in names:
        return names[obj]
    return f"{obj[0]} {obj[1] + 1}"


def as_dict(sight: Sight) -> dict[str, Any]:
    return {"label": sight.label, "kind": sight.kind, "share": sight.share, "contrast": sight.contrast,
            "sharpness": sight.sharpness, "ratio": sight.ratio, "edge_width": sight.edge_width}

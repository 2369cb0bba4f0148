"""The referee: the only reader of the simulation's truth (which pixels of each camera frame show
which object, and the frame as the camera took it). It judges the scripted operator's
confirmations; the operator and its eye (:mod:`coex_apps.demo.eye`) never import this module.

A confirmation counts for a target only when (:func:`judge`):

* the object the operator's eye pointed at (its box in the frame) is that target: at least
  :data:`MIN_OVERLAP` of the target's pixels in the frame lie in the box, or the target fills
  that share of the box;
* the target is a real target (a decoy is not), at least :data:`MIN_VISIBLE` of its top in the
  frame;
* the received image is faithful inside the target's outline (and :data:`RING` pixels around
  it): a PSNR of at least :data:`MIN_PSNR_DB` and a mean SSIM of at least :data:`MIN_SSIM`
  against the frame the camera took, both at half size.

The referee is frozen: these constants and their reasons are in docs/demo.md; a change to any of
them is a new experiment, re-run on fresh seeds for every condition, and recorded in
CHANGELOG.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import ndimage

__all__ = ["MIN_OVERLAP", "MIN_PSNR_DB", "MIN_SSIM", "MIN_VISIBLE", "RING", "SCALE", "FrameTruth", "fidelity",
           "frame_truth", "judge", "shrink"]

#: frames are kept and judged at half their size (320 x 240 for the 640 x 480 camera)
SCALE = 2
#: at least this share of the target's top in the frame
MIN_VISIBLE = 0.25
#: the object the eye pointed at is the target: this share of the target's pixels in the frame
#: inside the eye's box, or of the box covered by the target
MIN_OVERLAP = 0.5
#: the received image inside the target's outline (and RING pixels around it, half size) against
#: the frame the camera took: PSNR (dB) and mean SSIM (7 x 7 windows, the usual constants)
MIN_PSNR_DB = 21.0
MIN_SSIM = 0.6
RING = 2


def shrink(image: npt.ArrayLike, factor: int = SCALE) -> npt.NDArray[np.float32]:
    """Grey, box-filtered by ``factor`` (vectorised)."""
    a = np.asarray(image, np.float32)
    if a.ndim == 3:
        a = a[..., :3].mean(-1)
    h, w = a.shape[0] // factor * factor, a.shape[1] // factor * factor
    return np.asarray(a[:h, :w].reshape(h // factor, factor, w // factor, factor).mean((1, 3)), np.float32)


def shrink_labels(labels: npt.NDArray[np.uint8], factor: int = SCALE) -> npt.NDArray[np.uint8]:
    """Labels at the reduced size: the most common label of each block (ties to the higher)."""
    h, w = labels.shape[0] // factor * factor, labels.shape[1] // factor * factor
    tiles = labels[:h, :w].reshape(h // factor, factor, w // factor, factor).transpose(0, 2, 1, 3)
    blocks = tiles.reshape(h // factor, w // factor, factor * factor)
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


def _ssim(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The SSIM map of two grey images (Wang et al. 2004; 7 x 7 uniform windows, K1 0.01,
    K2 0.03, 8-bit range), vectorised with scipy.ndimage."""
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def f(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return np.asarray(ndimage.uniform_filter(x, 7), np.float64)
    ma, mb = f(a), f(b)
    va, vb, cab = f(a * a) - ma * ma, f(b * b) - mb * mb, f(a * b) - ma * mb
    return ((2 * ma * mb + c1) * (2 * cab + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2))


def fidelity(received: npt.ArrayLike, truth: FrameTruth, label: int) -> tuple[float, float] | None:
    """PSNR (dB) and mean SSIM of the received image against the frame the camera took, inside
    object ``label``'s outline and :data:`RING` pixels around it (half size); ``None`` when the
    image is not that frame's size or the object is not in it."""
    img = shrink(received)
    if img.shape != truth.labels.shape:
        return None
    mask = truth.labels == label
    if not mask.any():
        return None
    region = ndimage.binary_dilation(mask, iterations=RING)
    a, b = np.asarray(img, np.float64), np.asarray(truth.original, np.float64)
    err = float(((a - b)[region] ** 2).mean())
    psnr = 10.0 * float(np.log10(255.0**2 / max(err, 1e-9)))
    return psnr, float(_ssim(a, b)[region].mean())


def judge(received: npt.ArrayLike, truth: FrameTruth, box: tuple[int, int, int, int] | None = None,
          ) -> list[tuple[str, int]]:
    """The objects a received image really shows, by the truth (see the module docstring): each
    in frame by at least :data:`MIN_VISIBLE`, pointed at by the eye's ``box`` (full-size pixels
    x0, y0, x1, y1; ``None``: anywhere in the frame) and shown faithfully enough inside its
    outline. Targets and decoys alike: the caller tells them apart."""
    shown = []
    labels = truth.labels
    inside = None
    if box is not None:
        x0, y0, x1, y1 = (int(v) // SCALE for v in box)
        inside = np.zeros(labels.shape, bool)
        inside[max(y0, 0):max(y1, 0), max(x0, 0):max(x1, 0)] = True
    for label, obj in truth.objects.items():
        if truth.visible.get(label, 0.0) < MIN_VISIBLE:
            continue
        mask = labels == label
        if inside is not None:
            n_in = int((mask & inside).sum())
            if n_in < MIN_OVERLAP * max(int(mask.sum()), 1) and n_in < MIN_OVERLAP * max(int(inside.sum()), 1):
                continue
        fid = fidelity(received, truth, label)
        if fid is not None and fid[0] >= MIN_PSNR_DB and fid[1] >= MIN_SSIM:
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

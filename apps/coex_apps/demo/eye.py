"""The scripted operator's eye: what a person at the topside console makes of a received image.

It sees what reached topside and nothing else: the image as decoded (the JPEG 2000
reconstruction of however many layers arrived, crops pasted over it) and the metadata that
crossed the link (where and when the frame was taken, its size; the vehicle's altitude from its
statuses or the camera line the operator commanded) plus the camera's field of view, which
topside is configured with (:data:`~coex_apps.demo.specs.CAMERA_HFOV_DEG`). It never sees the
simulator's labels or its renderer: ``tests/test_demo_eye.py`` holds that this module and the
operator's import nothing of them.

It looks at every frame it is given, sand included, and finds objects itself, with classical
image analysis on the frame reduced to a quarter of its size (vectorised numpy and
scipy.ndimage):

1. **Background.** The lighting (vignette, the light's fall-off) is a smooth surface: a
   low-order polynomial in the image coordinates fitted robustly (iteratively, leaving out the
   pixels more than :attr:`EyeParams.background_clip` robust spreads from it). The image over its
   background is the *relative brightness*: about 1 on sand.
2. **Anomalies.** A pixel stands out when, smoothed, it is darker or brighter than the sand by
   :attr:`EyeParams.min_contrast` of the sand's robust spread, or when its local edge energy (the
   gradient, smoothed) is :attr:`EyeParams.min_edges` times the sand's median: a dark car, a pale
   hull, and a car as bright as the sand but with its rim and its clutter all stand out.
   Specks are opened away, gaps closed, holes filled, soft patches with no outline (what is
   left of the lighting) dropped; pieces closer than :attr:`EyeParams.group_gap_m` are one
   object (a debris patch). When a group is no target as a whole, its largest piece is looked
   at alone once the necks joining it to the rest are opened away: a car or a container beside a
   patch of the sand's clutter or a rock touching its corner keeps its own outline.
3. **Measures** of each object: its size in metres (second moments, the pixel's size on the
   seafloor from the altitude and the field of view), its outline's fit to a rectangle (how
   much of the rotated bounding box it fills, and what share of its outline lies on the box's
   sides), how much one end tapers (a bow), how much of its convex hull it fills (a patch of
   pieces leaves gaps and notches; a rock or a mound is rounded), how dark it is, how sharp its
   outline is and whether the frame cuts it.
4. **Verdict** (:data:`KINDS`): ``car``, ``container``, ``hull``, ``debris`` (man-made: a
   target), ``object`` (man-made, of no known kind: a target too), ``natural`` (a rounded or
   lobed outline: a rock, a mound of living things, a fish), ``unclear`` (too blurry to tell)
   or ``partial`` (cut by the frame's edge: the rest is in the frame before or after). A
   straight-edged rectangle the frame cuts (its outline but the frame's edge on its box's sides,
   clear of the margin, at least a car's width and length showing) is an ``object``: straight
   sides meeting square are man-made whatever the whole size. So is a cut object whose outline
   runs along two straight parallel lines (:attr:`EyeParams.min_cut_straight`, a boat hull's or
   a box's flanks; a rock's outline curves all along): a ``hull`` when its end away from the
   frame tapers. At the first look an object cut at the frame's side is ``unclear`` until the
   sharper look shows its sides; so is a whole object with a hull's length, aspect and taper
   whose outline is too rough for a hull (a blurred layer bends an outline, not a size or a
   taper), and at the sharper look while its measures are within
   :attr:`EyeParams.hull_doubt` of a hull's: never ``natural``, which ends the candidate. Nor is
   a whole object of a car's or a container's size that is nearly a rectangle (its measures
   within :attr:`EyeParams.margin` of the rectangle's) at the sharper look: ``unclear``,
   another frame would tell.

The parameters (:class:`EyeParams`) were set on the development scenes of ``bench/eye.py`` only
(rendered frames of every kind of object, seeds :data:`~coex_apps.demo.config.DEVELOPMENT_SEEDS`,
docs/demo.md says which), never on the dives that are reported.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy import ndimage

__all__ = ["KINDS", "SHAPED_KINDS", "TARGET_KINDS", "Eye", "EyeParams", "Segmentation", "Sight", "metres_per_pixel", "shrink"]

#: what the eye can say of an object
KINDS = ("car", "container", "hull", "debris", "object", "natural", "unclear", "partial")
#: the verdicts that are a target (something man-made): the operator confirms one of these
TARGET_KINDS = frozenset({"car", "container", "hull", "debris", "object"})
#: the target verdicts that come from one outline's shape (not from a patch of pieces)
SHAPED_KINDS = frozenset({"car", "container", "hull", "object"})

FloatImage = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


def shrink(image: npt.ArrayLike, factor: int) -> FloatImage:
    """Grey, box-filtered by ``factor`` (vectorised)."""
    a = np.asarray(image)
    h, w = a.shape[0] // factor * factor, a.shape[1] // factor * factor
    if a.ndim == 3:
        c = min(a.shape[2], 3)
        blocks = a[:h, :w, :c].reshape(h // factor, factor, w // factor, factor, c)
        return np.asarray(blocks.sum((1, 3, 4), dtype=np.float64) / (factor * factor * c), np.float64)
    blocks = a[:h, :w].reshape(h // factor, factor, w // factor, factor)
    return np.asarray(blocks.sum((1, 3), dtype=np.float64) / (factor * factor), np.float64)


def metres_per_pixel(altitude: float, width_px: int, hfov_deg: float) -> float:
    """The size on the seafloor of one pixel of a frame ``width_px`` wide taken looking down from
    ``altitude`` metres with a horizontal field of view of ``hfov_deg``."""
    return 2.0 * altitude * math.tan(math.radians(hfov_deg) / 2.0) / max(width_px, 1)


@dataclass(frozen=True)
class EyeParams:
    """The eye's parameters (set on development scenes only: see the module docstring)."""

    #: the frame is looked at reduced by this factor (160 x 120 for the 640 x 480 camera)
    scale: int = 4
    #: the background fit: rounds, and how far (robust spreads) a pixel may lie from it and count
    background_rounds: int = 4
    background_clip: float = 2.0
    #: smoothing (pixels of the reduced frame) before the anomaly maps
    smooth: float = 1.0
    #: a pixel stands out this many robust spreads of the sand darker or brighter ...
    min_contrast: float = 4.0
    #: ... or with this many times the sand's median local edge energy
    min_edges: float = 3.0
    #: smallest object (m²) and gap (m) under which pieces are one object
    min_area_m2: float = 0.6
    group_gap_m: float = 0.5
    #: an object runs off the frame when it lies along one of its edges for this long (m)
    cut_m: float = 0.3
    #: protrusions of an outline thinner than twice this (m) are opened away before it is measured
    open_m: float = 0.25
    #: a man-made outline: at least this share of its rotated bounding box filled (a rectangle
    #: about 1, an ellipse pi / 4) ...
    min_box_fill: float = 0.9
    #: ... and this share of its outline on the box's sides (straight edges), within
    #: ``side_tolerance`` pixels of them
    min_on_sides: float = 0.7
    side_tolerance: float = 1.5
    #: a hull: long (length over width), one end tapering to this share of the other's width,
    #: the rest straight-sided
    min_hull_aspect: float = 2.0
    max_bow_ratio: float = 0.75
    min_hull_sides: float = 0.62
    min_hull_fill: float = 0.86
    #: a whole object with a hull's length, aspect and tapering end whose outline is not straight
    #: or full enough for a hull is never ``natural`` from a layer still blurred (the first look:
    #: blur and the coding's ringing bend the outline, not the object's size or taper), and at
    #: the sharper look not while its straight share and its box's fill are within this of the
    #: hull's thresholds (``unclear``: another frame would tell)
    hull_doubt: float = 0.15
    #: debris: a ragged patch, filling at most this share of its convex hull (a rock, a mound
    #: or a car fills 0.9 or more; issue 50: 0.82 -> 0.86, chosen after seeing development
    #: scenes: patches called natural filled 0.83-0.93, decoys 0.89 or more, docs/demo.md)
    max_debris_solidity: float = 0.86
    #: ... at least this wide (m), its outline this many times the sand's gradient (wreckage has
    #: hard edges; a burrow's trail or a patch of spines on real sand is thin and soft)
    min_debris_width: float = 1.0
    min_debris_sharpness: float = 3.0
    #: sizes (m) of the kinds it knows
    car_length: tuple[float, float] = (2.4, 5.8)
    car_width: tuple[float, float] = (1.3, 2.35)
    container_length: tuple[float, float] = (5.8, 7.0)
    container_width: tuple[float, float] = (2.35, 3.0)
    hull_length: tuple[float, float] = (3.5, 9.0)
    debris_extent: tuple[float, float] = (1.5, 6.5)
    #: an object the frame cuts with two straight parallel sides (a hull's or a box's flanks), at
    #: least this long (m) and this many times as long as they are apart, apart by a car's to a
    #: container's width (m): man-made; a hull when its far end tapers (``max_bow_ratio``)
    min_cut_straight: float = 1.8
    min_cut_straight_ratio: float = 0.75
    cut_apart: tuple[float, float] = (1.2, 3.5)
    #: an outline at all: this many times the sand's median gradient on it
    min_sharpness: float = 1.5
    #: measures this close to a man-made threshold are asked about again at a higher quality
    #: (unless every layer asked for has arrived: the best image the operator will get)
    margin: float = 0.05


@dataclass(frozen=True)
class Sight:
    """One object the eye found in a frame: its verdict, where it is (a pixel box of the
    full-size frame: x0, y0, x1, y1, and its centre) and what it measured."""

    kind: str
    box: tuple[int, int, int, int]
    centre: tuple[float, float]
    length_m: float
    width_m: float
    area_m2: float
    #: share of the rotated bounding box filled, share of the outline on its sides
    box_fill: float
    on_sides: float
    #: narrow end over wide end (1: both ends alike); share of its convex hull it fills
    bow_ratio: float
    solidity: float
    #: mean relative brightness inside (1: the sand's), and in the sand's robust spreads
    brightness: float
    contrast: float
    sharpness: float
    edge_width: float
    #: the frame's edges it touches: "top" (ahead), "bottom" (behind), "left", "right"
    cut: tuple[str, ...] = ()
    why: str = ""
    #: the longest stretch (m) along its long axis over which both long sides are straight and
    #: parallel (they lie on its box's sides): a hull's or a box's flank, not a rock's curve
    straight_m: float = 0.0
    #: ... and how far apart they are (m)
    apart_m: float = 0.0

    @property
    def target(self) -> bool:
        """A verdict of something man-made (:data:`TARGET_KINDS`)."""
        return self.kind in TARGET_KINDS

    def describe(self) -> str:
        cut = f", cut by the frame's {'/'.join(self.cut)} edge" if self.cut else ""
        return (f"{self.kind}: {self.length_m:.1f} x {self.width_m:.1f} m, {self.box_fill:.0%} of its box filled, "
                f"{self.on_sides:.0%} of its outline straight, ends {self.bow_ratio:.0%} alike, {self.solidity:.0%} of its hull filled, {self.brightness:.0%} as bright "
                f"as the sand, edges {self.sharpness:.1f}x the sand's and {self.edge_width:.1f} px wide{cut}"
                + (f" ({self.why})" if self.why else ""))

    def as_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "box": list(self.box), "centre": [round(c, 1) for c in self.centre],
                "length_m": self.length_m, "width_m": self.width_m, "area_m2": self.area_m2,
                "box_fill": self.box_fill, "on_sides": self.on_sides, "bow_ratio": self.bow_ratio,
                "solidity": self.solidity, "brightness": self.brightness, "contrast": self.contrast,
                "sharpness": self.sharpness, "edge_width": self.edge_width, "cut": list(self.cut), "why": self.why,
                "straight_m": self.straight_m, "apart_m": self.apart_m}


@functools.lru_cache(maxsize=8)
def _basis(h: int, w: int, degree: int) -> FloatImage:
    """The 2-D polynomial terms up to ``degree`` over an ``h`` x ``w`` frame (centred, in half
    widths), one row per pixel."""
    yy, xx = np.mgrid[0:h, 0:w]
    x = ((xx - (w - 1) / 2) / (w / 2)).ravel()
    y = ((yy - (h - 1) / 2) / (w / 2)).ravel()
    return np.stack([x**i * y**j for i in range(degree + 1) for j in range(degree + 1 - i)], -1)


def _background(lg: FloatImage, exclude: Mask, rounds: int, clip: float, degree: int = 3) -> tuple[FloatImage, Mask]:
    """The lighting: a smooth surface (a polynomial of the log brightness ``lg``) fitted robustly,
    on every other pixel outside ``exclude`` (objects already outlined), leaving out at each round
    the pixels more than ``clip`` robust spreads from it; and the pixels that fit it (the sand)."""
    h, w = lg.shape
    basis = _basis(h, w, degree)
    flat = lg.ravel()
    sub = np.zeros((h, w), bool)
    sub[1::3, 1::3] = True
    sub &= ~exclude
    if sub.sum() < 0.2 * h * w / 9:  # objects everywhere: fit what there is
        sub = np.zeros((h, w), bool)
        sub[1::3, 1::3] = True
    sub_flat = sub.ravel()
    keep = sub_flat.copy()
    fit = np.full(flat.size, float(np.median(flat)))
    spread = 1.0
    ridge = 1e-6 * np.eye(basis.shape[1])
    for _ in range(max(rounds, 1)):
        b = basis[keep]
        coef = np.linalg.solve(b.T @ b + ridge, b.T @ flat[keep])  # the normal equations: a few terms
        fit = basis @ coef
        res = flat - fit
        spread = _robust_spread(res[keep]) + 1e-3
        inlier = np.abs(res) <= clip * spread
        if (inlier & sub_flat).sum() < 0.25 * sub_flat.sum():  # most of the frame is one object: keep the fit
            break
        keep = inlier & sub_flat
    sand = (np.abs(flat - fit) <= clip * spread).reshape(h, w) & ~exclude
    return fit.reshape(h, w), sand


def _robust_spread(a: npt.NDArray[np.float64]) -> float:
    return 1.4826 * float(np.median(np.abs(a - np.median(a)))) + 1e-6


@dataclass(frozen=True)
class Segmentation:
    """One frame as the eye reduced and split it: the log brightness (smoothed), the lighting
    fitted to it, its gradient, the sand's pixels and the objects' (every piece)."""

    lg: FloatImage
    background: FloatImage
    grad: FloatImage
    gx: FloatImage
    gy: FloatImage
    sand: Mask
    #: every object, gaps closed and holes filled; and before that (its pieces apart)
    mask: Mask
    raw: Mask
    #: the sand's robust spread of log brightness and its median gradient
    spread: float
    sand_energy: float


@dataclass
class Eye:
    """The operator's eye (see the module docstring): :meth:`look` at a received frame."""

    params: EyeParams = field(default_factory=EyeParams)

    def segment(self, received: npt.ArrayLike) -> Segmentation | None:
        """Steps 1 and 2 of the module docstring: the lighting, the sand and the objects."""
        p = self.params
        img = np.asarray(received)
        if img.ndim < 2 or min(img.shape[:2]) < 8 * p.scale:
            return None
        g = shrink(img, p.scale)
        lg = ndimage.gaussian_filter(np.log(np.maximum(g, 1.0)), p.smooth)
        gy, gx = np.gradient(lg)
        grad = np.hypot(gx, gy)
        grad[[0, -1], :] = 0.0  # one-sided differences at the frame's edges: no outline there
        grad[:, [0, -1]] = 0.0
        typical = float(np.median(grad)) + 1e-6
        square = np.ones((3, 3), bool)
        # outlines first: strong edges, closed, filled (an object the sand's own colour too) ...
        outlined = ndimage.binary_closing(grad >= p.min_edges * typical, square, iterations=2)
        outlined = ndimage.binary_opening(ndimage.binary_fill_holes(outlined), square)
        # ... then the lighting, fitted without them, and what is darker or brighter than the sand
        bg, sand = _background(lg, ndimage.binary_dilation(outlined, iterations=2), p.background_rounds,
                               p.background_clip)
        spread = _robust_spread((lg - bg)[sand])
        level = float(np.median((lg - bg)[sand]))
        # an object that the frame cuts keeps its edge: the morphology sees the frame's edge repeated
        k = 3
        pad = np.pad(outlined | (np.abs(lg - bg - level) >= p.min_contrast * spread), k, mode="edge")
        raw_pad = ndimage.binary_opening(pad, square)
        raw = raw_pad[k:-k, k:-k]
        mask = ndimage.binary_fill_holes(ndimage.binary_closing(raw_pad, square, iterations=2)[k:-k, k:-k])
        sand_energy = float(np.median(grad[sand])) + 1e-6
        # soft patches (no outline: what is left of the lighting) are not objects
        comps, n = ndimage.label(mask, square)
        if n:
            rim = mask & ~ndimage.binary_erosion(mask, border_value=1)
            edge = np.asarray(ndimage.mean(grad, np.where(rim, comps, 0), np.arange(1, n + 1)), np.float64)
            soft = np.flatnonzero(np.nan_to_num(edge) < p.min_sharpness * sand_energy) + 1
            if soft.size:
                gone = np.isin(comps, soft)
                mask &= ~gone
                raw &= ~gone
        return Segmentation(lg, bg + level, grad, gx, gy, sand & ~mask, mask, raw, spread, sand_energy)

    def look(self, received: npt.ArrayLike, mpp: float, *, settled: bool = False) -> list[Sight]:
        """The objects in ``received`` (a frame as decoded topside, full size), ``mpp`` metres of
        seafloor per full-size pixel (:func:`metres_per_pixel`); ``settled``: every layer asked
        for has arrived (the best image the operator will get). Largest first."""
        p = self.params
        seg = self.segment(received)
        if seg is None or not seg.mask.any():
            return []
        step = mpp * p.scale  # metres per pixel of the reduced frame
        square = np.ones((3, 3), bool)
        gap = max(1, round(p.group_gap_m / step / 2))
        groups, _ = ndimage.label(ndimage.binary_dilation(seg.mask, iterations=gap), square)
        sights = []
        h, w = seg.mask.shape
        pad = 8
        for k, sl in enumerate(ndimage.find_objects(groups), 1):
            if sl is None:
                continue
            # a window around the object, a margin wide, to measure it and the sand around it
            win = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, h)),
                   slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, w)))
            obj = (groups[win] == k) & seg.mask[win]
            if float(obj.sum()) * step * step < p.min_area_m2:
                continue
            sight = self._measure(obj, win, seg, step, settled, (h, w))
            for piece in ([] if sight.target else self._pieces(obj, step)):
                # a car or a container beside a patch of the sand's clutter is grouped with it:
                # its own outline, apart from the patch, tells what it is
                alone = self._measure(piece, win, seg, step, settled, (h, w))
                if alone.kind in SHAPED_KINDS:
                    sight = alone
                    break
            sights.append(sight)
        return sorted(sights, key=lambda s: -s.area_m2)

    def _pieces(self, obj: Mask, step: float) -> list[Mask]:
        """An object's largest piece once necks narrower than 2, 4, then 6 times
        :attr:`EyeParams.open_m` are opened away (what touches it cut off), each with its
        corners back (the object's pixels within 0.42 of the opening's radius of it); only
        pieces large enough to be an object and smaller than the whole."""
        p = self.params
        out = []
        for k in (1, 2, 3):
            r = max(1, round(k * p.open_m / step))
            pieces, n = ndimage.label(ndimage.binary_opening(obj, _disk(r)), np.ones((3, 3), bool))
            if n == 0:
                continue
            sizes = np.asarray(ndimage.sum_labels(np.ones_like(pieces), pieces, np.arange(1, n + 1)), np.float64)
            big = int(np.argmax(sizes))
            # the opening rounds a corner by at most 0.42 r: grown back that far, within the object
            piece = obj & ndimage.binary_dilation(pieces == big + 1, _disk(math.ceil(0.42 * r)))
            if float(piece.sum()) * step * step >= p.min_area_m2 and piece.sum() < 0.97 * obj.sum():
                out.append(np.asarray(piece))
        return out

    # ------------------------------------------------------------------ one object
    def _measure(self, obj: Mask, win: tuple[slice, slice], seg: Segmentation,
                 step: float, settled: bool, shape: tuple[int, int]) -> Sight:
        p = self.params
        r0, c0 = win[0].start, win[1].start
        # its outline without thin protrusions (a ripple or a speck of the sand that touches it)
        r = max(1, round(p.open_m / step))
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        h, w = shape
        # cut by the frame: it runs along an edge of the frame (a corner touching it is not a cut)
        rr, cc = np.nonzero(obj)
        run = max(2, round(p.cut_m / step))
        cut = tuple(name for name, hit in (("top", np.sum(rr + r0 == 0) >= run), ("bottom", np.sum(rr + r0 == h - 1) >= run),
                                           ("left", np.sum(cc + c0 == 0) >= run), ("right", np.sum(cc + c0 == w - 1) >= run))
                    if hit)
        smooth = ndimage.binary_opening(obj, xx * xx + yy * yy <= r * r)
        if smooth.sum() >= 0.5 * obj.sum():
            obj = smooth
        rows, cols = np.nonzero(obj)
        area = float(rows.size) * step * step
        ys, xs = (rows + 0.5) * step, (cols + 0.5) * step
        cov = np.cov(np.stack([xs, ys])) if rows.size > 2 else np.eye(2) * step * step
        ev, vec = np.linalg.eigh(cov)
        major = vec[:, 1]
        length = math.sqrt(12.0 * max(float(ev[1]), 0.0) + step * step)
        width = math.sqrt(12.0 * max(float(ev[0]), 0.0) + step * step)
        # the outline in the object's own axes: its rotated bounding box, how full it is, and the
        # share of the outline lying on its sides
        u = (xs - xs.mean()) * major[0] + (ys - ys.mean()) * major[1]
        v = -(xs - xs.mean()) * major[1] + (ys - ys.mean()) * major[0]
        edge = obj & ~ndimage.binary_erosion(obj)
        er, ec = np.nonzero(edge)
        ex, ey = (ec + 0.5) * step - xs.mean(), (er + 0.5) * step - ys.mean()
        eu, ev_ = ex * major[0] + ey * major[1], -ex * major[1] + ey * major[0]
        ulo, uhi = np.percentile(u, [0.5, 99.5])
        vlo, vhi = np.percentile(v, [0.5, 99.5])
        box_fill = min(area / max((uhi - ulo + step) * (vhi - vlo + step), step * step), 1.0)
        tol = p.side_tolerance * step
        on = (np.minimum(np.abs(eu - ulo), np.abs(eu - uhi)) <= tol) | (
            np.minimum(np.abs(ev_ - vlo), np.abs(ev_ - vhi)) <= tol)
        inner_edge = (er + r0 > 0) & (er + r0 < h - 1) & (ec + c0 > 0) & (ec + c0 < w - 1)
        if cut:  # the frame's edge is no side of the object's own: its outline is the rest
            on = on[inner_edge]
        on_sides = float(on.mean()) if on.size else 0.0
        straight, apart = _straight_sides(ex, ey, inner_edge, math.atan2(major[1], major[0]), step, tol)
        # taper: the object's width near each end of its long axis
        bow = 1.0
        ends: list[float] = []
        if u.size > 20 and uhi - ulo > 4 * step:
            span = uhi - ulo
            for a, b in ((ulo + 0.03 * span, ulo + 0.15 * span), (uhi - 0.15 * span, uhi - 0.03 * span)):
                sel = (u >= a) & (u <= b)
                ends.append(float(np.percentile(v[sel], 95) - np.percentile(v[sel], 5)) if sel.sum() > 3 else 0.0)
            bow = min(ends) / max(max(ends), 1e-6)
        # cut by the frame: how the end away from the frame compares with the straight sides'
        # spacing (a bow tapers; a car's or a container's end is as wide as its sides are apart)
        far = bow
        if cut and ends and apart > 0 and not inner_edge.all():
            at_frame = float(eu[~inner_edge].mean())
            far = min((ends[1] if at_frame < (ulo + uhi) / 2 else ends[0]) / apart, 1.0)
        # how much of its convex hull it fills: a patch of pieces leaves gaps and notches
        solid = _solidity(edge, rows.size)
        # brightness, and how clear its outline is: the step from the object to the sand around
        # it over the steepest gradients on the outline (a blurred edge spreads the step)
        band = ndimage.binary_dilation(obj) & ~ndimage.binary_erosion(obj)
        around = ndimage.binary_dilation(obj, iterations=6) & ~ndimage.binary_dilation(seg.mask[win], iterations=2)
        lg, bg, grad = seg.lg[win], seg.background[win], seg.grad[win]
        inside = float((lg - bg)[obj].mean())
        sand_level = float((lg - bg)[around].mean()) if around.sum() >= 10 else 0.0
        on_edge = float(np.percentile(grad[band], 75)) if band.any() else 0.0
        sharp = float(grad[band].mean()) / seg.sand_energy if band.any() else 0.0
        edge_width = abs(inside - sand_level) / max(on_edge, 1e-6)
        kind, why = self._verdict(length, width, box_fill, on_sides, bow, solid, sharp, settled, cut, (straight, apart, far))
        s = p.scale
        box = (int((c0 + cols.min()) * s), int((r0 + rows.min()) * s), int((c0 + cols.max() + 1) * s),
               int((r0 + rows.max() + 1) * s))
        centre = ((float(cols.mean()) + c0 + 0.5) * s, (float(rows.mean()) + r0 + 0.5) * s)
        return Sight(kind, box, centre, round(length, 2), round(width, 2), round(area, 2), round(box_fill, 2),
                     round(on_sides, 2), round(bow, 2), round(solid, 2), round(math.exp(inside - sand_level), 2),
                     round((inside - sand_level) / seg.spread, 1), round(sharp, 2), round(edge_width, 1), cut, why,
                     round(straight, 2), round(apart, 2))

    def _verdict(self, length: float, width: float, box_fill: float, on_sides: float, bow: float, solid: float,
                 sharp: float, settled: bool, cut: tuple[str, ...],
                 sides: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> tuple[str, str]:
        p = self.params
        m = p.margin

        def within(x: float, r: tuple[float, float]) -> bool:
            return r[0] <= x <= r[1]
        if sharp < p.min_sharpness:
            return ("natural", "a soft patch with no outline") if settled else ("unclear", "no clear outline")
        if cut:
            # a rectangle cut by the frame (beyond the margin, at least a car's width and length
            # showing) is man-made whatever its whole size: straight sides meeting square
            if (box_fill >= p.min_box_fill + m and on_sides >= p.min_on_sides + m
                    and min(length, width) >= p.car_width[0] and max(length, width) >= p.car_length[0]):
                return "object", "a straight-edged rectangle, cut by the frame"
            # two straight parallel sides running out of the frame (a hull's or a box's flanks;
            # a rock's or a mound's outline curves all along)
            straight, apart, far = sides
            if (straight >= p.min_cut_straight and straight >= p.min_cut_straight_ratio * apart
                    and within(apart, p.cut_apart)):
                if far <= p.max_bow_ratio:
                    return "hull", "straight parallel sides and a tapering end, cut by the frame"
                return "object", "straight parallel sides, cut by the frame"
            if not settled and len({"left", "right"} & set(cut)) == 1 and within(apart, p.cut_apart):
                # the first look's outline is too rough to show straight sides: decide at the
                # sharper look (nothing along the line would show more of it)
                return "unclear", "cut by the frame's side: a sharper look would tell its sides"
            return "partial", "cut by the frame"
        long = length / max(width, 1e-6) >= p.min_hull_aspect and within(length, p.hull_length)
        hull = long and bow <= p.max_bow_ratio and on_sides >= p.min_hull_sides and box_fill >= p.min_hull_fill
        rect = box_fill >= p.min_box_fill and on_sides >= p.min_on_sides
        debris = (solid <= p.max_debris_solidity and within(length, p.debris_extent) and width >= p.min_debris_width
                  and sharp >= p.min_debris_sharpness)
        # a measure this close to its threshold could go either way: a sharper look would tell
        near_bow = long and abs(bow - p.max_bow_ratio) <= m and on_sides >= p.min_hull_sides - m
        near_rect = ((abs(box_fill - p.min_box_fill) <= m and on_sides >= p.min_on_sides - m)
                     or (abs(on_sides - p.min_on_sides) <= m and box_fill >= p.min_box_fill - m))
        near_ragged = (abs(solid - p.max_debris_solidity) <= m and within(length, p.debris_extent)
                       and width >= p.min_debris_width and sharp >= p.min_debris_sharpness)
        for close, hit, what in ((near_bow, hull, "a tapering end"), (near_rect, rect, "a rectangle"),
                                 (near_ragged, debris, "a ragged patch")):
            if close and not settled:
                return "unclear", f"nearly {what}: a sharper look would tell"
            if hit:
                break
        if hull:
            return "hull", "long, straight-sided, one end tapering"
        if rect:
            if within(length, p.car_length) and within(width, p.car_width):
                return "car", "a straight-edged rectangle of a car's size"
            if within(length, p.container_length) and within(width, p.container_width):
                return "container", "a straight-edged rectangle of a container's size"
            return "object", "a straight-edged rectangle of no known size"
        if debris:
            return "debris", "a ragged patch of pieces"
        # a hull's length and taper, its outline too rough for a hull's: the first look's layer
        # is still blurred (issue 50: whole hulls 29-58 % straight at 3 layers, 76 % or more at
        # 4); at the sharper look a doubtful outline is looked at again in another frame
        if long and bow <= p.max_bow_ratio + (0.0 if settled else m):
            if not settled:
                return "unclear", "a hull's length and taper, its outline blurred: a sharper look would tell"
            if on_sides >= p.min_hull_sides - p.hull_doubt and box_fill >= p.min_hull_fill - p.hull_doubt:
                return "unclear", "a hull's length and taper, its outline nearly a hull's: another frame would tell"
        # nearly a rectangle of a car's or a container's size at the sharper look (a rock or a
        # mound fills at most 0.83 of its box): another frame would tell, never natural (issue
        # 50: a container's outline joined by the sand's clutter at 4 layers, 91 % filled)
        car_size = within(length, p.car_length) and within(width, p.car_width)
        container_size = within(length, p.container_length) and within(width, p.container_width)
        if settled and near_rect and (car_size or container_size):
            return "unclear", "nearly a rectangle of a car's or a container's size: another frame would tell"
        return "natural", "a rounded or irregular outline"


def _straight_sides(x: FloatImage, y: FloatImage, inner: Mask, angle: float, step: float, tol: float,
                    turn: float = 30.0) -> tuple[float, float]:
    """The longest stretch (m) over which an object's outline runs along two straight parallel
    lines (its long sides), and its width across them (m): the outline's points ``x``, ``y`` (m),
    those not on the frame's edge ``inner``; the directions tried lie within ``turn`` degrees of
    ``angle`` (radians, its long axis): the frame cuts a bar at a slant, which tilts its axis of
    inertia off its sides. A side is the outline's points within ``tol`` of the extreme line; its
    length the longest run of them along the direction, gaps of one pixel bridged."""
    if int(inner.sum()) < 8:
        return 0.0, 0.0
    a = angle + np.radians(np.arange(-turn, turn + 0.1, 1.5))
    c, s = np.cos(a)[:, None], np.sin(a)[:, None]
    u = x[None, :] * c + y[None, :] * s  # angles x points
    v = -x[None, :] * s + y[None, :] * c
    vhi, vlo = v.max(1, keepdims=True), v.min(1, keepdims=True)
    n = math.ceil(float(np.ptp(u, 1).max()) / step) + 3
    bins = np.clip(np.floor((u - u.min(1, keepdims=True)) / step).astype(np.int64) + 1, 0, n - 1)
    rows = np.broadcast_to(np.arange(a.size)[:, None], u.shape)
    best, across = 0.0, 0.0
    runs = []
    for side in (v >= vhi - tol, v <= vlo + tol):
        occ = np.zeros((a.size, n), bool)
        hit = side & inner[None, :]
        occ[rows[hit], bins[hit]] = True
        occ[:, 1:-1] |= occ[:, :-2] & occ[:, 2:]  # a one-pixel gap bridged
        pad = np.zeros((a.size, 1), bool)
        d = np.diff(np.concatenate([pad, occ, pad], 1).astype(np.int8), axis=1)
        # the longest run per angle: starts and ends of runs, in order, per row
        r_s, c_s = np.nonzero(d == 1)
        _, c_e = np.nonzero(d == -1)
        longest = np.zeros(a.size)
        np.maximum.at(longest, r_s, (c_e - c_s).astype(np.float64))
        runs.append(longest)
    both = np.minimum(runs[0], runs[1]) * step
    k = int(np.argmax(both))
    best = float(both[k])
    across = float(vhi[k, 0] - vlo[k, 0]) + step
    return best, across


@functools.lru_cache(maxsize=16)
def _disk(r: int) -> Mask:
    """A disk of radius ``r`` pixels (a structuring element)."""
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    return np.asarray(xx * xx + yy * yy <= r * r)


def _solidity(edge: Mask, area: int) -> float:
    """Share of its convex hull an object of ``area`` pixels fills, from its outline's pixels
    (their corners; scipy's Qhull)."""
    from scipy.spatial import ConvexHull, QhullError

    r, c = np.nonzero(edge)
    if r.size < 3:
        return 1.0
    pts = np.concatenate([np.stack([c + dx, r + dy], 1) for dx in (0, 1) for dy in (0, 1)]).astype(np.float64)
    try:
        hull = ConvexHull(pts)
    except QhullError:
        return 1.0
    return float(min(area / max(hull.volume, 1.0), 1.0))


def _box_fill(mask: Mask) -> float:
    """Share of its rotated bounding box that ``mask`` fills (1 for a rectangle, pi/4 for an
    ellipse)."""
    rows, cols = np.nonzero(mask)
    if rows.size < 4:
        return 0.0
    cov = np.cov(np.stack([cols.astype(float), rows.astype(float)]))
    _, vec = np.linalg.eigh(cov)
    major = vec[:, 1]
    x, y = cols - cols.mean(), rows - rows.mean()
    u, v = x * major[0] + y * major[1], -x * major[1] + y * major[0]
    box = (np.ptp(u) + 1.0) * (np.ptp(v) + 1.0)
    return float(min(rows.size / max(box, 1.0), 1.0))

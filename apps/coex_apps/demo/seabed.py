"""The sand's albedo built from real seafloor frames (``coex demo --images DIR``): part of the
simulator's renderer, never of the operator's eye.

Each real frame is turned into a texture of the sand: its grey level divided by its own lighting
(the frame blurred over a fifth of its width, which takes away the vignette and the fall-off of
the light it was taken with), scaled to the procedural sand's mean albedo. The seafloor is then
tiled with these textures in world coordinates: a lattice of nodes :data:`CELL` metres apart,
each node showing a piece of one frame (drawn by the seed: which frame, where in it, flipped or
not) under a raised-cosine window, the windows of neighbouring nodes overlapping by half so that
no seam is a straight edge, and the blend keeping the texture's contrast. The same ground point
always shows the same texture, so successive frames of a transect overlap as real ones do, and
whatever the real frames hold (ripples, burrows, brittle stars, a fish) lies on the simulated
seafloor, unlabelled: it is sand to the referee, and the eye may take it for something else.

Frames that show the 2022 wreck (:data:`WRECK_FRAMES` of ``../shared/data/nui040``) are left out:
an unlabelled car in the background would be a target that the truth does not know.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

__all__ = ["CELL", "METRES_PER_PIXEL", "WRECK_FRAMES", "RealSandTexture", "sand_frames"]

#: the ground size of a real frame's pixel (m): the NUI camera about 4-5 m above the seafloor
METRES_PER_PIXEL = 0.01
#: spacing of the texture's lattice (m); each node's window spans twice that
CELL = 2.0
#: the procedural sand's mean albedo (:class:`~coex_apps.demo.camera.SandTexture`), which the
#: real texture takes too
MEAN_ALBEDO = 0.55
#: NUI dive 040 frames that show the wreck (the README of ``../shared/data/nui040``)
WRECK_FRAMES = frozenset({"image_001714", "image_001715", "image_001716", "image_001717",
                          "image_001782", "image_001783", "image_001784", "image_001785"})


def sand_frames(files: Sequence[Path]) -> list[Path]:
    """The frames of ``files`` that show no wreck (all of them for frames not from NUI 040)."""
    return [f for f in files if f.stem not in WRECK_FRAMES]


def _blur(a: npt.NDArray[np.float64], sigma: float) -> npt.NDArray[np.float64]:
    from scipy import ndimage

    return np.asarray(ndimage.gaussian_filter(a, sigma, mode="reflect"), np.float64)


def _texture(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
    """A frame's sand texture: its grey level over its own lighting, at the sand's mean albedo."""
    g = np.asarray(image, np.float64)
    if g.ndim == 3:
        g = g[..., :3].mean(-1)
    light = np.maximum(_blur(g, g.shape[1] / 10), 1.0)
    t = g / light
    return np.asarray(np.clip(MEAN_ALBEDO * t / max(float(np.median(t)), 1e-6), 0.02, 1.2), np.float32)


class RealSandTexture:
    """The sand's albedo at ground points from real frames (see the module docstring); called
    like :class:`~coex_apps.demo.camera.SandTexture` with ground x and y arrays."""

    def __init__(self, images: Sequence[npt.NDArray[np.uint8]], seed: int = 0, nodes: int = 4096) -> None:
        if not images:
            raise ValueError("no real frames to build the sand from")
        tex = [_texture(im) for im in images]
        h = min(t.shape[0] for t in tex)
        w = min(t.shape[1] for t in tex)
        self.stack = np.stack([t[:h, :w] for t in tex])
        self.mean = float(self.stack.mean())
        half = int(CELL / METRES_PER_PIXEL)  # a window reaches CELL metres from its node
        if min(h, w) < 2 * half + 2:
            raise ValueError(f"real frames of {w} x {h} pixels are too small for {CELL:g} m windows")
        rng = np.random.default_rng([seed, 7])
        self.nodes = nodes
        self.frame = rng.integers(0, len(tex), nodes)
        self.row = rng.integers(half, h - half - 1, nodes)
        self.col = rng.integers(half, w - half - 1, nodes)
        self.flip = rng.choice(np.array([-1, 1]), (nodes, 2))

    def _node(self, i: npt.NDArray[np.int64], j: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        return np.asarray((i * 7919 + j * 104729) % self.nodes, np.int64)

    def __call__(self, gx: npt.ArrayLike, gy: npt.ArrayLike) -> npt.NDArray[np.float64]:
        x = np.asarray(gx, np.float64) / CELL
        y = np.asarray(gy, np.float64) / CELL
        i0, j0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        acc = np.zeros(x.shape, np.float64)
        wsum = np.zeros(x.shape, np.float64)
        for di in (0, 1):
            for dj in (0, 1):
                i, j = i0 + di, j0 + dj
                du, dv = x - i, y - j  # (-1, 1): in cells from the node
                wt = np.cos(0.5 * np.pi * du) ** 2 * np.cos(0.5 * np.pi * dv) ** 2
                k = self._node(i, j)
                px = du * CELL / METRES_PER_PIXEL * self.flip[k, 0]
                py = dv * CELL / METRES_PER_PIXEL * self.flip[k, 1]
                r = np.clip(np.round(self.row[k] - py).astype(np.int64), 0, self.stack.shape[1] - 1)
                c = np.clip(np.round(self.col[k] + px).astype(np.int64), 0, self.stack.shape[2] - 1)
                acc += wt * (self.stack[self.frame[k], r, c] - self.mean)
                wsum += wt * wt
        # the windows sum to one; dividing by the root of their squares keeps the contrast
        return np.asarray(MEAN_ALBEDO + acc / np.sqrt(np.maximum(wsum, 1e-6)) * (MEAN_ALBEDO / self.mean), np.float64)

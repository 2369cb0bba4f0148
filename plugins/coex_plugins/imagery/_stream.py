"""The ``params`` code of an image (spec/payloads.md section 3.1) and the order of its packets:
what the codec (:mod:`.codec`), the packet-header parser and writer (:mod:`.packets`) and the
layer tightening (:mod:`.tighten`) share. The codec re-exports every name here."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from coex import DecodeError, persistent

__all__ = ["PRECINCTS", "PROGRESSIONS", "StreamParams", "packet_order", "params_code", "parse_params"]

PROGRESSIONS = ("LRCP", "RLCP", "RPCL", "PCRL", "CPRL")
#: Precinct sizes by ``params`` code (bits 14..13): 0 = one precinct per resolution, else square
#: precincts of this many samples at every resolution (only with LRCP or RLCP).
PRECINCTS = (0, 256, 128, 512)


def params_code(progression: str, resolutions: int, layers: int, irreversible: bool, colour: bool,
                precincts: int = 0) -> int:
    """The 15-bit code sent in ``ImageAnnounce.params``.

    Bits (MSB first): precinct size code (2, :data:`PRECINCTS`), progression index (3),
    resolutions - 1 (3), layers - 1 (5), irreversible 9/7 wavelet (1), colour with
    multi-component transform (1)."""
    p = PROGRESSIONS.index(progression)
    return ((PRECINCTS.index(precincts) << 13) | (p << 10) | ((resolutions - 1) << 7) | ((layers - 1) << 2)
            | (int(irreversible) << 1) | int(colour))


@persistent("imagery.StreamParams")
@dataclass(frozen=True)
class StreamParams:
    """Decoded ``params`` code."""

    progression: str
    resolutions: int
    layers: int
    irreversible: bool
    colour: bool
    #: precinct size in samples at every resolution (0: one precinct per resolution)
    precincts: int = 0

    @property
    def components(self) -> int:
        return 3 if self.colour else 1

    def precinct_grid(self, width: int, height: int) -> list[tuple[int, int]]:
        """Precincts across and down at each resolution (0 = lowest) of a ``width x height`` image."""
        out = []
        for r in range(self.resolutions):
            s = 1 << (self.resolutions - 1 - r)
            w, h = -(-width // s), -(-height // s)
            if self.precincts:
                out.append((-(-w // self.precincts), -(-h // self.precincts)))
            else:
                out.append((1, 1))
        return out

    def n_packets(self, width: int, height: int) -> int:
        """Packets in the body of a ``width x height`` image."""
        per_layer = sum(nx * ny for nx, ny in self.precinct_grid(width, height))
        return self.layers * per_layer * self.components


def parse_params(code: int) -> StreamParams:
    """Inverse of :func:`params_code`; raises :class:`DecodeError` for an invalid code."""
    if not 0 <= code < 1 << 15:
        raise DecodeError(f"image params code {code} out of range")
    p = (code >> 10) & 7
    if p >= len(PROGRESSIONS):
        raise DecodeError(f"image params code {code:#x}: unknown progression {p}")
    precincts = PRECINCTS[code >> 13]
    if precincts and PROGRESSIONS[p] not in ("LRCP", "RLCP"):
        raise DecodeError(f"image params code {code:#x}: precincts with progression {PROGRESSIONS[p]}")
    return StreamParams(
        PROGRESSIONS[p], ((code >> 7) & 7) + 1, ((code >> 2) & 31) + 1, bool(code >> 1 & 1), bool(code & 1),
        precincts,
    )


@functools.lru_cache(maxsize=64)
def _packet_order(sp: StreamParams, width: int, height: int) -> npt.NDArray[np.int64]:
    grid = sp.precinct_grid(width, height)
    if not sp.precincts:
        dims = {"L": sp.layers, "R": sp.resolutions, "C": sp.components, "P": 1}
        grids = np.meshgrid(*[np.arange(dims[c]) for c in sp.progression], indexing="ij")
        cols = {c: g.ravel() for c, g in zip(sp.progression, grids, strict=True)}
        out = np.stack([cols["L"], cols["R"], cols["C"], cols["P"]], axis=1).astype(np.int64)
    else:  # LRCP or RLCP: precincts innermost, in raster order, their count depends on r
        rows: list[tuple[int, int, int, int]] = []
        outer = [(layer, r) for layer in range(sp.layers) for r in range(sp.resolutions)]
        if sp.progression == "RLCP":
            outer = [(layer, r) for r in range(sp.resolutions) for layer in range(sp.layers)]
        for layer, r in outer:
            nx, ny = grid[r]
            for c in range(sp.components):
                rows.extend((layer, r, c, p) for p in range(nx * ny))
        out = np.array(rows, np.int64).reshape(-1, 4)
    out.setflags(write=False)
    return out


def packet_order(sp: StreamParams, width: int = 1, height: int = 1) -> npt.NDArray[np.int64]:
    """``(n_packets, 4)`` array of (layer, resolution, component, precinct) in codestream order
    for a ``width x height`` image (precincts in raster order within their resolution)."""
    return _packet_order(sp, int(width), int(height))

"""JPEG 2000 coding for the imagery modality (glymur on OpenJPEG), without sending headers.

The vehicle encodes an image with a PLT marker (packet lengths), then keeps only the *body*: the
packet data between the tile-part's SOD marker and the EOC. The main header is the same for every
image with the same coding parameters and size, so it is never sent: ``ImageAnnounce.params``
carries a 15-bit code (:func:`params_code`, spec/payloads.md section 3.1: progression,
resolutions, layers, wavelet, colour and precinct size) and topside rebuilds the header by encoding a dummy
image with the same parameters (:func:`main_header`, cached).

Topside decodes *whole packets only* (:func:`assemble`): every packet that is missing or
incomplete, and every later packet of the same precinct (resolution, component and precinct: their code-block state
depends on it), is replaced by an empty packet (one ``0x00`` byte). The stream is closed with
``Psot = 0`` and an EOC marker, which stock OpenJPEG decodes in strict mode (recipe B of
``reference/imagery.md``).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import itertools
import os
import tempfile
import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from coex import ConfigError, DecodeError, persistent

from ._stream import PRECINCTS, PROGRESSIONS, StreamParams, packet_order, params_code, parse_params
from .tighten import tighten

__all__ = [
    "CodingParams",
    "Encoded",
    "PRECINCTS",
    "PROGRESSIONS",
    "StreamParams",
    "add_residual",
    "assemble",
    "decode_packets",
    "encode_image",
    "encode_residual",
    "main_header",
    "packet_order",
    "params_code",
    "parse_params",
    "region_packets",
    "residual",
    "to_grey",
]

MAX_LAYERS = 32
MAX_RESOLUTIONS = 8
#: The body of one image never exceeds this (the wire offset field has 20 bits).
MAX_BODY_BYTES = 2**20 - 1
#: Default layer ends (cumulative body bytes). Chosen by measurement on the NUI dive-040 images
#: (``bench/imagery.py``, docs/imagery.md): a small first layer so that a recognisable image
#: arrives in the first frame, few layers below 1 KB (each layer costs one packet header per
#: precinct), then steps of about 1.3x up to 20 KB. With 256-sample precincts (for regions) the
#: whole image reaches 25 / 30 / 35 dB in about the bytes of the earlier 22-layer ladder without
#: precincts.
DEFAULT_LAYER_BYTES: tuple[int, ...] = (
    40, 100, 220, 400, 600, 800, 1050, 1400, 1850, 2400, 3100, 4000, 5200, 6700, 8700, 11300,
    14700, 20480,
)
#: Default quality marks (PSNR, dB): each image's layers end exactly where it first reaches each
#: mark (:func:`quality_targets`), so a goal in dB never pays for the overshoot of a fixed byte
#: ladder. The levels operators name (25 recognisable, 30 good, 35 detailed) and 40 for the
#: rest; marks an image already reaches at an earlier layer are merged. Every layer below a mark
#: costs packet headers (one per precinct), so the marks are sparse: a 20 dB preview mark costs
#: 2 % at 30 dB and 28 % at 25 dB, 27.5 and 32.5 dB more another 2 % at 30 dB (measured,
#: docs/imagery.md). A deployment that sends a cheap preview of every frame adds 20 (the demo does).
DEFAULT_LAYER_PSNR: tuple[float, ...] = (25.0, 30.0, 35.0, 40.0)
#: A quality layer's target is narrowed until its image is at most this far above its mark.
QUALITY_TOLERANCE_DB = 0.06
#: The largest body a quality layer may take (a mark not reached within it is dropped).
QUALITY_CAP_BYTES = 65536
#: Default precinct size (samples, at every resolution): a 640 x 480 image has 6 precincts at
#: full resolution and 2 at half resolution, so a quarter-frame region needs about a third of
#: the full-resolution packets.
DEFAULT_PRECINCTS = 256

_SOT_LEN = 12
_SOD = b"\xff\x93"
_EOC = b"\xff\xd9"


@persistent("imagery.CodingParams")
@dataclass(frozen=True)
class CodingParams:
    """How the vehicle encodes images (all configurable; defaults measured, see ``docs/imagery.md``).

    ``layer_psnr`` are quality marks (dB): each image's layers end at the fewest body bytes that
    reach each mark (the default; None = the default marks unless ``layer_bytes`` is given, an
    empty tuple = fixed byte layers). ``layer_bytes`` are cumulative targets for the *body*
    (packet data) at the end of each quality layer, used when there are no quality marks;
    ``max_size`` bounds the larger side (images are reduced by whole factors with
    a box filter until they fit); ``grey`` turns colour input into BT.601 luma."""

    progression: str = "LRCP"
    resolutions: int = 7
    layer_bytes: tuple[int, ...] = DEFAULT_LAYER_BYTES
    irreversible: bool = True
    grey: bool = True
    max_size: int = 1024
    precincts: int = DEFAULT_PRECINCTS
    layer_psnr: tuple[float, ...] | None = None
    #: with quality marks, end each layer at the fewest bytes that still reach its mark, inside
    #: a coding pass if need be (:mod:`.tighten`); false: where OpenJPEG ends it
    tighten: bool = True

    def __post_init__(self) -> None:
        if self.progression not in PROGRESSIONS:
            raise ConfigError(f"progression must be one of {PROGRESSIONS}, got {self.progression!r}")
        if not 1 <= self.resolutions <= MAX_RESOLUTIONS:
            raise ConfigError(f"resolutions must be in 1..{MAX_RESOLUTIONS}, got {self.resolutions}")
        lb = tuple(int(b) for b in self.layer_bytes)
        if not 1 <= len(lb) <= MAX_LAYERS:
            raise ConfigError(f"1..{MAX_LAYERS} layers, got {len(lb)}")
        if any(b <= 0 for b in lb) or any(b2 <= b1 for b1, b2 in itertools.pairwise(lb)):
            raise ConfigError(f"layer_bytes must be positive and strictly increasing, got {lb}")
        if lb[-1] > MAX_BODY_BYTES // 2:
            raise ConfigError(f"the last layer target {lb[-1]} B is too large")
        object.__setattr__(self, "layer_bytes", lb)
        if not 8 <= self.max_size <= 4096:
            raise ConfigError(f"max_size must be in 8..4096, got {self.max_size}")
        if self.precincts not in PRECINCTS:
            raise ConfigError(f"precincts must be one of {PRECINCTS} (0 = none), got {self.precincts}")
        if self.precincts and self.progression not in ("LRCP", "RLCP"):
            raise ConfigError(f"precincts need progression LRCP or RLCP, not {self.progression}")
        marks = self.layer_psnr
        if marks is None:
            marks = DEFAULT_LAYER_PSNR if lb == DEFAULT_LAYER_BYTES else ()
        try:
            mk = tuple(float(m) for m in marks)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"layer_psnr must be numbers (dB): {exc}") from None
        if len(mk) > MAX_LAYERS:
            raise ConfigError(f"at most {MAX_LAYERS} quality marks, got {len(mk)}")
        if any(not 10.0 <= m <= 60.0 for m in mk) or any(b <= a for a, b in itertools.pairwise(mk)):
            raise ConfigError(f"layer_psnr must be strictly increasing dB values in 10..60, got {mk}")
        object.__setattr__(self, "layer_psnr", mk)

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | None) -> CodingParams:
        """Build from a plain mapping (keys as the field names); unknown keys are ignored."""
        if not config:
            return cls()
        kw: dict[str, Any] = {}
        for key in ("progression", "resolutions", "layer_bytes", "irreversible", "grey", "max_size",
                    "precincts", "layer_psnr", "tighten"):
            if key in config:
                kw[key] = config[key]
        try:
            if "layer_bytes" in kw:
                kw["layer_bytes"] = tuple(int(b) for b in kw["layer_bytes"])
            if "resolutions" in kw:
                kw["resolutions"] = int(kw["resolutions"])
            if "max_size" in kw:
                kw["max_size"] = int(kw["max_size"])
            if "precincts" in kw:
                kw["precincts"] = int(kw["precincts"] or 0)
            if "layer_psnr" in kw:
                v = kw["layer_psnr"]
                kw["layer_psnr"] = None if v is None else () if v in ("", "none", False) else tuple(
                    float(m) for m in v)
            if "progression" in kw:
                kw["progression"] = str(kw["progression"]).upper()
            if "tighten" in kw and not isinstance(kw["tighten"], bool):
                raise ConfigError(f"tighten must be true or false, got {kw['tighten']!r}")
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"invalid coding parameter: {exc}") from exc
        return cls(**kw)


def region_packets(sp: StreamParams, width: int, height: int, box: tuple[int, int, int, int],
                   margin: int = 8) -> npt.NDArray[np.bool_]:
    """Which packets (codestream order) hold wavelet coefficients that shape the pixels of
    ``box`` = (x0, y0, x1, y1) (x1, y1 exclusive): the packets of every precinct that meets the
    box, mapped to each resolution and widened by ``margin`` samples there (the 9/7 filters'
    reach). Without precincts, every packet."""
    order = packet_order(sp, width, height)
    if not sp.precincts:
        return np.ones(len(order), bool)
    x0, y0, x1, y1 = box
    grid = sp.precinct_grid(width, height)
    keep: dict[int, set[int]] = {}
    for r, (nx, ny) in enumerate(grid):
        s = 1 << (sp.resolutions - 1 - r)
        lo_x, hi_x = x0 // s - margin, -(-x1 // s) + margin
        lo_y, hi_y = y0 // s - margin, -(-y1 // s) + margin
        p = sp.precincts
        cols = [i for i in range(nx) if i * p < hi_x and (i + 1) * p > lo_x]
        rows = [j for j in range(ny) if j * p < hi_y and (j + 1) * p > lo_y]
        keep[r] = {j * nx + i for j in rows for i in cols}
    return np.array([int(pr) in keep[int(r)] for _l, r, _c, pr in order], bool)


def to_grey(img: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """BT.601 luma rounded to uint8 (OpenCV's weights); grey input is returned as uint8."""
    a = np.asarray(img)
    if a.ndim == 2:
        return _as_u8(a)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        rgb = _as_u8(a[..., :3]).astype(np.float64)
        y = rgb @ np.array([0.299, 0.587, 0.114])
        return _u8(np.clip(np.rint(y), 0, 255))
    raise ConfigError(f"expected an (H, W) or (H, W, 3) image, got shape {a.shape}")


def _as_u8(a: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.uint16:
        return (a >> 8).astype(np.uint8)
    if np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)):
            raise ConfigError("image contains NaN or infinite values")
        hi = 1.0 if float(a.max(initial=0.0)) <= 1.0 else 255.0
        return _u8(np.clip(np.rint(a * (255.0 / hi)), 0, 255))
    if np.issubdtype(a.dtype, np.integer):
        return _u8(np.clip(a, 0, 255))
    raise ConfigError(f"unsupported image dtype {a.dtype}")


def _reduce(img: npt.NDArray[np.uint8], max_size: int) -> npt.NDArray[np.uint8]:
    """Shrink by the smallest whole factor that fits ``max_size`` (box filter, vectorised)."""
    h, w = img.shape[:2]
    f = 1
    while max(h, w) > max_size * f:
        f += 1
    if f == 1:
        return img
    h2, w2 = h // f, w // f
    a = img[: h2 * f, : w2 * f].astype(np.float64)
    shape = (h2, f, w2, f, *a.shape[2:])
    return _u8(np.clip(np.rint(a.reshape(shape).mean(axis=(1, 3))), 0, 255))


@persistent("imagery.Encoded")
@dataclass(frozen=True)
class Encoded:
    """An encoded image: its body (packet data) and where each packet starts in it."""

    body: bytes
    packet_starts: npt.NDArray[np.int64]
    params: int
    width: int
    height: int
    grey: bool
    image: npt.NDArray[np.uint8] = field(repr=False)

    @property
    def stream(self) -> StreamParams:
        return parse_params(self.params)

    def layer_end(self, k: int) -> int:
        """Body bytes needed for the first ``k`` layers (whole packets)."""
        sp = self.stream
        if k <= 0:
            return 0
        if k >= sp.layers:
            return len(self.body)
        order = packet_order(sp, self.width, self.height)
        last = int(np.nonzero(order[:, 0] < k)[0].max())
        return packet_end(self.packet_starts, len(self.body), last)


def packet_end(starts: npt.NDArray[np.int64], total: int, index: int) -> int:
    return int(starts[index + 1]) if index + 1 < len(starts) else total


def _feasible_resolutions(h: int, w: int, wanted: int) -> int:
    r = wanted
    while r > 1 and min(h, w) < (1 << (r - 1)) * 2:
        r -= 1
    return r


_tmpdir: tempfile.TemporaryDirectory[str] | None = None


#: where the scratch directory goes when it can: memory (Linux), not a disk's journal
_RAM_DIR = "/dev/shm"


def _scratch() -> str:
    """A private scratch directory for glymur, which reads and writes files only: in
    :data:`_RAM_DIR` where there is one to write to (each encode and decode writes, reads and
    removes a file; a calibration makes about a hundred), else the system's temporary directory."""
    global _tmpdir
    if _tmpdir is None:
        ram = _RAM_DIR if os.path.isdir(_RAM_DIR) and os.access(_RAM_DIR, os.W_OK | os.X_OK) else None
        _tmpdir = tempfile.TemporaryDirectory(prefix="coex-imagery-", dir=ram)
    return _tmpdir.name


_THREADS_SET = False


def set_threads(n: int) -> None:
    """OpenJPEG threads for this process's encodes (glymur's ``lib.num_threads``): 0 codes in
    the caller's thread (the default), more split each image's code-blocks over that many
    threads. The bytes are the same either way; more threads only help while cores are idle (a
    single ``coex demo``), not where every core runs a dive (a sweep). Decodes always run in the
    caller's thread (:func:`decode_codestream`)."""
    global _THREADS_SET
    import glymur

    if n < 0:
        raise ConfigError(f"threads must be >= 0, got {n}")
    _THREADS_SET = True
    if glymur.get_option("lib.num_threads") != n:
        try:
            glymur.set_option("lib.num_threads", n)
        except RuntimeError:  # an OpenJPEG without thread support codes in the caller's thread
            pass


def _glymur() -> Any:
    """glymur, set once to code in the caller's thread: its default (``lib.num_threads`` 1)
    hands every encode and decode to a thread pool of one, made and joined each time, which
    costs CPU and, on a loaded machine, waits (the bytes are the same either way)."""
    global _THREADS_SET
    import glymur

    if not _THREADS_SET:
        _THREADS_SET = True
        if glymur.get_option("lib.num_threads") == 1:
            try:
                glymur.set_option("lib.num_threads", 0)
            except RuntimeError:  # an OpenJPEG without thread support: nothing to turn off
                pass
    return glymur


def _cratios(raw: int, targets: Sequence[int]) -> list[float]:
    """OpenJPEG's compression ratios for cumulative stream targets (bytes) of a ``raw``-byte image."""
    cratios = [max(raw / t, 1.0001) for t in targets]
    for i in range(1, len(cratios)):  # must strictly decrease
        cratios[i] = min(cratios[i], cratios[i - 1] * 0.999)
    return cratios


def rate_limits(raw: int, targets: Sequence[int], sot: int) -> tuple[int, ...]:
    """The byte limit OpenJPEG 2.5's rate control gives each layer's packets (all layers up to
    it) for these cumulative stream ``targets`` of an image of ``raw`` 8-bit samples whose
    main header (with OpenJPEG's COM) ends at ``sot``: its ``opj_j2k_update_rates`` in the same
    single-precision steps (the ratio to bytes, less the header; the first layer at least 30,
    each later one at least 10 above the one before or else 20 above it, the last 2 less) and
    ``ceil``. Two encodes of an image with the same limits are the same codestream; the packets
    of the last layer are the fewest bytes within its limit that OpenJPEG's bisection reaches,
    so an encode whose packets come to ``n`` bytes is also what every limit from ``n`` up to its
    own gives (:class:`_Trials`)."""
    f32 = np.float32
    rates = [f32(float(raw * 8) / float(f32(f32(c) * f32(8.0)))) for c in _cratios(raw, targets)]
    head = f32(sot)
    rates[0] = max(f32(rates[0] - head), f32(30.0))
    last = len(rates) - 1
    for k in range(1, len(rates)):
        rates[k] = f32(rates[k] - (head if k < last else f32(head + f32(2.0))))
        if rates[k] < rates[k - 1] + f32(10.0):
            rates[k] = f32(rates[k - 1] + f32(20.0))
    return tuple(int(np.ceil(r)) for r in rates)


def _write_j2k(path: str, data: npt.NDArray[np.uint8], sp: StreamParams, targets: Sequence[int], plt: bool) -> bytes:
    glymur = _glymur()
    cratios = _cratios(data.size, targets)
    kwargs: dict[str, Any] = dict(
        data=data, numres=sp.resolutions, cratios=cratios, prog=sp.progression, irreversible=sp.irreversible
    )
    if plt:
        kwargs["plt"] = True
    if sp.precincts:
        kwargs["psizes"] = [(sp.precincts, sp.precincts)] * sp.resolutions
    if sp.colour:
        kwargs["mct"] = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        glymur.Jp2k(path, **kwargs)
    with open(path, "rb") as fh:
        out = fh.read()
    os.unlink(path)
    return out


def _markers(cs: bytes, start: int, stop_marker: int) -> tuple[dict[int, list[tuple[int, int]]], int]:
    """Walk marker segments from ``start`` until ``stop_marker``; return {marker: [(pos, end)]}, pos."""
    found: dict[int, list[tuple[int, int]]] = {}
    pos = start
    while pos + 4 <= len(cs):
        marker = int.from_bytes(cs[pos:pos + 2], "big")
        if marker == stop_marker:
            return found, pos
        if marker >> 8 != 0xFF:
            raise ValueError(f"not a marker at {pos}")
        length = int.from_bytes(cs[pos + 2:pos + 4], "big")
        found.setdefault(marker, []).append((pos, pos + 2 + length))
        pos += 2 + length
    raise ValueError(f"marker {stop_marker:#x} not found")


def _split(cs: bytes) -> tuple[bytes, int, int, int, list[int]]:
    """(main header without COM, SOT position, body start, body end, packet lengths from PLT)."""
    segs, sot = _markers(cs, 2, 0xFF90)
    header = bytearray(cs[:sot])
    for pos, end in sorted(segs.get(0xFF64, []), reverse=True):  # strip COM
        del header[pos:end]
    psot = int.from_bytes(cs[sot + 6:sot + 10], "big")
    tsegs, sod = _markers(cs, sot + _SOT_LEN, 0xFF93)
    lengths: list[int] = []
    for pos, end in tsegs.get(0xFF58, []):
        seg = cs[pos + 5:end]  # skip marker, Lplt, Zplt
        v = 0
        for b in seg:
            v = (v << 7) | (b & 0x7F)
            if not b & 0x80:
                lengths.append(v)
                v = 0
    body_end = sot + psot if psot else len(cs) - 2
    return bytes(header), sot, sod + 2, body_end, lengths


def main_header(params: int, width: int, height: int) -> bytes:
    """The JPEG 2000 main header (SOC .. before SOT, no COM) for these parameters and size,
    rebuilt by encoding an all-zero image. Raises :class:`DecodeError` for impossible values."""
    return _main_header(params, width, height)[0]


@functools.lru_cache(maxsize=32)
def _main_header(params: int, width: int, height: int) -> tuple[bytes, int]:
    """:func:`main_header` and where OpenJPEG's SOT follows it (its COM included)."""
    sp = parse_params(params)
    if not (1 <= width <= 4096 and 1 <= height <= 4096):
        raise DecodeError(f"image size {width}x{height} out of range")
    if _feasible_resolutions(height, width, sp.resolutions) != sp.resolutions:
        raise DecodeError(f"{sp.resolutions} resolutions impossible for {width}x{height}")
    shape: tuple[int, ...] = (height, width, 3) if sp.colour else (height, width)
    dummy = np.zeros(shape, np.uint8)
    targets = [1000 * (i + 1) for i in range(sp.layers)]
    path = os.path.join(_scratch(), "hdr.j2k")
    cs = _write_j2k(path, dummy, sp, targets, plt=False)
    header, sot, *_ = _split(cs)
    return header, sot


def _stream_targets(code: int, width: int, height: int, targets: Sequence[int]) -> list[int]:
    """Cumulative body targets as OpenJPEG's rate control counts them (with its headers)."""
    overhead = len(main_header(code, width, height)) + 39 + _SOT_LEN + 2  # its COM and SOT/SOD
    return [overhead + b for b in targets]


def _encode_body(data: npt.NDArray[np.uint8], code: int, targets: Sequence[int]) -> tuple[bytes, list[int]]:
    """Encode with these parameters and cumulative body targets: (body, packet lengths)."""
    sp = parse_params(code)
    h, w = data.shape[:2]
    hdr = main_header(code, w, h)
    path = os.path.join(_scratch(), "enc.j2k")
    cs = _write_j2k(path, data, sp, _stream_targets(code, w, h, targets), plt=True)
    header, _sot, start, end, lengths = _split(cs)
    body = cs[start:end]
    if header != hdr:
        raise AssertionError("OpenJPEG wrote a main header that differs from the rebuilt one")
    if len(lengths) != sp.n_packets(w, h) or sum(lengths) != len(body):
        raise AssertionError(f"PLT gives {len(lengths)} packets / {sum(lengths)} B, expected "
                             f"{sp.n_packets(w, h)} / {len(body)}")
    return body, lengths


def layer_psnrs(data: npt.NDArray[np.uint8], code: int, body: bytes, lengths: Sequence[int],
                last_only: bool = False, base: npt.NDArray[np.uint8] | None = None,
                reference: npt.NDArray[np.uint8] | None = None) -> list[float]:
    """The PSNR (dB, against ``data``) of the image decoded from each layer prefix (only the
    whole body with ``last_only``). With ``base``, ``data`` is a residual (:func:`residual`):
    the PSNR is that of ``add_residual(base, decoded)`` against ``reference``."""
    sp = parse_params(code)
    h, w = data.shape[:2]
    layer_of = packet_order(sp, w, h)[:, 0]
    ends = np.cumsum(lengths)
    starts = ends - np.asarray(lengths)
    quality = _quality(data, base, reference)
    out = []
    for k in range(sp.layers - 1 if last_only else 0, sp.layers):
        pk = [body[int(a):int(b)] if layer_of[i] <= k else None
              for i, (a, b) in enumerate(zip(starts, ends, strict=True))]
        out.append(quality(code, pk))
    return out


def _quality(data: npt.NDArray[np.uint8], base: npt.NDArray[np.uint8] | None = None,
             reference: npt.NDArray[np.uint8] | None = None) -> Callable[[int, Sequence[bytes | None]], float]:
    """The PSNR (dB) of the image decoded from packets of ``data``'s encode (a params code and
    the packets), against ``data``; with ``base``, ``data`` is a residual (:func:`residual`): the
    PSNR is that of ``add_residual(base, decoded)`` against ``reference``."""
    h, w = data.shape[:2]
    known: dict[bytes, float] = {}  # the same packets decode to the same image: decoded once

    def quality(code: int, packets: Sequence[bytes | None]) -> float:
        digest = hashlib.blake2b(code.to_bytes(4, "big"), digest_size=16)
        for p in packets:
            digest.update(b"\x00" if p is None else len(p).to_bytes(4, "big") + b"\x01")
            if p:
                digest.update(p)
        key = digest.digest()
        q = known.get(key)
        if q is None:
            decoded = decode_packets(code, w, h, packets)
            if base is None:
                q = psnr(decoded, data)
            else:
                q = psnr(add_residual(base, decoded), data if reference is None else reference)
            known[key] = q
        return q

    return quality


def residual(original: npt.NDArray[Any], base: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """What a crop codes (spec/payloads.md 3.7): ``original - base`` offset by 128 and clipped
    to 0..255, for pixels topside already shows as ``base`` (a flat 128 base gives the original)."""
    d = np.asarray(original, np.int16) - np.asarray(base, np.int16) + 128
    return _u8(np.clip(d, 0, 255))


def add_residual(base: npt.NDArray[Any], decoded: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """The pixels a crop shows: ``base + decoded - 128`` clipped to 0..255 (inverse of
    :func:`residual` up to the clipping)."""
    d = np.asarray(base, np.int16) + np.asarray(decoded, np.int16) - 128
    return _u8(np.clip(d, 0, 255))


#: calibrated targets of the last images encoded, by content (an image encoded again, e.g. the
#: same frame for two senders, is not calibrated twice), with the body those targets encode to
#: when a trial made it; bounded
_TARGETS: dict[tuple[Any, ...], tuple[list[int], tuple[bytes, list[int]] | None]] = {}
_TARGETS_MAX = 64


def _digest(a: npt.NDArray[Any] | None) -> bytes:
    return b"" if a is None else hashlib.blake2b(np.ascontiguousarray(a).tobytes(), digest_size=16).digest()


def quality_targets(data: npt.NDArray[np.uint8], cp: CodingParams, resolutions: int,
                    base: npt.NDArray[np.uint8] | None = None,
                    reference: npt.NDArray[np.uint8] | None = None) -> list[int]:
    """The layer targets of :func:`calibrate_quality`, remembered for the last 64 images."""
    return list(_calibrated(data, cp, resolutions, base, reference)[0])


def _calibrated(data: npt.NDArray[np.uint8], cp: CodingParams, resolutions: int,
                base: npt.NDArray[np.uint8] | None, reference: npt.NDArray[np.uint8] | None,
                ) -> tuple[list[int], tuple[bytes, list[int]] | None]:
    key = (_digest(data), data.shape, cp.progression, cp.irreversible, cp.precincts, cp.layer_psnr, resolutions,
           _digest(base), _digest(reference))
    hit = _TARGETS.get(key)
    if hit is None:
        trials = _Trials(data, base, reference)
        targets = _calibrate(trials, cp, resolutions)
        code = params_code(cp.progression, resolutions, len(targets), cp.irreversible, data.ndim == 3, cp.precincts)
        hit = (targets, trials.known(code, targets))
        if len(_TARGETS) >= _TARGETS_MAX:
            del _TARGETS[next(iter(_TARGETS))]
        _TARGETS[key] = hit
    return hit


class _Trials:
    """The trial encodes of one image's calibration, each made once: an encode is known by the
    byte limits OpenJPEG's rate control gives its layers (:func:`rate_limits`). Two targets
    with the same limits, or whose last limit lies between the packet bytes of an encode with
    the same earlier limits and that encode's own last limit, encode to the same body (the
    bisection makes the same choices: every threshold it tries is feasible for both or for
    neither), so such a trial costs neither an encode nor a decode. Its result is what the
    encode would have measured, to the bit; only the work is saved."""

    def __init__(self, data: npt.NDArray[np.uint8], base: npt.NDArray[np.uint8] | None,
                 reference: npt.NDArray[np.uint8] | None) -> None:
        self.data = data
        self.quality = _quality(data, base, reference)
        self.encodes = 0
        self._done: dict[tuple[int, tuple[int, ...]], list[tuple[int, int, float, bytes, list[int]]]] = {}

    def _limits(self, code: int, targets: Sequence[int]) -> tuple[int, ...]:
        h, w = self.data.shape[:2]
        return rate_limits(self.data.size, _stream_targets(code, w, h, targets), _main_header(code, w, h)[1])

    def _find(self, code: int, limits: tuple[int, ...]) -> tuple[int, int, float, bytes, list[int]] | None:
        for made in self._done.get((code, limits[:-1]), ()):
            limit, n = made[0], made[1]
            if limits[-1] == limit or n <= limits[-1] <= limit:
                return made
        return None

    def known(self, code: int, targets: Sequence[int]) -> tuple[bytes, list[int]] | None:
        """The body and packet lengths of these targets if a trial made them, else None."""
        made = self._find(code, self._limits(code, targets))
        return None if made is None else (made[3], list(made[4]))

    def last_quality(self, code: int, targets: Sequence[int]) -> float:
        """The PSNR (dB) of the image decoded from the whole body these targets encode to."""
        limits = self._limits(code, targets)
        made = self._find(code, limits)
        if made is None:
            body, lengths = _encode_body(self.data, code, targets)
            self.encodes += 1
            ends = np.cumsum(lengths)
            q = self.quality(code, [body[int(e) - n:int(e)] for e, n in zip(ends, lengths, strict=True)])
            made = (limits[-1], len(body), q, body, lengths)
            self._done.setdefault((code, limits[:-1]), []).append(made)
        return made[2]

    def layer_qualities(self, code: int, targets: Sequence[int], enough: float) -> list[float]:
        """The PSNR (dB) of each layer prefix of the encode of ``targets``, in order, up to the
        first that reaches ``enough`` (the rest cannot change which layer first reaches a mark
        at or below it)."""
        h, w = self.data.shape[:2]
        body, lengths = _encode_body(self.data, code, targets)
        self.encodes += 1
        sp = parse_params(code)
        layer_of = packet_order(sp, w, h)[:, 0]
        ends = np.cumsum(lengths)
        packets = [body[int(e) - n:int(e)] for e, n in zip(ends, lengths, strict=True)]
        out: list[float] = []
        for k in range(sp.layers):
            out.append(self.quality(code, [p if layer_of[i] <= k else None for i, p in enumerate(packets)]))
            if out[-1] >= enough:
                break
        return out


def calibrate_quality(data: npt.NDArray[np.uint8], cp: CodingParams, resolutions: int,
                      base: npt.NDArray[np.uint8] | None = None,
                      reference: npt.NDArray[np.uint8] | None = None) -> list[int]:
    """Cumulative body targets that end a layer at the fewest bytes reaching each quality mark
    (with ``base``, the quality of a residual's composite against ``reference``, as
    :func:`layer_psnrs`).

    OpenJPEG allocates layers in order (a layer's bytes do not depend on later layers), so the
    marks are calibrated in order: one probe encode (24 layers, 16 B to
    :data:`QUALITY_CAP_BYTES`) brackets every mark, then each mark's target is narrowed
    (interpolation in log bytes, kept inside the bracket) until its image is at most
    :data:`QUALITY_TOLERANCE_DB` above the mark, with the earlier layers fixed, each trial one
    encode and one decode unless an earlier trial already tells its body (:class:`_Trials`).
    Marks not reached within the cap, or already reached by the layer before, are dropped.
    Deterministic for a given image."""
    return _calibrate(_Trials(data, base, reference), cp, resolutions)


def _calibrate(trials: _Trials, cp: CodingParams, resolutions: int, ahead: bool = True) -> list[int]:
    """:func:`calibrate_quality` on ``trials``. With ``ahead``, once a trial leaves the image
    below a mark exactly as the lower end of its bracket left it, the last trial of the run that
    would follow if every one did the same is made first (:func:`_flat_run`): the same search
    and the same targets, fewer encodes (issue 55)."""
    colour = trials.data.ndim == 3
    cap = min(QUALITY_CAP_BYTES, MAX_BODY_BYTES // 2)
    marks = cp.layer_psnr or ()

    def code_for(n: int) -> int:
        return params_code(cp.progression, resolutions, n, cp.irreversible, colour, cp.precincts)

    probe = [int(x) for x in np.unique(np.geomspace(16, cap, 24).astype(np.int64))]
    pq = np.maximum.accumulate(np.asarray(trials.layer_qualities(code_for(len(probe)), probe,
                                                                 max(marks, default=float("inf")))))

    def trial(targets: list[int]) -> float:
        return trials.last_quality(code_for(len(targets)), targets)

    done: list[int] = []
    q_done = 0.0
    for mark in marks:
        if mark > pq[-1]:
            break
        if done and q_done >= mark:
            continue  # the previous layer already reaches it
        i = int(np.searchsorted(pq, mark))
        floor = done[-1] + 1 if done else 1
        # the probe's earlier layers differ from ``done``: its bracket is checked again
        lo, q_lo = float(max(probe[i - 1], floor)) if i else float(floor), q_done
        hi = float(max(probe[i], lo + 1))
        q_hi = trial([*done, int(hi)])
        if lo > floor:
            q_lo = trial([*done, int(lo)])
            if q_lo >= mark:
                lo, q_lo, hi, q_hi = float(floor), q_done, lo, q_lo
        while q_hi < mark and hi < cap:  # earlier layers changed what a target buys: widen
            lo, q_lo, hi = hi, q_hi, min(hi * 2, cap)
            q_hi = trial([*done, int(hi)])
        if q_hi < mark:
            break
        flat = False  # the last trial left the image below the mark exactly as it was
        while q_hi - mark > QUALITY_TOLERANCE_DB and hi > max(lo * 1.01, lo + 2):
            if flat and ahead:  # the trials to come if the image stays as it is, up to one already known
                run = list(itertools.takewhile(
                    lambda t: trials.known(code_for(len(done) + 1), [*done, t]) is None,
                    _flat_run(lo, q_lo, hi, q_hi, mark)))
                if len(run) > 1:  # the last first: if it is the lower end's body, so are the others
                    trial([*done, run[-1]])
            t = _next_target(lo, q_lo, hi, q_hi, mark)
            q = trial([*done, t])
            if q >= mark:
                hi, q_hi, flat = float(t), q, False
            else:
                lo, q_lo, flat = float(t), q, q == q_lo
        done.append(int(hi))
        q_done = q_hi
    return done or [probe[-1]]


def _next_target(lo: float, q_lo: float, hi: float, q_hi: float, mark: float) -> int:
    """The calibration's next trial target between ``lo`` (below the mark) and ``hi`` (at or
    above it): interpolation in log bytes, kept inside the bracket."""
    f = (mark - q_lo) / (q_hi - q_lo) if q_hi > q_lo else 0.5
    g = float(np.exp(np.log(lo) + min(max(f, 0.1), 0.9) * (np.log(hi) - np.log(lo))))
    return min(max(round(g), int(lo) + 1), int(hi) - 1)


def _flat_run(lo: float, q_lo: float, hi: float, q_hi: float, mark: float) -> list[int]:
    """The targets the calibration tries next if every one of them leaves the quality at
    ``q_lo`` (each becomes the new lower end, nothing else changes), up to where its bracket is
    narrow enough to stop. :func:`_calibrate` runs the last one first: when it gives the lower
    end's body, every earlier one lies between that body's bytes and its byte limit, so each is
    that body without an encode (:class:`_Trials`); the search and its result stay the same."""
    out: list[int] = []
    while hi > max(lo * 1.01, lo + 2):
        t = _next_target(lo, q_lo, hi, q_hi, mark)
        out.append(t)
        lo = float(t)
    return out


def encode_image(image: npt.NDArray[Any], params: CodingParams | None = None) -> Encoded:
    """Encode an image; keep the body and the packet boundaries (from a PLT marker)."""
    cp = params or CodingParams()
    a = np.asarray(image)
    if a.ndim not in (2, 3) or a.size == 0:
        raise ConfigError(f"expected a non-empty (H, W) or (H, W, 3) image, got shape {a.shape}")
    if cp.grey or a.ndim == 2:
        data: npt.NDArray[np.uint8] = to_grey(a)
    else:
        if a.shape[2] not in (3, 4):
            raise ConfigError(f"colour images need 3 channels, got {a.shape[2]}")
        data = np.ascontiguousarray(_as_u8(a[..., :3]))
    return _encode(_reduce(data, cp.max_size), cp)


def encode_residual(original: npt.NDArray[Any], base: npt.NDArray[Any], params: CodingParams) -> Encoded:
    """Encode the difference of ``original`` to ``base`` (:func:`residual`; both ``(H, W)`` or
    both ``(H, W, 3)`` uint8, as the receiver shows them): a crop's codestream (spec/payloads.md
    3.7). Quality marks are met by the composite :func:`add_residual` of ``base`` and the
    decoded residual, against ``original``. ``Encoded.image`` is the residual."""
    o, b = np.asarray(original), np.asarray(base)
    if o.shape != b.shape or o.dtype != np.uint8 or b.dtype != np.uint8 or o.ndim not in (2, 3):
        raise ConfigError(f"a residual needs two uint8 images of one shape, got {o.shape} {o.dtype} and "
                          f"{b.shape} {b.dtype}")
    if o.ndim == 3 and (o.shape[2] != 3 or params.grey):
        raise ConfigError("a colour residual needs 3 channels and grey=False")
    return _encode(residual(o, b), params, b, o)


def _encode(data: npt.NDArray[np.uint8], cp: CodingParams, base: npt.NDArray[np.uint8] | None = None,
            reference: npt.NDArray[np.uint8] | None = None) -> Encoded:
    h, w = data.shape[:2]
    if min(h, w) < 8:
        raise ConfigError(f"image {w}x{h} is too small (8 px minimum)")
    colour = data.ndim == 3
    res = _feasible_resolutions(h, w, cp.resolutions)
    made: tuple[bytes, list[int]] | None = None
    if cp.layer_psnr:
        targets, made = _calibrated(data, cp, res, base, reference)
        targets = list(targets)
    else:
        targets = list(cp.layer_bytes)
    code = params_code(cp.progression, res, len(targets), cp.irreversible, colour, cp.precincts)
    body, lengths = made if made is not None else _encode_body(data, code, targets)
    lengths = list(lengths)
    if cp.layer_psnr and cp.tighten:
        body, lengths = tighten(code, w, h, body, cp.layer_psnr, _quality(data, base, reference),
                                _digest(data) + _digest(base) + _digest(reference))
    starts = np.concatenate([[0], np.cumsum(lengths[:-1], dtype=np.int64)]).astype(np.int64)
    return Encoded(body, starts, code, w, h, not colour, data)


def assemble(
    params: int,
    width: int,
    height: int,
    packets: Sequence[bytes | None],
) -> tuple[bytes, int]:
    """A decodable codestream from whole packets (``None`` = missing or incomplete).

    Returns ``(codestream, used)``: ``used`` counts the real packets kept. Trailing missing
    packets are dropped; inner ones, and every later packet of the same resolution, component
    and precinct, become empty packets."""
    sp = parse_params(params)
    n = sp.n_packets(width, height)
    if len(packets) > n:
        raise DecodeError(f"{len(packets)} packets for a stream of {n}")
    order = packet_order(sp, width, height)
    last = max((i for i, p in enumerate(packets) if p is not None), default=-1)
    poisoned: set[tuple[int, int, int]] = set()
    parts = [main_header(params, width, height), b"\xff\x90\x00\x0a\x00\x00\x00\x00\x00\x00\x00\x01", _SOD]
    used = 0
    for i in range(last + 1):
        key = (int(order[i, 1]), int(order[i, 2]), int(order[i, 3]))
        p = packets[i]
        if p is None or key in poisoned:
            poisoned.add(key)
            parts.append(b"\x00")
        else:
            parts.append(p)
            used += 1
    parts.append(_EOC)
    return b"".join(parts), used


def decode_codestream(cs: bytes, reduce: int = 0) -> npt.NDArray[np.uint8]:
    """Decode a codestream with OpenJPEG (strict mode); ``reduce`` halves the size that many times.

    Always in the caller's thread, whatever :func:`set_threads` gave the encodes: a decode of
    these images takes a few milliseconds, and OpenJPEG makes and joins its pool of threads for
    each one, which cost 50 % more CPU than the decode saved (measured on a 640 x 480 frame,
    2.9 against 4.6 ms of CPU, issue 55); the pixels are the same either way. A whole-size
    decode calls OpenJPEG through glymur's bindings directly (:func:`_decode_file`: the calls
    glymur's ``Jp2k`` reader makes, without its parse of the file's boxes and marker segments
    in Python, a fifth of a decode's time; the same pixels, tested)."""
    glymur = _glymur()
    path = os.path.join(_scratch(), f"dec-{threading.get_ident()}.j2k")
    with open(path, "wb") as fh:
        fh.write(cs)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if not reduce:
                out = _decode_file(path)
            else:
                threads = glymur.get_option("lib.num_threads")
                if threads:
                    glymur.set_option("lib.num_threads", 0)
                try:
                    step = 1 << reduce
                    out = glymur.Jp2k(path)[::step, ::step]
                finally:
                    if threads:
                        glymur.set_option("lib.num_threads", threads)
    except Exception as exc:  # OpenJPEG / glymur raise several types for a bad stream
        raise DecodeError(f"JPEG 2000 decode failed: {exc}") from exc
    finally:
        os.unlink(path)
    return np.asarray(out, dtype=np.uint8)


def _decode_file(path: str) -> npt.NDArray[Any]:
    """The whole image of the J2K codestream in ``path``, in the caller's thread: the calls of
    glymur's ``Jp2k(path)[:]`` to OpenJPEG (its bindings, its error and warning handlers,
    default decoder parameters), without its Python parse of the file. Raises what glymur's
    bindings raise for a bad stream."""
    from glymur.lib import openjp2 as opj2

    dparams = opj2.set_default_decoder_parameters()
    dparams.decod_format = opj2.CODEC_J2K
    with contextlib.ExitStack() as stack:
        stream = opj2.stream_create_default_file_stream(path, True)
        stack.callback(opj2.stream_destroy, stream)
        codec = opj2.create_decompress(opj2.CODEC_J2K)
        stack.callback(opj2.destroy_codec, codec)
        opj2.set_error_handler(codec, opj2._ERROR_CALLBACK)
        opj2.set_warning_handler(codec, opj2._WARNING_CALLBACK)
        opj2.set_info_handler(codec, None)
        opj2.setup_decoder(codec, dparams)
        opj2.codec_set_threads(codec, 0)
        raw = opj2.read_header(stream, codec)
        stack.callback(opj2.image_destroy, raw)
        opj2.set_decode_area(codec, raw, 0, 0, 0, 0)
        opj2.decode(codec, stream, raw)
        opj2.end_decompress(codec, stream)
        img = raw.contents
        bands = []
        for k in range(img.numcomps):
            comp = img.comps[k]
            if comp.prec > 8 or comp.sgnd or not comp.w or not comp.h:
                raise DecodeError(f"component {k}: {comp.prec}-bit{' signed' if comp.sgnd else ''} "
                                  f"{comp.w} x {comp.h}, not an 8-bit CoEx image")
            arr = (ctypes.c_int32 * (comp.h * comp.w)).from_address(ctypes.addressof(comp.data.contents))
            bands.append(np.frombuffer(arr, np.int32).astype(np.uint8).reshape(comp.h, comp.w))
        if len(bands) == 1:
            return bands[0]
        if any(b.shape != bands[0].shape for b in bands):
            raise DecodeError("components of different sizes")
        return np.stack(bands, axis=-1)


def decode_packets(params: int, width: int, height: int, packets: Sequence[bytes | None]) -> npt.NDArray[np.uint8]:
    """Decode an image from whole packets (see :func:`assemble`); no packet gives mid-grey."""
    sp = parse_params(params)
    if not any(p is not None for p in packets):
        shape: tuple[int, ...] = (height, width, 3) if sp.colour else (height, width)
        return np.full(shape, 128, np.uint8)
    cs, _ = assemble(params, width, height, packets)
    return decode_codestream(cs)


def split_packets(body: bytes, starts: npt.NDArray[np.int64], upto: int | None = None) -> list[bytes | None]:
    """Packets of a body prefix of ``upto`` bytes (the incomplete last one is ``None``)."""
    n = len(body) if upto is None else upto
    out: list[bytes | None] = []
    for i, s in enumerate(starts):
        e = packet_end(starts, len(body), i)
        if e <= n:
            out.append(body[int(s):e])
        else:
            break
    return out


def psnr(a: npt.NDArray[Any], b: npt.NDArray[Any]) -> float:
    """PSNR in dB of two uint8 images (inf when identical). Two uint8 arrays of one shape take a
    path in integers: their squared differences summed exactly, the same value to the last bit
    as the mean of the differences squared in float64 (every partial sum there is an integer
    below 2**53) in a tenth of the time."""
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype == np.uint8 and b.dtype == np.uint8 and a.shape == b.shape and a.size:
        d = np.subtract(a, b, dtype=np.int16).ravel()
        mse = float(np.einsum("i,i->", d, d, dtype=np.int64)) / d.size
        return float("inf") if mse == 0 else 10.0 * float(np.log10(255.0**2 / mse))
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else 10.0 * float(np.log10(255.0**2 / mse))


def _u8(a: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    out: npt.NDArray[np.uint8] = np.asarray(a).astype(np.uint8)
    return out

"""The time-series wavelet code: blocks, refinement passes and their coefficient bit code.

Pure functions on numpy arrays (no I/O, no clock). Both sides use the same functions, so the
vehicle knows exactly what topside reconstructs and can state the error bound it achieves.

A *block* is ``count`` samples on a regular grid. Its wavelet transform (PyWavelets,
``mode="symmetric"``, deepest level PyWavelets allows, at most :data:`MAX_LEVEL`) is flattened:
approximation first, then details coarse to fine. A *pass* holds integer codes ``q`` for every
flat coefficient; coefficient = ``q * step``. Pass 0 codes the block itself with a coarse step;
pass ``p`` codes the residual left by passes ``0..p-1``. Because the transform is linear the
reconstruction is ``waverec(sum_p q_p * step_p)``.

Coefficient bit code of one chunk (``data``), bits most-significant first:

* ``dense`` (1 bit), ``dpcm`` (1 bit);
* sparse form (``dense`` = 0): ``n`` (13 bits, number of non-zero codes); Rice parameters of
  the zero runs, then of the magnitudes ``|q| - 1``, each ``k`` (5 bits), an escape flag (1 bit)
  and, when set, an escape width ``w`` (6 bits, 1..63); the unary quotients (``v >> k``
  one-bits and a zero; 16 one-bits then a zero mean "escaped") of every run, then of every magnitude; the
  low ``k`` bits of the non-escaped runs, then magnitudes; the escaped runs, then magnitudes, in
  ``w`` bits each; one sign bit per non-zero code (1 = negative);
* dense form (``dense`` = 1): one Rice parameter set as above, then every code zigzag-mapped
  (0, -1, 1, -2 ... to 0, 1, 2, 3 ...) as unary quotients, low bits, escapes;
* zero bits up to a whole byte (they must be zero, and fewer than 8).

With ``dpcm`` set (in a wavelet chunk starting at coefficient 0, or in any chunk of a samples
pass, where it covers every code) the approximation codes are sent as differences from the
previous code. Separate unary and fixed-width sections make encoding and decoding a handful of
vectorised numpy operations.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import pywt

from coex import persistent
from coex.messages import Wavelet

__all__ = [
    "CODE_BIAS",
    "MAX_LEVEL",
    "Layout",
    "Pass",
    "analyse",
    "ceil_code",
    "code_value",
    "decode_codes",
    "encode_codes",
    "floor_code",
    "layout",
    "make_pass",
    "noise_sigma",
    "split_pass",
    "synthesise",
]

WAVELET_NAMES: dict[Wavelet, str] = {
    Wavelet.HAAR: "haar",
    Wavelet.BIOR22: "bior2.2",
    Wavelet.BIOR44: "bior4.4",
    Wavelet.DB4: "db4",
}
MODE = "symmetric"
MAX_LEVEL = 10
#: code c means the value 2 ** ((c - CODE_BIAS) / CODE_SCALE) (channel units)
CODE_BIAS = 160
CODE_SCALE = 8
_N_BITS = 13
_K_BITS = 5
_W_BITS = 6
_HEADER_BITS = 2 + _N_BITS + 2 * (_K_BITS + 1)
_MAX_K = (1 << _K_BITS) - 1
#: a unary quotient of this many one-bits means: the value is in the escape section
_ESC = 16
#: codes (and magnitudes) are below 2^62, so sums and signs never overflow int64
_MAX_CODE = 1 << 62


def code_value(code: int) -> float:
    """The step or error bound a code stands for."""
    return float(2.0 ** ((int(code) - CODE_BIAS) / CODE_SCALE))


def floor_code(value: float) -> int:
    """The largest code whose value is at most ``value`` (clamped to 0..255)."""
    if value <= 0:
        return 0
    c = math.floor(math.log2(value) * CODE_SCALE + CODE_BIAS + 1e-9)
    while c > 0 and code_value(c) > value:
        c -= 1
    return int(min(max(c, 0), 255))


def ceil_code(value: float) -> int:
    """The smallest code whose value is at least ``value`` (clamped to 0..255)."""
    if value <= code_value(0):
        return 0
    c = math.ceil(math.log2(value) * CODE_SCALE + CODE_BIAS - 1e-9)
    while c < 255 and code_value(c) < value:
        c += 1
    return int(min(max(c, 0), 255))


@persistent("timeseries.Layout")
@dataclass(frozen=True)
class Layout:
    """Coefficient layout of a block: decomposition level, band lengths, flat size."""

    count: int
    wavelet: Wavelet
    level: int
    lengths: tuple[int, ...]

    @property
    def total(self) -> int:
        return sum(self.lengths)

    @property
    def n_approx(self) -> int:
        return self.lengths[0]


@functools.lru_cache(maxsize=256)
def layout(count: int, wavelet: Wavelet) -> Layout:
    """The coefficient layout of a ``count``-sample block."""
    name = WAVELET_NAMES[Wavelet(wavelet)]
    level = min(MAX_LEVEL, pywt.dwt_max_level(count, pywt.Wavelet(name).dec_len))
    if level <= 0:
        return Layout(count, Wavelet(wavelet), 0, (count,))
    coeffs = pywt.wavedec(np.zeros(count), name, mode=MODE, level=level)
    return Layout(count, Wavelet(wavelet), level, tuple(len(c) for c in coeffs))


def analyse(x: np.ndarray, wavelet: Wavelet) -> np.ndarray:
    """Flat wavelet coefficients of ``x`` (last axis); 2-D input gives one row per series."""
    lay = layout(x.shape[-1], wavelet)
    if lay.level == 0:
        return np.array(x, dtype=np.float64)
    coeffs = pywt.wavedec(x, WAVELET_NAMES[lay.wavelet], mode=MODE, level=lay.level, axis=-1)
    flat: np.ndarray = np.concatenate(coeffs, axis=-1)
    return flat


def synthesise(flat: np.ndarray, count: int, wavelet: Wavelet) -> np.ndarray:
    """Samples from flat coefficients (last axis), the inverse of :func:`analyse`."""
    lay = layout(count, wavelet)
    if lay.level == 0:
        return np.array(flat[..., :count], dtype=np.float64)
    bounds = np.cumsum(lay.lengths)[:-1]
    coeffs = np.split(flat, bounds, axis=-1)
    out = pywt.waverec(coeffs, WAVELET_NAMES[lay.wavelet], mode=MODE, axis=-1)
    return np.asarray(out[..., :count], dtype=np.float64)


def noise_sigma(x: np.ndarray, wavelet: Wavelet) -> float:
    """Robust noise estimate: median absolute finest detail / 0.6745 (Donoho)."""
    lay = layout(x.shape[-1], wavelet)
    if lay.level == 0 or x.size < 4:
        return 0.0
    finest = analyse(x, wavelet)[lay.total - lay.lengths[-1]:]
    return float(np.median(np.abs(finest)) / 0.6745)


# -------------------------------------------------------------------------- passes


@persistent("timeseries.Pass")
@dataclass(frozen=True)
class Pass:
    """One refinement pass of a block: step code, integer codes, achieved error bound code.

    ``samples`` passes code the residual samples themselves (one code per sample) instead of
    wavelet coefficients: near the noise level that is cheaper, and the error is exactly at
    most half the step."""

    step: int
    codes: np.ndarray
    error: int
    max_error: float
    samples: bool = False

    def coefficients(self) -> np.ndarray:
        return self.codes.astype(np.float64) * code_value(self.step)


def _quantise(w: np.ndarray, steps: np.ndarray) -> np.ndarray:
    q: np.ndarray = np.rint(w[None, :] / steps[:, None])
    return q


def make_pass(x: np.ndarray, recon: np.ndarray, target: float, wavelet: Wavelet) -> tuple[Pass, np.ndarray]:
    """The cheapest uniform-step pass that brings ``max |x - recon'|`` to at most ``target``.

    Returns the pass and the new reconstruction. Candidate steps are tried 48 at a time (one
    vectorised inverse transform); the largest step meeting the target wins, which also keeps
    the codes smallest. If no step meets it (target below float precision) the finest step is
    used and the bound states what was achieved. A samples pass (the residual rounded to twice
    the target, difference-coded) replaces it when that codes smaller."""
    count = x.shape[-1]
    resid = x - recon
    w = analyse(resid, wavelet)
    top = min(255, ceil_code(max(target, code_value(0)) * 4.0) + 8)
    best: tuple[int, np.ndarray, np.ndarray, float] | None = None
    while top >= 0:
        codes = np.arange(top, max(top - 48, -1), -1)
        steps = 2.0 ** ((codes - CODE_BIAS) / CODE_SCALE)
        q = _quantise(w, steps)
        rec = synthesise(q * steps[:, None], count, wavelet)
        err = np.max(np.abs(resid[None, :] - rec), axis=1)
        ok = np.flatnonzero(err <= target)
        if ok.size:
            i = int(ok[0])
            best = (int(codes[i]), q[i], rec[i], float(err[i]))
            break
        if codes[-1] == 0:
            i = int(np.argmin(err))
            best = (int(codes[i]), q[i], rec[i], float(err[i]))
            break
        top = int(codes[-1]) - 1
    assert best is not None
    step, q_best, rec_best, _ = best
    samples = False
    # the same target coded sample by sample: the residual rounded to a step of twice the target
    s_code = floor_code(2 * target)
    s_step = code_value(s_code)
    q_samp = np.rint(resid / s_step)
    n_approx = layout(count, wavelet).n_approx
    if np.max(np.abs(resid - q_samp * s_step), initial=0.0) <= target and \
            coded_bytes(q_samp.astype(np.int64), 0, True) < coded_bytes(q_best.astype(np.int64), n_approx):
        step, q_best, rec_best, samples = s_code, q_samp, q_samp * s_step, True
    new_recon = recon + rec_best
    achieved = float(np.max(np.abs(x - new_recon))) if count else 0.0
    p = Pass(step, q_best.astype(np.int64), ceil_code(achieved), achieved, samples)
    return p, new_recon


# ------------------------------------------------------------------- coefficient code


class CodeError(ValueError):
    """Malformed coefficient data (the caller turns it into its own typed error)."""


def _rice_params(values: np.ndarray) -> tuple[int, int]:
    """Rice parameter ``k`` and escape width ``w`` (0: no escapes) that code ``values`` in the
    fewest bits; a value whose quotient ``v >> k`` reaches :data:`_ESC` is escaped."""
    if values.size == 0:
        return 0, 0
    ks = np.arange(_MAX_K + 1)
    q = values[:, None] >> ks[None, :]
    esc = q >= _ESC
    widths = np.where(esc, _bit_length(values)[:, None], 0).max(axis=0)
    cost = (np.minimum(q, _ESC) + 1).sum(axis=0) + ks * (~esc).sum(axis=0) + widths * esc.sum(axis=0)
    cost = cost + np.where(widths > 0, _W_BITS, 0)
    k = int(np.argmin(cost))
    return k, int(widths[k])


def _rice_k(values: np.ndarray) -> int:
    """Best plain Rice parameter (used by benchmarks for a naive delta code)."""
    if values.size == 0:
        return 0
    ks = np.arange(_MAX_K + 1)
    cost = (values[:, None] >> ks[None, :]).sum(axis=0) + values.size * (ks + 1)
    return int(np.argmin(cost))


def _bit_length(values: np.ndarray) -> np.ndarray:
    out = np.zeros(values.shape, dtype=np.int64)
    v = values.copy()
    for _ in range(64):  # over bit positions, not samples
        nz = v > 0
        if not nz.any():
            break
        out += nz
        v >>= 1
    return out


def _fixed_bits(values: np.ndarray, k: int) -> np.ndarray:
    if k == 0 or values.size == 0:
        return np.zeros(0, dtype=np.uint8)
    shifts = np.arange(k - 1, -1, -1)
    return ((values[:, None] >> shifts[None, :]) & 1).astype(np.uint8).ravel()


def _unary(q: np.ndarray) -> np.ndarray:
    total = int(q.sum() + q.size)
    bits = np.ones(total, dtype=np.uint8)
    bits[np.cumsum(q + 1) - 1] = 0
    return bits


def _uint_bits(value: int, width: int) -> np.ndarray:
    return _fixed_bits(np.array([value], dtype=np.int64), width)


def _rice_sections(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Parameter bits, unary part, low bits of ordinary values, escaped values."""
    k, w = _rice_params(values)
    q = values >> k
    esc = q >= _ESC
    # the escape width is present only when something is escaped
    params = np.concatenate([_uint_bits(k, _K_BITS), np.array([1 if w else 0], dtype=np.uint8),
                             _uint_bits(w, _W_BITS) if w else np.zeros(0, dtype=np.uint8)])
    return params, _unary(np.minimum(q, _ESC)), _fixed_bits(values[~esc], k), _fixed_bits(values[esc], w)


def encode_codes(codes: np.ndarray, n_approx: int = 0, dpcm: bool = False) -> bytes:
    """The bit code of integer codes (one chunk's range): the shorter of the sparse form (zero
    runs and magnitudes) and the dense form (every code zigzag-mapped). ``dpcm``
    difference-codes the first ``n_approx`` codes."""
    v = np.asarray(codes, dtype=np.int64).copy()
    if dpcm and n_approx > 1:
        a = min(n_approx, v.size)
        v[1:a] = np.diff(v[:a])
    sparse = _sparse(v, dpcm)
    if v.size > 8 * len(sparse):
        return sparse  # the dense form needs at least a bit per code
    dense = _dense(v, dpcm)
    return dense if len(dense) < len(sparse) else sparse


def _dense(v: np.ndarray, dpcm: bool) -> bytes:
    z = np.where(v >= 0, 2 * v, -2 * v - 1)
    p, u, low, esc = _rice_sections(z)
    parts = [np.array([1, 1 if dpcm else 0], dtype=np.uint8), p, u, low, esc]
    return np.packbits(np.concatenate(parts)).tobytes()


def _sparse(v: np.ndarray, dpcm: bool) -> bytes:
    nz = np.flatnonzero(v)
    if nz.size >= 1 << _N_BITS:
        raise ValueError("too many non-zero codes for one chunk")
    runs = np.diff(np.concatenate(([-1], nz))) - 1
    vals = v[nz]
    mags = np.abs(vals) - 1
    pr, ur, lr, er = _rice_sections(runs)
    pm, um, lm, em = _rice_sections(mags)
    parts = [np.array([0, 1 if dpcm else 0], dtype=np.uint8), _uint_bits(nz.size, _N_BITS), pr, pm,
             ur, um, lr, lm, er, em, (vals < 0).astype(np.uint8)]
    return np.packbits(np.concatenate(parts)).tobytes()


def encoded_bits(codes: np.ndarray) -> int:
    """Bits :func:`encode_codes` needs (without differences), computed without building them."""
    return 8 * len(encode_codes(codes))


def _read_uint(bits: np.ndarray, pos: int, width: int) -> int:
    v = 0
    for b in bits[pos:pos + width].tolist():  # one header field, at most 13 bits
        v = (v << 1) | b
    return v


def _from_fixed(bits: np.ndarray, n: int, k: int) -> np.ndarray:
    if k == 0 or n == 0:
        return np.zeros(n, dtype=np.int64)
    weights = (1 << np.arange(k - 1, -1, -1)).astype(np.int64)
    out: np.ndarray = (bits.reshape(n, k).astype(np.int64) * weights[None, :]).sum(axis=1)
    return out


def decode_codes(data: bytes, length: int, n_approx: int = 0, allow_dpcm: bool = True) -> np.ndarray:
    """Integer codes of a chunk's range of ``length`` coefficients; raises :class:`CodeError`."""
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8))
    if bits.size < 2 + _K_BITS + 1:
        raise CodeError("coefficient data shorter than its header")
    dense, dpcm = bool(bits[0]), bool(bits[1])
    if dpcm and not allow_dpcm:
        raise CodeError("difference coding in a chunk that does not start at coefficient 0")
    out = _decode_dense(bits, length) if dense else _decode_sparse(bits, length)
    if dpcm and n_approx > 1:
        a = min(n_approx, length)
        out[:a] = np.cumsum(out[:a])
    return out


def _read_params(bits: np.ndarray, pos: int) -> tuple[int, int, int]:
    """Rice parameter, escape width (0 when absent) and the position after them."""
    if pos + _K_BITS + 1 > bits.size:
        raise CodeError("truncated coefficient header")
    k = _read_uint(bits, pos, _K_BITS)
    pos += _K_BITS + 1
    if not bits[pos - 1]:
        return k, 0, pos
    if pos + _W_BITS > bits.size:
        raise CodeError("truncated coefficient header")
    w = _read_uint(bits, pos, _W_BITS)
    if w == 0:
        raise CodeError("escape width 0 is not canonical")
    return k, w, pos + _W_BITS


def _read_rice(bits: np.ndarray, pos: int, n: int, k: int, w: int) -> tuple[np.ndarray, int]:
    """``n`` Rice-with-escape values whose unary part starts at ``pos`` and whose low bits and
    escapes follow it; returns them and the position after them."""
    if n == 0:
        return np.zeros(0, dtype=np.int64), pos
    zeros = np.flatnonzero(bits[pos:] == 0)
    if zeros.size < n:
        raise CodeError("truncated unary section")
    z = zeros[:n]
    q = (np.diff(np.concatenate(([-1], z))) - 1).astype(np.int64)
    if q.max() > _ESC:
        raise CodeError("unary quotient above the escape code")
    pos += int(z[-1]) + 1
    esc = q == _ESC
    ne = int(esc.sum())
    if ne and w == 0:
        raise CodeError("escaped value without an escape width")
    if pos + (n - ne) * k + ne * w > bits.size:
        raise CodeError("truncated fixed-width section")
    out = q << k
    out[~esc] |= _from_fixed(bits[pos:pos + (n - ne) * k], n - ne, k)
    pos += (n - ne) * k
    out[esc] = _from_fixed(bits[pos:pos + ne * w], ne, w)
    return out, pos + ne * w


def _check_padding(bits: np.ndarray, pos: int) -> None:
    pad = bits.size - pos
    if pad < 0 or pad >= 8 or (pad > 0 and bits[pos:].any()):
        raise CodeError("coefficient data is not in canonical form (padding)")


def _decode_dense(bits: np.ndarray, length: int) -> np.ndarray:
    pos = 2
    k, w, pos = _read_params(bits, pos)
    z, pos = _read_rice(bits, pos, length, k, w)
    _check_padding(bits, pos)
    if z.size and z.max() >= _MAX_CODE:
        raise CodeError("code out of range")
    return np.where(z % 2 == 0, z // 2, -(z + 1) // 2)


def _decode_sparse(bits: np.ndarray, length: int) -> np.ndarray:
    if bits.size < _HEADER_BITS:
        raise CodeError("coefficient data shorter than its header")
    pos = 2
    n = _read_uint(bits, pos, _N_BITS)
    pos += _N_BITS
    kr, wr, pos = _read_params(bits, pos)
    km, wm, pos = _read_params(bits, pos)
    if n > length:
        raise CodeError(f"{n} non-zero codes for {length} coefficients")
    out = np.zeros(length, dtype=np.int64)
    if n:
        zeros = np.flatnonzero(bits[pos:] == 0)
        if zeros.size < 2 * n:
            raise CodeError("truncated unary section")
        z = zeros[: 2 * n]
        ones = np.diff(np.concatenate(([-1], z))) - 1
        qr, qm = ones[:n].astype(np.int64), ones[n:].astype(np.int64)
        if qr.max() > _ESC or qm.max() > _ESC:
            raise CodeError("unary quotient above the escape code")
        pos += int(z[-1]) + 1
        er, em = qr == _ESC, qm == _ESC
        if (er.any() and wr == 0) or (em.any() and wm == 0):
            raise CodeError("escaped value without an escape width")
        ner, nem = int(er.sum()), int(em.sum())
        need = (n - ner) * kr + (n - nem) * km + ner * wr + nem * wm + n
        if pos + need > bits.size:
            raise CodeError("truncated fixed-width section")
        runs, mags = qr, qm
        sections = []
        for count, width in ((n - ner, kr), (n - nem, km), (ner, wr), (nem, wm)):
            sections.append(_from_fixed(bits[pos:pos + count * width], count, width))
            pos += count * width
        runs = np.where(er, 0, (qr << kr))
        runs[~er] |= sections[0]
        runs[er] = sections[2]
        mags = np.where(em, 0, (qm << km))
        mags[~em] |= sections[1]
        mags[em] = sections[3]
        neg = bits[pos:pos + n].astype(bool)
        pos += n
        if runs.max() >= length or mags.max() >= _MAX_CODE:
            raise CodeError("zero run or magnitude out of range")
        idx = np.cumsum(runs + 1) - 1
        if idx[-1] >= length:
            raise CodeError("coefficient index beyond the chunk's range")
        vals = mags + 1
        out[idx] = np.where(neg, -vals, vals)
    _check_padding(bits, pos)
    return out


def _best_code(codes: np.ndarray, first: int, n_approx: int, samples: bool = False) -> bytes:
    plain = encode_codes(codes)
    if samples:
        n_approx, first = codes.size, 0  # a samples chunk may difference-code all its codes
    if first == 0 and n_approx > 1 and codes[: min(n_approx, codes.size)].any():
        diff = encode_codes(codes, n_approx, dpcm=True)
        if len(diff) < len(plain):
            return diff
    return plain


def coded_bytes(codes: np.ndarray, n_approx: int, samples: bool = False) -> int:
    """Bytes of the whole pass coded as one range (the better of plain and differences)."""
    return len(_best_code(codes, 0, n_approx, samples))


def split_pass(codes: np.ndarray, n_approx: int, max_bytes: int,
               samples: bool = False) -> list[tuple[int, int, bytes]]:
    """Split a pass into ``(first, end, data)`` ranges, each coded in at most ``max_bytes``.

    Ranges are contiguous and cover every coefficient. A range is halved (by its non-zero
    codes) until it fits; each piece is decodable on its own."""
    out: list[tuple[int, int, bytes]] = []
    stack = [(0, int(codes.size))]
    while stack:
        first, end = stack.pop()
        data = _best_code(codes[first:end], first, n_approx, samples)
        if len(data) <= max_bytes:
            out.append((first, end, data))
            continue
        nz = np.flatnonzero(codes[first:end]) + first
        if nz.size <= 1:
            raise ValueError("a single coefficient does not fit in one chunk")
        cut = int(nz[nz.size // 2])
        stack.append((cut, end))
        stack.append((first, cut))
    return out

"""The binary arithmetic coder of ``PredictedSubgrid`` (spec/payloads.md section 1.7).

A classic integer arithmetic coder (Witten, Neal and Cleary, 1987) on 32-bit registers, coding
one binary decision at a time with a 12-bit probability of the decision being 0 (1..4095 in
units of 1/4096). It writes bits, not bytes, so the coded stream can start anywhere in a
message's bit stream, and its length follows from the decoding itself (the number of register
shifts plus two), so the message stays self-delimiting without a length field.

* Encoding a bit ``b`` with probability ``p0``: ``r = high - low + 1``; ``split = low + ((r *
  p0) >> 12) - 1``; a 0 keeps ``[low, split]``, a 1 keeps ``[split + 1, high]``. Then, while
  the interval lies in one half or straddles the middle within the middle half, the registers
  shift left by one bit (E1: ``high < 2^31``, write 0; E2: ``low >= 2^31``, write 1; E3:
  ``2^30 <= low`` and ``high < 3 * 2^30``, one more *pending* bit), ``low = 2 low``, ``high = 2
  high + 1`` (modulo the half or quarter taken away). A written bit is followed by the pending
  bits, each its opposite.
* Finishing: one more pending bit, then 0 if ``low < 2^30`` else 1, then the pending bits: the
  coded stream is ``shifts + 2`` bits long, and any bits after it decode the same decisions.
* Decoding mirrors the encoder with ``value``, the first 32 bits of the stream (bits after the
  end of the input read as 0).

Adaptive probabilities (:class:`Contexts`): after each decision ``p0 += (4096 - p0) >> 4`` for a
0 and ``p0 -= p0 >> 4`` for a 1 (``p0`` stays within 1..4095). Fixed-probability decisions use
``p0 = 2048`` and are not adapted.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["ArithDecoder", "ArithEncoder", "CodeError", "HALF_P", "RATE", "adapt"]

_TOP = (1 << 32) - 1
_HALF = 1 << 31
_QTR = 1 << 30
_3QTR = 3 << 30
#: probability unit: 12 bits
PROB_BITS = 12
#: a fixed decision (a "raw" bit): probability 1/2, never adapted
HALF_P = 2048
#: adaptation shift
RATE = 4


class CodeError(ValueError):
    """A coded stream breaks a rule: ``reason`` is the spec's error word."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(f"{message} ({reason})")
        self.reason = reason


def adapt(p0: int, bit: int) -> int:
    """The probability of a 0 after coding ``bit`` with ``p0``."""
    return p0 + ((4096 - p0) >> RATE) if bit == 0 else p0 - (p0 >> RATE)


class ArithEncoder:
    """Writes decisions; :meth:`finish` returns the coded bits (a list of 0 and 1)."""

    __slots__ = ("bits", "high", "low", "pending")

    def __init__(self) -> None:
        self.low = 0
        self.high = _TOP
        self.pending = 0
        self.bits: list[int] = []

    def _emit(self, b: int) -> None:
        self.bits.append(b)
        if self.pending:
            self.bits.extend([1 - b] * self.pending)
            self.pending = 0

    def encode(self, bit: int, p0: int) -> None:
        low, high = self.low, self.high
        split = low + (((high - low + 1) * p0) >> PROB_BITS) - 1
        if bit:
            low = split + 1
        else:
            high = split
        if high >= _HALF and low < _HALF and (low < _QTR or high >= _3QTR):
            self.low, self.high = low, high  # no shift: the common case of a likely decision
            return
        bits = self.bits
        pending = self.pending
        while True:
            if high < _HALF:
                bits.append(0)
                if pending:
                    bits.extend([1] * pending)
                    pending = 0
            elif low >= _HALF:
                bits.append(1)
                if pending:
                    bits.extend([0] * pending)
                    pending = 0
                low -= _HALF
                high -= _HALF
            elif low >= _QTR and high < _3QTR:
                pending += 1
                low -= _QTR
                high -= _QTR
            else:
                break
            low <<= 1
            high = (high << 1) | 1
        self.low, self.high, self.pending = low, high, pending

    def adaptive(self, bit: int, probs: list[int], k: int) -> None:
        """Encode ``bit`` with the adaptive probability ``probs[k]``, then adapt it."""
        p0 = probs[k]
        self.encode(bit, p0)
        probs[k] = p0 + ((4096 - p0) >> RATE) if bit == 0 else p0 - (p0 >> RATE)

    def finish(self) -> list[int]:
        self.pending += 1
        self._emit(0 if self.low < _QTR else 1)
        return self.bits


class ArithDecoder:
    """Reads decisions from ``read`` (the next bit of the stream, 0 or 1); :attr:`length` is the
    number of bits the encoder wrote for the decisions read so far (once finished). A decision
    that makes that length pass ``max_bits`` raises :class:`CodeError` (``too large``)."""

    __slots__ = ("high", "limit", "low", "read", "shifts", "value")

    def __init__(self, read: Callable[[], int], max_bits: int | None = None) -> None:
        self.read = read
        self.limit = (1 << 62) if max_bits is None else max_bits - 2
        self.low = 0
        self.high = _TOP
        v = 0
        for _ in range(32):
            v = (v << 1) | read()
        self.value = v
        self.shifts = 0

    def adaptive(self, probs: list[int], k: int) -> int:
        """Decode a decision with the adaptive probability ``probs[k]``, then adapt it."""
        p0 = probs[k]
        bit = self.decode(p0)
        probs[k] = p0 + ((4096 - p0) >> RATE) if bit == 0 else p0 - (p0 >> RATE)
        return bit

    def decode(self, p0: int) -> int:
        low, high, value = self.low, self.high, self.value
        split = low + (((high - low + 1) * p0) >> PROB_BITS) - 1
        if value <= split:
            bit = 0
            high = split
        else:
            bit = 1
            low = split + 1
        shifts = 0
        while True:
            if high < _HALF:
                pass
            elif low >= _HALF:
                low -= _HALF
                high -= _HALF
                value -= _HALF
            elif low >= _QTR and high < _3QTR:
                low -= _QTR
                high -= _QTR
                value -= _QTR
            else:
                break
            low <<= 1
            high = (high << 1) | 1
            value = (value << 1) | self.read()
            shifts += 1
        self.low, self.high, self.value = low, high, value
        self.shifts += shifts
        if self.shifts > self.limit:
            raise CodeError(f"the code passes {self.limit + 2} bits", "too large")
        return bit

    @property
    def length(self) -> int:
        """Bits of the coded stream: every shift wrote (or deferred) one bit, finishing two."""
        return self.shifts + 2

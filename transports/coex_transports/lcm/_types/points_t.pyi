# Typing stub of the lcm-gen module beside it, written by regen.py from the class's
# __slots__, __typenames__ and __dimensions__. DO NOT MODIFY BY HAND.

from collections.abc import Sequence
from typing import BinaryIO


class points_t:
    __slots__: list[str]
    __typenames__: list[str]
    __dimensions__: list[list[int | str] | None]
    utime: int
    n: int
    x: Sequence[float]
    y: Sequence[float]
    z: Sequence[float]
    def __init__(self) -> None: ...
    def encode(self) -> bytes: ...
    @staticmethod
    def decode(data: bytes | BinaryIO) -> points_t: ...
    @staticmethod
    def _get_packed_fingerprint() -> bytes: ...
    def get_hash(self) -> int: ...

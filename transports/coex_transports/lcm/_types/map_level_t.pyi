# Typing stub of the lcm-gen module beside it, written by regen.py from the class's
# __slots__, __typenames__ and __dimensions__. DO NOT MODIFY BY HAND.

from typing import BinaryIO


class map_level_t:
    __slots__: list[str]
    __typenames__: list[str]
    __dimensions__: list[list[int | str] | None]
    utime: int
    level: int
    resolution: float
    subgrids: int
    cells: int
    x_min: float
    y_min: float
    x_max: float
    y_max: float
    z_min: float
    z_max: float
    newest_stamp: int
    def __init__(self) -> None: ...
    def encode(self) -> bytes: ...
    @staticmethod
    def decode(data: bytes | BinaryIO) -> map_level_t: ...
    @staticmethod
    def _get_packed_fingerprint() -> bytes: ...
    def get_hash(self) -> int: ...

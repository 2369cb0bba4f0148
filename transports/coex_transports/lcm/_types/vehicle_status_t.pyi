# Typing stub of the lcm-gen module beside it, written by regen.py from the class's
# __slots__, __typenames__ and __dimensions__. DO NOT MODIFY BY HAND.

from typing import BinaryIO


class vehicle_status_t:
    __slots__: list[str]
    __typenames__: list[str]
    __dimensions__: list[list[int | str] | None]
    utime: int
    stamp: int
    x: float
    y: float
    depth: float
    has_altitude: bool
    altitude: float
    heading: float
    speed: float
    battery: int
    mode: int
    mode_name: str
    faults: int
    def __init__(self) -> None: ...
    def encode(self) -> bytes: ...
    @staticmethod
    def decode(data: bytes | BinaryIO) -> vehicle_status_t: ...
    @staticmethod
    def _get_packed_fingerprint() -> bytes: ...
    def get_hash(self) -> int: ...

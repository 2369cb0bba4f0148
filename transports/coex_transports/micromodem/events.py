"""What a :class:`~.driver.MicromodemDriver` is configured with (:class:`DriverConfig`) and what it
reports (:data:`Event`: received frames, transmissions done or failed, acknowledgements, pings,
reboots, modem errors, link status). Plain frozen values; :mod:`.driver` re-exports them."""

from __future__ import annotations

from dataclasses import dataclass

from coex_core.errors import ConfigError
from coex_core.messages import LinkStatus

from .nmea import FDP_RATES, RATES

__all__ = [
    "DriverConfig",
    "Event",
    "ReceivedFrame",
    "TxDone",
    "TxFailed",
    "Acked",
    "PingResult",
    "Rebooted",
    "ModemErrorEvent",
]


@dataclass(frozen=True)
class DriverConfig:
    """Settings of one modem link (the URI options of ``micromodem:``)."""

    src: int = 1
    dest: int = 0
    rate: int = 5
    mode: str = "cycle"  # "cycle" (legacy $CCCYC, Micromodem-1 and -2) or "fdp" ($CCTDP, Micromodem-2)
    ack: bool = False
    link: int = 0
    firmware: str = "mm2"  # "mm2" or "mm1": which clock and keep-alive commands to use
    nvram: tuple[tuple[str, str], ...] = ()
    reset_nvram: bool = False
    base64: bool = False
    set_clock: bool = True
    reply_timeout: float = 2.0
    retries: int = 3
    keepalive: float = 10.0
    tx_timeout: float = 60.0
    max_attempts: int = 3
    reboot_pause: float = 2.0

    def __post_init__(self) -> None:
        if not 0 <= self.src <= 127:
            raise ConfigError(f"src must be 0..127, got {self.src}")
        if not 0 <= self.dest <= 127:
            raise ConfigError(f"dest must be 0..127, got {self.dest}")
        if self.mode not in ("cycle", "fdp"):
            raise ConfigError(f"mode must be 'cycle' or 'fdp', got {self.mode!r}")
        table = FDP_RATES if self.mode == "fdp" else RATES
        if self.rate not in table:
            raise ConfigError(f"rate {self.rate} is not valid for mode {self.mode} (valid: {sorted(table)})")
        if self.firmware not in ("mm1", "mm2"):
            raise ConfigError(f"firmware must be 'mm1' or 'mm2', got {self.firmware!r}")
        if not 0 <= self.link <= 7:
            raise ConfigError(f"link must be 0..7, got {self.link}")
        if self.reply_timeout <= 0 or self.tx_timeout <= 0 or self.keepalive <= 0:
            raise ConfigError("timeouts must be positive")
        if self.retries < 0 or self.max_attempts < 1:
            raise ConfigError("retries must be >= 0 and max_attempts >= 1")
        if self.mode == "fdp" and self.firmware == "mm1":
            raise ConfigError("FDP needs a Micromodem-2 (firmware=mm2)")

    @property
    def mtu(self) -> int:
        return RATES[self.rate].frame_bytes


# ------------------------------------------------------------------------------------ events
@dataclass(frozen=True)
class ReceivedFrame:
    """One frame delivered by the modem (a good ``$CARXD`` or ``crc_ok`` FDP data frame)."""

    data: bytes
    src: int
    dest: int
    rate: int
    index: int  # 1-based frame number within its packet
    time: float
    fdp: bool = False


@dataclass(frozen=True)
class TxDone:
    frames: tuple[bytes, ...]
    rate: int
    dest: int
    time: float


@dataclass(frozen=True)
class TxFailed:
    frames: tuple[bytes, ...]
    rate: int
    dest: int
    reason: str
    time: float


@dataclass(frozen=True)
class Acked:
    src: int
    frame: int
    time: float


@dataclass(frozen=True)
class PingResult:
    dest: int
    owtt: float
    time: float


@dataclass(frozen=True)
class Rebooted:
    time: float


@dataclass(frozen=True)
class ModemErrorEvent:
    module: str
    number: str
    message: str
    time: float


Event = ReceivedFrame | TxDone | TxFailed | Acked | PingResult | Rebooted | ModemErrorEvent | LinkStatus

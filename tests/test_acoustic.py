"""The simulated acoustic channel: rate table, timing, half duplex, collisions, loss, CRC."""

from __future__ import annotations

import pytest

from coex_core.acoustic import RATES, AcousticChannel, GilbertElliott, rate_info
from coex_core.errors import ConfigError, FrameTooLarge


def _pair(**kw: object) -> AcousticChannel:
    ch = AcousticChannel(**kw)  # type: ignore[arg-type]
    ch.set_position(1, (0.0, 0.0, 0.0))
    ch.set_position(2, (1500.0, 0.0, 0.0))
    return ch


def test_rate_table_matches_micromodem_layout() -> None:
    layout = {r: (i.frame_bytes, i.frames) for r, i in RATES.items()}
    assert layout == {0: (32, 1), 1: (64, 3), 2: (64, 3), 3: (256, 2), 4: (256, 2), 5: (256, 8), 6: (32, 6)}
    assert RATES[5].airtime() == pytest.approx(3.0, abs=0.05)
    assert RATES[1].airtime(72) == pytest.approx(1.57, abs=0.05)
    assert RATES[1].airtime(192) == pytest.approx(3.07, abs=0.05)
    assert RATES[5].airtime(100) < RATES[5].airtime(200)
    with pytest.raises(ConfigError):
        rate_info(9)


def test_propagation_delay_and_airtime() -> None:
    ch = _pair()
    end = ch.transmit(1, [b"a" * 256, b"b" * 10], 5, now=100.0)
    assert end == pytest.approx(100.0 + RATES[5].packet_airtime(2))
    assert ch.poll(end + 0.5) == []  # still travelling (1 s delay)
    (a,) = ch.poll(end + 1.0)
    assert (a.src, a.dst, a.rate) == (1, 2, 5)
    assert a.start == pytest.approx(101.0) and a.end == pytest.approx(end + 1.0)
    assert a.frames == [b"a" * 256, b"b" * 10]
    rec = ch.log()
    assert rec[0]["capacity_bytes"] == 512 and rec[0]["used_bytes"] == 266
    assert rec[0]["delivered"] == [True, True]


def test_oversize_rejected() -> None:
    ch = _pair()
    with pytest.raises(FrameTooLarge):
        ch.transmit(1, [b"x" * 257], 5, 0.0)
    with pytest.raises(FrameTooLarge):
        ch.transmit(1, [b"x"] * 9, 5, 0.0)
    with pytest.raises(ConfigError):
        ch.transmit(7, [b"x"], 5, 0.0)
    with pytest.raises(ConfigError):
        ch.transmit(1, [5], 5, 0.0)  # type: ignore[list-item]
    with pytest.raises(ConfigError):
        ch.set_position(3, (0.0, float("nan"), 0.0))
    with pytest.raises(ConfigError):
        AcousticChannel(loss=1.5)
    with pytest.raises(ConfigError):
        GilbertElliott(p_good_bad=2.0)


def test_half_duplex_and_collision() -> None:
    ch = _pair()
    ch.transmit(1, [b"one"], 5, 0.0)
    ch.transmit(2, [b"two"], 5, 0.5)  # node 2 transmits while node 1's packet arrives
    got = ch.poll(100.0)
    by_dst = {a.dst: a for a in got}
    assert by_dst[2].cause == "half-duplex" and by_dst[2].frames == [None]
    assert by_dst[1].cause == "" and by_dst[1].frames == [b"two"]  # node 1 was done by then
    ch3 = _pair()
    ch3.set_position(3, (3000.0, 0.0, 0.0))
    ch3.transmit(1, [b"one"], 5, 0.0)
    ch3.transmit(3, [b"three"], 5, 0.2)
    at2 = [a for a in ch3.poll(100.0) if a.dst == 2]
    assert {a.cause for a in at2} == {"collision"}
    # separated in time: no collision
    ch4 = _pair()
    ch4.set_position(3, (3000.0, 0.0, 0.0))
    ch4.transmit(1, [b"one"], 5, 0.0)
    ch4.transmit(3, [b"three"], 5, 10.0)
    assert all(a.cause == "" for a in ch4.poll(100.0))


def test_independent_loss_rate_and_determinism() -> None:
    def run(seed: int) -> list[bool]:
        ch = _pair(loss=0.3, seed=seed)
        t = 0.0
        for _ in range(200):
            t = ch.transmit(1, [b"x" * 20] * 8, 5, t) + 2.0
        return [f is not None for a in ch.poll(1e9) for f in a.frames]

    a, b = run(4), run(4)
    assert a == b
    assert a != run(5)
    lost = 1 - sum(a) / len(a)
    assert 0.25 < lost < 0.35


def test_burst_loss_is_bursty() -> None:
    ge = GilbertElliott(p_good_bad=0.05, p_bad_good=0.25)
    ch = _pair(burst=ge, seed=1)
    t = 0.0
    for _ in range(300):
        t = ch.transmit(1, [b"y"] * 8, 5, t) + 1.0
    ok = [f is not None for a in ch.poll(1e9) for f in a.frames]
    lost = 1 - sum(ok) / len(ok)
    assert abs(lost - ge.mean_loss) < 0.06
    runs = []
    n = 0
    for good in ok:
        if not good:
            n += 1
        elif n:
            runs.append(n)
            n = 0
    assert sum(runs) / len(runs) > 2.5  # independent loss at this rate would give ~1.2


def test_bit_errors_caught_by_crc() -> None:
    ch = _pair(bit_error_rate=1e-3, seed=3)
    payload = bytes(range(256))
    t = 0.0
    for _ in range(40):
        t = ch.transmit(1, [payload] * 8, 5, t) + 1.0
    frames = [f for a in ch.poll(1e9) for f in a.frames]
    # P(frame clean) = (1 - 1e-3)^2048 ~ 0.13: most frames fail the CRC, the rest are intact
    assert 0.05 < sum(f is not None for f in frames) / len(frames) < 0.25
    assert all(f == payload for f in frames if f is not None)
    assert "crc" in ch.log()[0]["cause"]


def test_range_loss() -> None:
    ch = _pair(range_loss=lambda d: 1.0 if d > 1000 else 0.0)
    ch.set_position(3, (500.0, 0.0, 0.0))
    ch.transmit(1, [b"z"], 5, 0.0)
    got = {a.dst: a.frames for a in ch.poll(100.0)}
    assert got == {2: [None], 3: [b"z"]}


def test_busy_sender_queues_behind_itself() -> None:
    ch = _pair()
    e1 = ch.transmit(1, [b"a"], 5, 0.0)
    e2 = ch.transmit(1, [b"b"], 5, 0.0)
    assert e2 == pytest.approx(e1 + RATES[5].packet_airtime(1))
    assert [a.frames for a in ch.poll(100.0)] == [[b"a"], [b"b"]]

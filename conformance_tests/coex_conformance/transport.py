"""Abstract tests every transport plugin must pass (use with :class:`TransportFixtures`)."""

from __future__ import annotations

from collections.abc import Sequence

import pytest

from coex import FrameTooLarge, Transport


def _frame(size: int, salt: int) -> bytes:
    return bytes((i * 31 + salt * 7 + size) % 256 for i in range(size))


class TransportTests:
    """Back-to-back frames of every size up to the MTU arrive intact; over-MTU frames are refused."""

    def test_mtu_is_positive(self, transport_pair: tuple[Transport, Transport]) -> None:
        """Both ends state a positive MTU (the largest frame they carry)."""
        a, b = transport_pair
        assert a.mtu > 0 and b.mtu > 0, f"rule: a transport states a positive MTU; got {a.mtu} and {b.mtu}"

    @pytest.mark.parametrize("direction", ["a_to_b", "b_to_a"])
    def test_back_to_back_every_size(
        self,
        transport_pair: tuple[Transport, Transport],
        frame_sizes: Sequence[int],
        burst: int,
        recv_timeout: float,
        direction: str,
    ) -> None:
        """Frames of every size up to the MTU, sent back to back in bursts, arrive whole and in
        order, in both directions."""
        a, b = transport_pair
        tx, rx = (a, b) if direction == "a_to_b" else (b, a)
        sizes = [s for s in frame_sizes if s <= tx.mtu]
        for start in range(0, len(sizes), burst):
            frames = [_frame(s, start) for s in sizes[start:start + burst]]
            for f in frames:
                tx.send(f)
            got = []
            for _ in frames:
                frame = rx.recv(timeout=recv_timeout)
                assert frame is not None, (f"rule: a lossless transport delivers every frame; lost one "
                                           f"of sizes {sizes[start:start + burst]}")
                got.append(frame)
            assert got == frames, (f"rule: frames arrive whole and in order; sizes {sizes[start:start + burst]} "
                                   "came back different")

    def test_over_mtu_refused(self, transport_pair: tuple[Transport, Transport], recv_timeout: float) -> None:
        """A frame above the MTU is refused with FrameTooLarge, nothing of it arrives, and the
        transport still works."""
        a, b = transport_pair
        with pytest.raises(FrameTooLarge):
            a.send(bytes(a.mtu + 1))
        # nothing of the refused frame arrives, and the transport still works
        a.send(b"\x01\x02\x03")
        assert b.recv(timeout=recv_timeout) == b"\x01\x02\x03", (
            "rule: after refusing an over-MTU frame the transport carries the next one, alone")

    def test_recv_times_out_with_none(self, transport_pair: tuple[Transport, Transport]) -> None:
        """recv with a timeout and nothing sent returns None (no exception, no stale frame)."""
        _, b = transport_pair
        assert b.recv(timeout=0.2) is None, "rule: recv returns None when nothing arrives in time"

    def test_close_is_idempotent(self, transport_pair: tuple[Transport, Transport]) -> None:
        """close() twice is harmless and leaves the transport closed."""
        a, _ = transport_pair
        a.close()
        a.close()
        assert a.closed, "rule: a closed transport says so (closed is true)"

"""Fixture contracts. Required fixtures raise ``NotImplementedError``; optional ones have
defaults and double as capability flags."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

from coex import Modality, ModalityReceiver, ModalitySender, Transport


class ModalityFixtures:
    """Fixtures a modality plugin provides to run :class:`~coex_conformance.ModalityTests`."""

    @pytest.fixture
    def modality(self) -> Modality:
        """Required: an instance of the plugin's :class:`~coex.Modality`."""
        raise NotImplementedError("provide a `modality` fixture")

    @pytest.fixture
    def sample_inputs(self) -> Sequence[tuple[float, Any]]:
        """Required: ``(now, data)`` pairs to :meth:`ModalitySender.ingest`, in time order.
        Keep them small: the suite moves them over a ~100 B/s link several times."""
        raise NotImplementedError("provide a `sample_inputs` fixture")

    @pytest.fixture
    def converged(self) -> Callable[[ModalitySender, ModalityReceiver], bool]:
        """Required: a function telling whether the receiver holds everything the sender should
        have delivered (the suite calls it after every round)."""
        raise NotImplementedError("provide a `converged` fixture")

    @pytest.fixture
    def sender_config(self) -> dict[str, Any] | None:
        """Optional: configuration for ``modality.sender``."""
        return None

    @pytest.fixture
    def receiver_config(self) -> dict[str, Any] | None:
        """Optional: configuration for ``modality.receiver``."""
        return None

    @pytest.fixture
    def start_requests(self) -> Callable[[ModalityReceiver, float], None] | None:
        """Optional: called once after ingest to make the receiver issue requests (goals, ROI)."""
        return None

    @pytest.fixture
    def loss(self) -> float:
        """Optional: frame loss of the lossy link, both directions."""
        return 0.3

    @pytest.fixture
    def frame_budget(self) -> int:
        """Optional: bytes per frame offered to the sender (a Micromodem rate-5 sub-frame)."""
        return 256

    @pytest.fixture
    def max_rounds(self) -> int:
        """Optional: rounds (one frame each way) allowed to converge."""
        return 3000

    @pytest.fixture
    def round_seconds(self) -> float:
        """Optional: simulated seconds per round."""
        return 5.0

    @pytest.fixture
    def node_converge_seconds(self) -> float:
        """Optional: simulated seconds every plugin in the two-node test may take to converge."""
        return 4 * 3600.0

    @pytest.fixture
    def other_plugins(self) -> Sequence[Any]:
        """Optional: further plugins (:class:`~coex_conformance.companions.Companion`) to run
        beside the plugin under test in the two-node tests, on top of the sample third-party
        plugin and the built-in modalities (``coex plugins check A B`` passes B here for A)."""
        return ()

    @pytest.fixture
    def settle_seconds(self) -> float:
        """Optional: simulated seconds after convergence before the sender must be quiet (acks
        in flight, spare work finishing)."""
        return 1800.0


class TransportFixtures:
    """Fixtures a transport plugin provides to run :class:`~coex_conformance.TransportTests`."""

    @pytest.fixture
    def transport_pair(self) -> Iterator[tuple[Transport, Transport]]:
        """Required: two connected, lossless transport ends ``(a, b)``; close them after ``yield``."""
        raise NotImplementedError("provide a `transport_pair` fixture")

    @pytest.fixture
    def recv_timeout(self) -> float:
        """Optional: seconds to wait for a frame that must arrive."""
        return 5.0

    @pytest.fixture
    def frame_sizes(self, transport_pair: tuple[Transport, Transport]) -> Sequence[int]:
        """Optional: frame sizes to try; default every size from 1 to the MTU (sampled above 256)."""
        mtu = transport_pair[0].mtu
        if mtu <= 256:
            return list(range(1, mtu + 1))
        step = max(1, mtu // 64)
        return sorted({1, 2, 3, *range(4, mtu, step), mtu - 1, mtu})

    @pytest.fixture
    def burst(self) -> int:
        """Optional: frames sent back to back before the receiver reads them."""
        return 4

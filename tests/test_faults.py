"""The fault suite (fixed seeds): a short dive with all three modalities through a simulated link
with independent loss 0-60 %, burst loss, duplicated, reordered, bit-flipped and truncated
frames, a modem that reboots mid-packet, and modalities that raise. Every time: the map
converges to the vehicle's, every image reaches its goal (image 1, requested, in full), the time
series arrive within their bounds, and no node raises."""

from __future__ import annotations

from typing import Any

import pytest

from coex_core.acoustic import AcousticChannel, GilbertElliott
from coex_core.channel import BadFrame, Rejected, SenderFailed

from ._faults import (
    T0,
    Dive,
    FailingReceiver,
    FailingSender,
    FaultyChannel,
    build_dive,
    images_complete,
    map_converged,
    run_modems,
    run_sim,
    series_complete,
)

LIMIT = T0 + 3600.0  # simulated; data end at T0 + 900 s


def converge(dive: Dive, net: Any) -> float:
    """Run on until everything has arrived (at most until LIMIT); returns when it had."""
    while not (map_converged(dive) and images_complete(dive) and series_complete(dive)):
        assert net.now < LIMIT, (
            f"not converged by {LIMIT - T0:.0f} s: map {map_converged(dive)}, images "
            f"{images_complete(dive)}, series {series_complete(dive)}")
        net.run(net.now + 150.0)
    return net.now - T0


def events(dive: Dive) -> tuple[list[Any], list[Any]]:
    return dive.vehicle.events(), dive.topside.events()


@pytest.mark.parametrize("loss", [0.0, 0.2, 0.4, 0.6])
def test_independent_loss(loss: float) -> None:
    dive = build_dive()
    ch = AcousticChannel(loss=loss, seed=11)
    net = run_sim(dive, ch, T0 + 900.0)
    took = converge(dive, net)
    assert took < LIMIT - T0
    if loss:
        assert dive.vehicle.stats["frames"] > 0 and dive.topside.stats["frames"] > 0


def test_burst_loss() -> None:
    dive = build_dive()
    burst = GilbertElliott(p_good_bad=0.05, p_bad_good=0.2, loss_good=0.02, loss_bad=0.95)
    ch = AcousticChannel(burst=burst, seed=12)
    net = run_sim(dive, ch, T0 + 900.0)
    converge(dive, net)
    assert burst.mean_loss > 0.2


@pytest.mark.parametrize("fault", ["dup", "reorder", "flip", "truncate"])
def test_tampered_frames(fault: str) -> None:
    dive = build_dive(crc=True)
    # a reorder needs two arrivals pending at once: rarer, so it is drawn more often
    ch = FaultyChannel(loss=0.1, seed=13, fault_seed=14, **{fault: 0.4 if fault == "reorder" else 0.2})
    net = run_sim(dive, ch, T0 + 900.0)
    converge(dive, net)
    assert ch.counts[fault] > 20, ch.counts
    vev, tev = events(dive)
    if fault in ("flip", "truncate"):
        bad = [e for e in vev + tev if isinstance(e, BadFrame)]
        assert bad and dive.topside.stats["bad_frames"] + dive.vehicle.stats["bad_frames"] >= len(bad)


def test_everything_at_once() -> None:
    dive = build_dive(crc=True)
    ch = FaultyChannel(loss=0.3, seed=15, fault_seed=16, dup=0.1, reorder=0.1, flip=0.05, truncate=0.05)
    net = run_sim(dive, ch, T0 + 900.0)
    converge(dive, net)
    assert all(v > 0 for v in ch.counts.values()), ch.counts


def test_modalities_that_raise() -> None:
    failing: list[FailingSender] = []
    failing_rx: list[FailingReceiver] = []

    def wrap(s: Any) -> Any:
        failing.append(FailingSender(s, every=7))
        return failing[-1]

    def wrap_rx(r: Any) -> Any:
        failing_rx.append(FailingReceiver(r, every=9))
        return failing_rx[-1]

    dive = build_dive(wrap_sender=wrap, wrap_receiver=wrap_rx)
    net = run_sim(dive, AcousticChannel(loss=0.2, seed=17), T0 + 900.0)
    converge(dive, net)
    assert all(f.raised > 0 for f in failing) and all(f.raised > 0 for f in failing_rx)
    vev, tev = events(dive)
    assert any(isinstance(e, SenderFailed) for e in vev)
    assert any(isinstance(e, Rejected) for e in tev)  # the receiver's exception, reported


def test_a_sensor_driver_that_raises_loses_only_its_own_batch() -> None:
    failing: list[FailingSender] = []

    def wrap(s: Any) -> Any:
        failing.append(FailingSender(s, every=5, fail_ingest=True))
        return failing[-1]

    dive = build_dive(wrap_sender=wrap)
    net = run_sim(dive, AcousticChannel(loss=0.2, seed=18), T0 + 900.0)
    errors = net.input_errors  # type: ignore[attr-defined]
    assert errors and set(errors) == {"sensor driver crashed"}
    while not map_converged(dive):  # the map topside is the vehicle's map of what it did take
        assert net.now < LIMIT
        net.run(net.now + 150.0)


def test_modem_reboots_mid_packet() -> None:
    dive = build_dive()
    # reboots while the vehicle's packets are on the serial line or in the water
    reboots = [T0 + 101.3, T0 + 333.7, T0 + 615.2]
    _net, runners = run_modems(dive, T0 + 1500.0, reboots)
    assert map_converged(dive) and images_complete(dive) and series_complete(dive), (
        map_converged(dive), images_complete(dive), series_complete(dive))
    driver = runners[0].transports[0]
    assert driver.stats()["reboots"] == len(reboots)

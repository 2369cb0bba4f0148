"""The plugins the suite runs beside the plugin under test: the sample third-party plugin
(:mod:`coex_conformance.sample`) and every built-in modality that is installed (bathymetry,
imagery, time series), each with small inputs and a test of convergence.

A plugin gives its inputs as a :class:`Companion`, registered under the ``coex.conformance``
entry-point group with the modality's name; the built-in modalities register theirs exactly
so (``coex_plugins.<name>.conformance:companion``), and their own conformance tests use them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from coex import Modality, ModalityReceiver, ModalitySender
from coex.registry import entry_points

__all__ = ["BUILT_IN", "CONFORMANCE_GROUP", "Companion", "companions", "sample"]

CONFORMANCE_GROUP = "coex.conformance"
#: the built-in modalities the two-node tests run beside every plugin (those installed)
BUILT_IN = ("bathymetry", "imagery", "timeseries", "survey", "detections")


@dataclass(frozen=True)
class Companion:
    """A plugin's conformance inputs: its modality, small sample inputs (``(now, data)`` pairs
    for ``ingest``), a test of convergence, and optional configurations and start requests."""

    name: str
    modality: Callable[[], Modality]
    sample_inputs: Callable[[], list[tuple[float, Any]]]
    converged: Callable[[ModalitySender, ModalityReceiver], bool]
    sender_config: Callable[[], Any] = lambda: None
    receiver_config: Callable[[], Any] = lambda: None
    start_requests: Callable[[ModalityReceiver, float], None] | None = None


def sample() -> Companion:
    """Entry point ``coex.conformance: conformance-sample``."""
    from .sample import SampleModality, sample_converged, sample_inputs

    return Companion(SampleModality.name, SampleModality, sample_inputs, sample_converged)


def registered(name: str) -> Companion | None:
    """The inputs registered under ``coex.conformance`` as ``name`` (None: none, or its plugin
    is not installed with what it needs, e.g. imagery without glymur)."""
    ep = entry_points(CONFORMANCE_GROUP).get(name)
    if ep is None:
        return None
    try:
        return ep.load()()  # type: ignore[no-any-return]
    except ImportError:
        return None


def companions() -> list[Companion]:
    """The sample third-party plugin and every built-in modality installed."""
    out = [sample()]
    for name in BUILT_IN:
        c = registered(name)
        if c is not None:
            out.append(c)
    return out

"""The detections receiver's product: every detection held."""

from __future__ import annotations

from dataclasses import dataclass

from coex import TypedProduct

__all__ = ["DetectionsProduct"]


@dataclass(frozen=True, kw_only=True)
class DetectionsProduct(TypedProduct):
    """The vehicle's detections (kind ``detections``, key ``detections``). ``data``: their rows
    (dicts: ``id``, ``source``, ``x``, ``y``, ``score`` ...), highest score first."""

    count: int

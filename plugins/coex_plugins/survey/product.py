"""The survey receiver's product: what became of one survey asked."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

from coex import TypedProduct, persistent

__all__ = ["SurveyProduct"]


@persistent("survey.Product")
@dataclass(frozen=True, kw_only=True)
class SurveyProduct(TypedProduct):
    """A survey (kind ``survey``, key its id): its state (``requested``, ``accepted``,
    ``started``, ``completed``, ``rejected``, ``aborted``, ``given up``, ``unknown``), why
    (``reason``, ``text``), its history and, when topside knows its command, the plan
    (``survey_kind`` is ``kind`` in :attr:`meta`). Registered state: a console that holds no
    survey receiver saves the products it was told."""

    META_NAMES: ClassVar[Mapping[str, str]] = {"survey_kind": "kind"}

    survey_id: int
    state: str
    text: str
    reason: str | None
    #: the waypoint reached (None before any)
    index: int | None
    time: float
    #: (time, state, text), the newest 12, in the order things happened
    history: list[list[float | str]]
    #: the command's kind in lower case (``lawnmower`` ...), None without a command
    survey_kind: str | None = None
    #: [[x, y], ...] metres east/north
    waypoints: list[list[float]] | None = None
    heading: float | None = None
    length: float | None = None
    width: float | None = None
    spacing: float | None = None
    altitude: float | None = None
    depth: float | None = None
    speed: float | None = None
    append: bool | None = None

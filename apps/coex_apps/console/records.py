"""The records the console's state keeps (:mod:`.model`): a map region asked, an image and a
crop the imagery receiver holds, a command in the list. Saved with the state under stable names
(``console.RoiRequest``, ``console.Image``, ``console.Crop``, ``console.Command``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from coex import messages as m
from coex import persistent
from coex.tracker import Event, State, Tracked
from coex_plugins.bathymetry import Region

__all__ = ["_Command", "_Crop", "_Image", "_RoiRequest"]


@persistent("console.RoiRequest")
@dataclass
class _RoiRequest:
    """A map region asked from the console: the bathymetry receiver's region object (which
    it sends, retries and closes), and when it was asked."""

    level: int
    x0: int
    y0: int
    w: int
    h: int
    sent: float
    region: Region
    #: the most subgrids the vehicle said it queued for it (0: it never sent anything)
    got: int = 0


@persistent("console.Image")
@dataclass
class _Image:
    """An image the console keeps: what the imagery receiver holds of it (its decoded picture
    and the receiver's meta), the goal asked of it and its thumbnail."""

    image_id: int
    t: float | None = None
    goal: tuple[str, int] | None = None
    version: int = 0
    thumb: bytes | None = None
    thumb_version: int = -1
    decoded: Any = None
    decoded_version: int = -1
    decoded_meta: dict[str, Any] = field(default_factory=dict)
    #: the regions the imagery receiver lists for it (its product's ``regions``)
    regions: list[dict[str, Any]] = field(default_factory=list)


@persistent("console.Crop")
@dataclass
class _Crop:
    """A crop the imagery receiver holds (a region of an image coded on its own): what it shows
    of its box and the receiver's meta (``parent``, ``box``, ``command_id``, bytes ...)."""

    crop_id: int
    decoded: Any = None
    decoded_version: int = -1
    meta: dict[str, Any] = field(default_factory=dict)
    png: bytes | None = None
    png_version: int = -1


#: saved ``status`` of version 1 -> the tracker's state
_V1_STATES = {"queued": State.QUEUED, "sent": State.SENT, "pending": State.PENDING, "accepted": State.DONE}


def _upgrade_command(fields: dict[str, Any], saved: int) -> dict[str, Any]:
    """Version 1 kept its own ``status`` (a word) and ``answered``: now the core tracker's
    entry holds them (the vehicle's answer, upper case, in ``answer``)."""
    if saved < 2:
        status = str(fields.pop("status", "sent"))
        answered = fields.pop("answered", None)
        state = _V1_STATES.get(status, State.REFUSED)
        sent = float(fields.get("sent", 0.0))
        fields["track"] = Tracked(None, state, None if state is State.QUEUED else sent,
                                  0 if state is State.QUEUED else 1, answered_at=answered,
                                  answer="" if state in (State.QUEUED, State.SENT) else status.upper())
    return fields


@persistent("console.Command", version=2, upgrade=_upgrade_command)
@dataclass
class _Command:
    """A command in the console's list: what it was, who sent it and when, and its state in
    the core tracker (``track``; sent at ``sent`` unless given)."""

    command_id: int
    kind: str
    summary: str
    sent: float
    message: m.Message
    roi_key: int | None = None
    #: who sent it: the signed-in operator ("" for a console without sign-in)
    by: str = ""
    #: why the vehicle answered as it did, in words (a rejection's likely cause)
    reason: str = ""
    #: its state (None when made: sent at ``sent``)
    track: Tracked[None] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.track is None:
            self.track = Tracked(None)
            self.track.apply(Event.SEND, self.sent)

    @property
    def status(self) -> str:
        """The command as the page lists it: the vehicle's answer (lower case) once there is
        one, else the tracker's state."""
        t = self.track
        if t.answer and t.state in (State.PENDING, State.DONE, State.REFUSED):
            return t.answer.lower()
        return t.state.value

    @property
    def answered(self) -> float | None:
        """When the vehicle answered (None: not yet)."""
        return self.track.answered_at

"""The one request/command tracker of CoEx: the states a request or command topside sent goes
through, in one table (:data:`TRANSITIONS`), as h11's ``_state.py`` keeps a connection's.

Every tracked request or command is a :class:`Tracked` entry. What happens to it is an
:class:`Event`; the table says the state it leads to:

=============  ========================================================================
state          meaning
=============  ========================================================================
``queued``     recorded, not sent yet (waiting for a slot on the uplink)
``sent``       sent (or sent again); its answer has not come
``pending``    answered, not finished: it stands on the vehicle (a ``PENDING``
               ``CommandAck``; a map region whose subgrids are on their way or not
               surveyed yet)
``done``       answered for good: accepted (``ACCEPTED``) or what it asked for arrived
``refused``    refused by the vehicle (``answer`` says how: ``REJECTED``,
               ``UNKNOWN_TARGET``, ``UNAUTHENTICATED``)
``no answer``  given up: sent as often as allowed and never answered
``aborted``    withdrawn before it finished (by topside, or replaced)
=============  ========================================================================

``done``, ``refused``, ``no answer`` and ``aborted`` are final: nothing in them is sent or
awaited again. An event the table does not list for the current state is **ignored** (the state
stays and :meth:`Tracked.apply` returns None): over a lossy, slow link a late or repeated answer
is normal, and it must never change what a command already ended as (command ids wrap at 256: an
old answer must not land on a newer command). That is the one difference from h11, which raises.
The one exception is ``no answer``: it says only that no answer came in time, so an answer that
comes after all is taken (the vehicle did act on it: the ship must show what it did).

Sans-I/O: time comes in as ``now``; nothing here reads a clock. The retrying trackers built on
it: :class:`coex_core.requests.RequestTracker` (fixed retry and try count), the bathymetry
receiver's regions (a retry time per answer), the channel manager's commands and the console's
command list (:mod:`coex_apps.console.commands`).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Generic, TypeVar

from .state import persistent

__all__ = ["FINAL", "OPEN", "TRANSITIONS", "Event", "State", "Tracked", "answer_event"]

M = TypeVar("M")


@persistent("core.TrackState")
class State(enum.Enum):
    """Where a tracked request or command is (the words are what a page shows)."""

    QUEUED = "queued"
    SENT = "sent"
    PENDING = "pending"
    DONE = "done"
    REFUSED = "refused"
    NO_ANSWER = "no answer"
    ABORTED = "aborted"


class Event(enum.Enum):
    """What can happen to a tracked request or command."""

    #: it went out (again)
    SEND = "send"
    #: the vehicle answered that it stands (PENDING; a region's data on its way or not surveyed)
    STAND = "stand"
    #: the vehicle accepted it, or what it asked for arrived
    ACCEPT = "accept"
    #: the vehicle refused it
    REFUSE = "refuse"
    #: sent as often as allowed, never answered
    GIVE_UP = "give up"
    #: withdrawn by topside (or replaced by a newer one)
    ABORT = "abort"


#: state -> event -> the state it leads to. The one table of CoEx's request and command states.
TRANSITIONS: dict[State, dict[Event, State]] = {
    State.QUEUED: {
        Event.SEND: State.SENT,
        Event.ACCEPT: State.DONE,  # what it asks for came before it went out
        Event.ABORT: State.ABORTED,
    },
    State.SENT: {
        Event.SEND: State.SENT,
        Event.STAND: State.PENDING,
        Event.ACCEPT: State.DONE,
        Event.REFUSE: State.REFUSED,
        Event.GIVE_UP: State.NO_ANSWER,
        Event.ABORT: State.ABORTED,
    },
    State.PENDING: {
        Event.SEND: State.SENT,  # asked again: the answer to the new copy decides
        Event.STAND: State.PENDING,  # the same answer again (every copy is answered)
        Event.ACCEPT: State.DONE,
        Event.REFUSE: State.REFUSED,
        Event.GIVE_UP: State.NO_ANSWER,
        Event.ABORT: State.ABORTED,
    },
    State.DONE: {},
    State.REFUSED: {},
    State.NO_ANSWER: {  # an answer that comes after all
        Event.STAND: State.PENDING,
        Event.ACCEPT: State.DONE,
        Event.REFUSE: State.REFUSED,
    },
    State.ABORTED: {},
}

#: states still sent or awaited
OPEN = frozenset((State.QUEUED, State.SENT, State.PENDING))
#: states a request or command ends in (nothing more is sent; only ``no answer`` takes a late
#: answer)
FINAL = frozenset(TRANSITIONS) - OPEN

_ANSWERED = frozenset((Event.STAND, Event.ACCEPT, Event.REFUSE))


def answer_event(status: str) -> Event:
    """The event of a ``CommandAck`` status (an :class:`~coex_core.messages.AckStatus` name):
    ``ACCEPTED`` accepts, ``PENDING`` stands, anything else refuses."""
    if status == "ACCEPTED":
        return Event.ACCEPT
    if status == "PENDING":
        return Event.STAND
    return Event.REFUSE


@persistent("core.Pending", version=2,
            upgrade=lambda fields, saved: {
                "state": State.SENT if fields.get("tries") else State.QUEUED,
                "due_at": -math.inf, "answered_at": None, "answer": "", **fields})
@dataclass
class Tracked(Generic[M]):
    """One tracked request or command: its message, its :class:`State`, when it was last sent
    (None: not yet) and how often, when it is due to go out again (``due_at``), when it was last
    answered and how (``answer``: the vehicle's status name, when it gave one).

    Saved as ``core.Pending`` (the name of version 1, which held ``message``, ``sent_at`` and
    ``tries``; its state comes from ``tries``)."""

    message: M
    state: State = State.QUEUED
    sent_at: float | None = None
    tries: int = 0
    due_at: float = -math.inf
    answered_at: float | None = None
    answer: str = ""

    @property
    def open(self) -> bool:
        """Whether it may still change (queued, sent or pending)."""
        return self.state in OPEN

    def apply(self, event: Event, now: float, *, answer: str | None = None,
              due: float | None = None) -> State | None:
        """Take ``event`` at ``now``: the state :data:`TRANSITIONS` leads to, or None when the
        table lists no such move (ignored: a late or repeated answer). A send counts a try and
        stamps ``sent_at``; an answer stamps ``answered_at`` and keeps ``answer``; ``due`` (when
        given) is when it goes out again."""
        new = TRANSITIONS[self.state].get(event)
        if new is None:
            return None
        self.state = new
        if event is Event.SEND:
            self.sent_at = now
            self.tries += 1
        elif event in _ANSWERED:
            self.answered_at = now
            if answer is not None:
                self.answer = answer
        if due is not None:
            self.due_at = due
        return new

    def send(self, now: float, retry: float) -> State | None:
        """It goes out now and, unanswered, again ``retry`` seconds later."""
        return self.apply(Event.SEND, now, due=now + retry)

    def is_due(self, now: float) -> bool:
        """Whether it should go out now: open, and its time came (or the clock went back
        before its last send)."""
        return self.state in OPEN and (now >= self.due_at or (self.sent_at is not None and now < self.sent_at))

"""The survey modality's conformance inputs (entry point ``coex.conformance: survey``): what its
autonomy reports of the vehicle's own missions (sample inputs), a survey command sent at the
start, and convergence: topside knows the newest state of every survey the vehicle holds."""

from __future__ import annotations

from typing import Any

from coex import ModalityReceiver, ModalitySender
from coex.messages import SurveyReason, SurveyState
from coex_conformance.companions import Companion


def survey_inputs() -> list[tuple[float, Any]]:
    from .plan import SurveyReport

    return [(10.0, SurveyReport(900, SurveyState.STARTED, 10.0, index=0)),
            (20.0, SurveyReport(900, SurveyState.STARTED, 20.0, index=1)),
            (30.0, SurveyReport(900, SurveyState.COMPLETED, 30.0)),
            (40.0, SurveyReport(901, SurveyState.ABORTED, 40.0, SurveyReason.AUTONOMY_STOPPED))]


def survey_start(receiver: ModalityReceiver, now: float) -> None:
    from . import SurveyReceiver

    assert isinstance(receiver, SurveyReceiver)
    receiver.request("lawnmower", 50.0, -20.0, now, heading=30.0, length=80.0, width=40.0, spacing=10.0,
                     altitude=5.0)


def survey_converged(sender: ModalitySender, receiver: ModalityReceiver) -> bool:
    """Topside holds the newest state of every survey the vehicle holds."""
    from . import SurveyReceiver, SurveySender

    assert isinstance(sender, SurveySender) and isinstance(receiver, SurveyReceiver)
    for sid, s in sender.surveys.items():
        rec = receiver.surveys.get(sid)
        if rec is None or rec.state != s.state.name.lower() or rec.index != s.index:
            return False
    return bool(sender.surveys)


def companion() -> Companion:
    """Entry point ``coex.conformance: survey``."""
    from . import SurveyModality

    return Companion("survey", SurveyModality, survey_inputs, survey_converged, start_requests=survey_start)

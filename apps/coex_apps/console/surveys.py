"""The console's surveys: the survey receiver's records (what was asked, what the vehicle and
its autonomy answered) as the page lists and draws them, and their lines in the event log.

A part of :class:`~coex_apps.console.state.ConsoleState` (its API is the state's).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from coex import Product
from coex_plugins.survey import SurveyReceiver

from .words import _num

__all__ = ["MAX_SURVEYS", "SURVEY_OUTCOMES", "SURVEY_STATES", "SurveysView"]

#: The states of a survey the page draws (the survey receiver's ``SurveyRecord.state``).
SURVEY_STATES = ("requested", "accepted", "started", "completed", "rejected", "aborted", "given up")
#: The surveys the page lists and draws (the newest).
MAX_SURVEYS = 40
#: How a finished survey reads in the list and on the map when the state alone would hide what
#: happened: (state, reason) -> words. A refusal by the autonomy (autopilot, helm, planner) is
#: not the vehicle's own checks, an autonomy that never answered did not refuse anything, and an
#: abort says who stopped it. Anything else reads as its state ("rejected" by the geofence or a
#: limit, "completed", "given up": no answer from the vehicle over the link).
SURVEY_OUTCOMES = {
    ("rejected", "AUTONOMY_REFUSED"): "refused by autonomy",
    ("rejected", "AUTONOMY_NO_ANSWER"): "no answer from autonomy",
    ("rejected", "NO_AUTONOMY"): "no autonomy",
    ("rejected", "UNAUTHENTICATED"): "not authenticated",
    ("aborted", "SUPERSEDED"): "replaced",
    ("aborted", "AUTONOMY_STOPPED"): "stopped by autonomy",
    ("aborted", "MANUAL_OVERRIDE"): "taken over",
    ("aborted", "AUTONOMY_RESTARTED"): "autonomy restarted",
    ("aborted", "ALL_STOP"): "all-stop",
    ("aborted", "AUTONOMY_SILENT"): "autopilot silent",
}


class SurveysView:
    """The surveys part of :class:`~coex_apps.console.state.ConsoleState`."""

    @property
    def survey_receiver(self) -> Any:
        """The survey receiver (``coex_plugins.survey.SurveyReceiver``) that sends the operator's
        survey requests and follows them (None: this console cannot ask for surveys)."""
        return self.receivers.get("survey")

    def _survey_product(self, product: Product, meta: dict[str, Any], now: float) -> None:
        """A survey changed state (the survey receiver's product): shown in the surveys
        section, and in the event log with its reason in words."""
        try:
            sid = int(meta.get("survey_id", product.key))
        except (TypeError, ValueError):
            return
        if self.survey_receiver is None:  # nobody holds the records: keep what we were told
            self.survey_products[sid] = dict(meta)
        self._log_survey(sid, meta, now)
        self._survey_sig = None  # shown again at once
        self._touch("surveys", "commands")

    def _log_survey(self, sid: int, meta: Mapping[str, Any], now: float) -> None:
        """One event-log line per state the survey receiver added to the survey's history (the
        present state, or an older one that arrived late), at its time. The history is the
        receiver's, in the vehicle's time order; nothing is re-sorted here. The present state
        reads as its outcome ("survey 3 no answer from autonomy: ...")."""
        history = [(float(h[0]), str(h[1]), str(h[2] or "")) for h in meta.get("history") or ()]
        if not history:  # a receiver without a history: the present state
            history = [(float(meta.get("time") or now), str(meta.get("state", "")), str(meta.get("text") or ""))]
        present = (str(meta.get("state", "")), str(meta.get("text") or ""))
        seen = self._survey_logged.get(sid)
        if seen is None:  # first heard of: its present state (its request was logged when sent)
            new = [h for h in history if (h[1], h[2]) == present][-1:]
        else:
            new = [h for h in history if h not in seen]
        self._survey_logged[sid] = history
        while len(self._survey_logged) > 2 * MAX_SURVEYS:
            del self._survey_logged[next(iter(self._survey_logged))]
        for t, state, text in new:
            label = SURVEY_OUTCOMES.get((state, str(meta.get("reason"))), state) if (state, text) == present else state
            bad = state in ("rejected", "aborted", "given up")
            self._log(t, f"survey {sid} {label}" + (f": {text}" if text else ""), "warn" if bad else "info")

    def refresh_surveys(self) -> bool:
        """Look at the survey receiver's records (a request made by someone else, a survey given
        up for want of an answer): True, and the surveys section changed, if they did."""
        rx = self.survey_receiver
        if not isinstance(rx, SurveyReceiver):
            return False
        sig = tuple((int(k), int(r.version), str(r.state)) for k, r in list(rx.surveys.items()))
        if sig == self._survey_sig:
            return False
        self._survey_sig = sig
        self._touch("surveys", "commands")
        return True

    def _survey_metas(self) -> dict[int, dict[str, Any]]:
        """survey id -> the survey receiver's product metadata (cached per record version)."""
        rx = self.survey_receiver
        if not isinstance(rx, SurveyReceiver):
            return dict(self.survey_products)
        records = rx.surveys
        out: dict[int, dict[str, Any]] = {}
        rows: dict[int, tuple[int, dict[str, Any]]] = {}
        stale = [k for k, r in records.items()
                 if self._survey_rows.get(int(k), (None,))[0] != r.version]
        fresh = ({int(p.key): dict(p.meta) for p in rx.products() if str(p.key).isdigit()}
                 if stale else {})
        for k, r in records.items():
            k = int(k)
            version = int(r.version)
            cached = self._survey_rows.get(k)
            meta = fresh.get(k) if cached is None or cached[0] != version else cached[1]
            if meta is None:
                continue
            rows[k] = (version, meta)
            out[k] = meta
        self._survey_rows = rows
        return out

    def _snap_surveys(self) -> dict[str, Any]:
        """Every survey asked (the newest :data:`MAX_SURVEYS`): its path (``waypoints``, metres
        east/north), its state and, for a rejection or an abort, the reason in words."""
        items = []
        for sid, meta in self._survey_metas().items():
            history = [[_num(float(t), 1), str(st), str(tx)] for t, st, tx in meta.get("history") or ()]
            requested = history[0][0] if history else _num(meta.get("time"), 1)
            wps = [[_num(float(a), 2), _num(float(b), 2)] for a, b in meta.get("waypoints") or ()]
            state, reason = meta.get("state"), meta.get("reason")
            row = {"survey_id": sid, "kind": meta.get("kind"), "state": state,
                   "outcome": SURVEY_OUTCOMES.get((str(state), str(reason)), state),
                   "text": meta.get("text") or "", "reason": reason,
                   "index": meta.get("index"), "time": _num(meta.get("time"), 1),
                   "requested": requested, "history": history, "waypoints": wps}
            for k in ("heading", "length", "width", "spacing", "altitude", "depth", "speed"):
                v = meta.get(k)
                row[k] = _num(float(v), 2) if isinstance(v, int | float) else None
            row["append"] = bool(meta.get("append", False))
            items.append(row)
        items.sort(key=lambda r: (r["requested"] or 0.0, r["survey_id"]))
        # whether the page may ask for surveys (a node's survey receiver sends them)
        available = self.survey_receiver is not None and not self.own_receivers
        return {"items": items[-MAX_SURVEYS:], "available": available,
                "states": list(SURVEY_STATES)}

"""The survey modality passes the CoEx modality conformance suite, on the inputs it registers
for `coex plugins check survey` (coex_plugins.survey.conformance: one source of truth)."""

from __future__ import annotations

from coex_conformance.check import suite_class

TestSurveyModality = suite_class("survey")

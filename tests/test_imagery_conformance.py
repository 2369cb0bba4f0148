"""The imagery modality passes the CoEx modality conformance suite, on the inputs it registers
for `coex plugins check imagery` (coex_plugins.imagery.conformance: one source of truth)."""

from __future__ import annotations

from coex_conformance.check import suite_class

TestImageryConformance = suite_class("imagery")

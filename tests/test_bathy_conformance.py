"""The bathymetry modality passes the CoEx modality conformance suite, on the inputs it registers
for `coex plugins check bathymetry` (coex_plugins.bathymetry.conformance: one source of truth)."""

from __future__ import annotations

from coex_conformance.check import suite_class

TestBathymetryConformance = suite_class("bathymetry")

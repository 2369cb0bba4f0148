"""The timeseries modality passes the CoEx modality conformance suite, on the inputs it registers
for `coex plugins check timeseries` (coex_plugins.timeseries.conformance: one source of truth)."""

from __future__ import annotations

from coex_conformance.check import suite_class

TestTimeSeriesModality = suite_class("timeseries")

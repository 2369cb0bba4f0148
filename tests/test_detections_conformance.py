"""The detections modality passes the CoEx modality conformance suite, on the inputs it
registers for `coex plugins check detections` (coex_plugins.detections.conformance)."""

from __future__ import annotations

from coex_conformance.check import suite_class

TestDetectionsModality = suite_class("detections")

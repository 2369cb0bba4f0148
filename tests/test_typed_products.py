"""Typed products (issue 53): each built-in product kind is a frozen dataclass the console, the
exports and the ROS view read by attribute; ``meta`` is made from the fields; a third-party
modality's generic product still reaches the console's generic panel; a console saved with
survey products as dicts (state version 2) loads them typed."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from coex import Product, TypedProduct
from coex import messages as m
from coex.state import dumps, loads
from coex_apps.console import ConsoleState
from coex_apps.console.state import _upgrade_state
from coex_apps.console.testing import feed_sample
from coex_plugins.bathymetry import MapLevel
from coex_plugins.detections import DetectionsProduct
from coex_plugins.imagery import ImageProduct, ProgressProduct
from coex_plugins.survey import SurveyProduct, SurveyReceiver
from coex_plugins.timeseries import SeriesProduct

from . import _products as typed

T0 = 36000.0


def test_the_built_in_receivers_make_typed_products_whose_meta_is_their_fields() -> None:
    st = ConsoleState()
    made = feed_sample(st, t0=T0, images=1)
    bathy = st.receivers["bathymetry"]
    level = bathy.level_product(min(bathy.levels()))
    assert isinstance(level, MapLevel) and level.kind == "map-level"
    assert level.meta["cell_size"] == level.cell_size == level.level_cell * level.step
    assert (level.zmin is None) == (level.zmax is None) and level.zmin is not None
    series = [p for p in made["series_receiver"].products()]
    assert series and all(isinstance(p, SeriesProduct) and p.meta["channel"] == p.channel for p in series)
    images = made["image_receiver"].products()
    assert any(isinstance(p, ImageProduct) for p in images)
    assert all(isinstance(p, ImageProduct | ProgressProduct) for p in images if p.kind in ("image", "image-progress"))
    image = next(p for p in images if isinstance(p, ImageProduct))
    fields = {f.name for f in dataclasses.fields(image)} - {"kind", "key", "version", "data", "meta"}
    assert set(image.meta) == fields and image.meta["image_id"] == image.image_id
    with pytest.raises(dataclasses.FrozenInstanceError):
        image.image_id = 3  # type: ignore[misc]
    with pytest.raises(TypeError):  # meta is made, not given
        MapLevel("map-level", "level-0", 1, None, {"x0": 1.0})  # type: ignore[call-arg, misc]


def test_a_survey_product_keeps_kind_in_its_meta_and_the_console_reads_it() -> None:
    rx = SurveyReceiver()
    st = ConsoleState(receivers={"survey": rx})
    cmd = rx.request("goto", 10.0, 5.0, T0)
    (p,) = rx.receive(m.CommandAck(cmd.command_id, m.AckStatus.ACCEPTED), T0 + 5)
    assert isinstance(p, SurveyProduct) and p.kind == "survey" and p.survey_kind == "goto"
    assert p.meta["kind"] == "goto" and "survey_kind" not in p.meta
    st.apply_product("survey", p, T0 + 5)
    (row,) = st.snapshot()["surveys"]["items"]
    assert (row["kind"], row["state"], row["waypoints"][-1]) == ("goto", "accepted", [10.0, 5.0])
    assert rx.view(p) == {"survey": cmd.survey_id, "kind": "goto", "state": "accepted", "why": ""}


def test_a_generic_product_of_a_third_party_modality_reaches_the_generic_panel() -> None:
    st = ConsoleState(receivers={})
    st.apply_product("ctd", Product("cast", "cast", 2, [(0, 1.0)], {"samples": 1, "deepest": 1.5}), T0)

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class CastProduct(TypedProduct):
        samples: int

    st.apply_product("adcp", CastProduct("cast", "c1", 1, None, samples=4), T0)
    other = {o["name"]: o["products"] for o in st.snapshot()["other"]["modalities"]}
    assert other["ctd"][0]["fields"] == {"samples": 1, "deepest": 1.5}
    assert other["adcp"][0]["fields"] == {"samples": 4} and other["adcp"][0]["version"] == 1


def test_an_untyped_product_of_a_built_in_kind_is_not_read_by_string_keys() -> None:
    """The console dispatches on the product's type: a generic ``map-level`` product (as made
    before products were typed) changes nothing, the typed one sets the colour scale."""
    st = ConsoleState()
    z = np.array([[-30.0, -20.0]])
    st.apply_product("bathymetry", Product("map-level", "level-0", 1, z, {"zmin": -30.0, "zmax": -20.0}), T0)
    assert st.snapshot()["map"]["zrange"] is None
    st.apply_product("bathymetry", typed.map_level(0, z, zmin=-30.0, zmax=-20.0), T0)
    assert st.snapshot()["map"]["zrange"] == [-30.0, -20.0]


def test_detections_product_is_typed() -> None:
    from coex_plugins.detections import DetectionsReceiver

    rx = DetectionsReceiver()
    (p,) = rx.products() or [rx._product()]
    assert isinstance(p, DetectionsProduct) and p.count == len(p.data) and p.meta == {"count": p.count}


def _survey_meta() -> dict[str, Any]:
    return {"survey_id": 4, "state": "rejected", "text": "outside the geofence", "reason": "GEOFENCE",
            "index": None, "time": T0, "history": [[T0 - 5, "requested", ""], [T0, "rejected", "outside"]],
            "kind": "lawnmower", "waypoints": [[0, 0], [10, 0]], "heading": 90.0, "length": 10,
            "width": None, "spacing": None, "altitude": 5.0, "depth": None, "speed": 1.0, "append": False}


def test_survey_products_saved_as_dicts_load_typed_and_typed_ones_survive_a_save() -> None:
    up = _upgrade_state({"log": [], "survey_products": {4: _survey_meta()}}, 2)["survey_products"][4]
    assert isinstance(up, SurveyProduct)
    assert (up.survey_id, up.state, up.survey_kind, up.waypoints, up.length) == (
        4, "rejected", "lawnmower", [[0.0, 0.0], [10.0, 0.0]], 10.0)
    st = ConsoleState()  # no survey receiver held: the console keeps what it is told
    st.survey_products[4] = up
    back = loads(dumps(st))
    assert back.survey_products[4] == up and back.survey_products[4].meta["kind"] == "lawnmower"
    (row,) = back.snapshot()["surveys"]["items"]
    assert (row["kind"], row["outcome"], row["length"]) == ("lawnmower", "rejected", 10.0)

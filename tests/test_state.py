"""coex_core.state: the explicit state format (never pickle)."""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from coex_core import messages as m
from coex_core.state import StateError, dumps, loads, persistent


@persistent("test.Box")
class Box:
    def __init__(self, value: Any) -> None:
        self.value = value


@persistent("test.Hooked", transient=("callback",))
class Hooked:
    def __init__(self, value: Any) -> None:
        self.value = value
        self.callback = print  # not state: rebuilt after a restore

    def _after_restore(self) -> None:
        self.callback = print


class Careless:
    def __init__(self) -> None:
        self.callback = print


persistent("test.Careless")(Careless)  # registered, but its callback is not declared transient


@persistent("test.Point", version=2, upgrade=lambda f, v: {**f, "z": 0.0} if v < 2 else f)
@dataclass(frozen=True)
class Point:
    x: float
    y: float
    z: float = 0.0


class Unknown:
    pass


def test_values_round_trip() -> None:
    value = {
        "none": None, "flag": True, "n": -3, "x": 1.5, "nan": float("nan"), "inf": float("-inf"),
        "text": "é", "list": [1, [2]], "tuple": (1, 2), "set": {3, 4}, "frozen": frozenset({5}),
        "deque": deque([1, 2], maxlen=5), "od": OrderedDict([("b", 1), ("a", 2)]),
        (1, 2): "tuple key", 7: "int key", "bytes": b"\x00\xff", "ba": bytearray(b"ab"),
        "array": np.arange(12, dtype=np.int16).reshape(3, 4), "scalar": np.float32(2.5),
        "message": m.QueueStatus(5, (m.StreamStatus(3, True, 1, 30, 2, 100, 7, 0),)),
        "enum": m.AckStatus.REJECTED,
        # lists of plain values are written whole; anything else in one is visited
        "plain": [1, 2.5, "a", None, True], "plain_tuple": (3, -4), "inf_tuple": (1.0, float("inf")),
        "enum_tuple": (m.AckStatus.REJECTED, 1), "numpy_list": [np.int64(3), 4],
    }
    back = loads(dumps(value))
    assert np.isnan(back.pop("nan")) and np.isnan(value.pop("nan"))
    arr = back.pop("array")
    assert arr.dtype == np.int16 and (arr == value.pop("array")).all()
    assert back == value
    assert type(back["deque"]) is deque and back["deque"].maxlen == 5
    assert list(back["od"]) == ["b", "a"] and type(back["scalar"]) is np.float32
    assert type(back["ba"]) is bytearray and back["enum"] is m.AckStatus.REJECTED
    assert back["enum_tuple"][0] is m.AckStatus.REJECTED and type(back["numpy_list"][0]) is np.int64


def test_shared_objects_stay_shared_and_cycles_work() -> None:
    image = np.zeros((480, 640, 3), np.uint8)  # a receiver's image that the console shows too
    data = dumps({"receiver": image, "console": image})
    assert len(data) < image.nbytes * 1.1  # written once
    back = loads(data)
    assert back["receiver"] is back["console"]
    inner = Box([1, 2])
    outer = Box({"a": inner, "b": inner})
    inner.value.append(outer)  # a cycle
    back = loads(dumps(outer))
    assert back.value["a"] is back.value["b"]
    assert back.value["a"].value[2] is back


def test_transient_attributes_are_not_saved_and_are_rebuilt() -> None:
    b = Hooked(1)
    b.callback = lambda: None
    back = loads(dumps(b))
    assert back.callback is print and back.value == 1


class _Saving:
    """Declares both persistence hooks; they log into ``calls``."""

    calls: list[tuple[str, int]] = []

    def __init__(self, value: int) -> None:
        self.value = value

    def _before_save(self) -> None:
        self.calls.append(("save", self.value))

    def _after_restore(self) -> None:
        self.calls.append(("restore", self.value))


@persistent("test.SavingChild")
class SavingChild(_Saving):
    """Inherits both hooks from an unregistered base: still declared."""


@persistent("test.Plain")
class Plain:
    def __init__(self) -> None:
        self.value = 3


def test_persistence_hooks_are_declared_by_the_class_and_recorded_once() -> None:
    """``_before_save`` / ``_after_restore`` are the class's declared protocol: recorded when
    ``@persistent`` registers it, not looked up on each object; an instance attribute of that
    name is not a hook, and a non-method of that name is refused at registration."""
    from coex_core.state import _BY_NAME

    assert (_BY_NAME["test.SavingChild"].before_save, _BY_NAME["test.SavingChild"].after_restore) == (True, True)
    assert (_BY_NAME["test.Hooked"].before_save, _BY_NAME["test.Hooked"].after_restore) == (False, True)
    assert (_BY_NAME["test.Plain"].before_save, _BY_NAME["test.Plain"].after_restore) == (False, False)
    _Saving.calls.clear()
    back = loads(dumps([SavingChild(1), SavingChild(2)]))
    assert _Saving.calls == [("save", 1), ("save", 2), ("restore", 1), ("restore", 2)]
    assert [b.value for b in back] == [1, 2]
    p = Plain()
    p.__dict__["_after_restore"] = 5  # a field of that name is a field, never called
    assert loads(dumps(p))._after_restore == 5

    class NotAHook:
        _before_save = 1

    with pytest.raises(StateError, match=r"NotAHook._before_save is not a method"):
        persistent("test.NotAHook")(NotAHook)
    assert "test.NotAHook" not in _BY_NAME


def test_unregistered_types_are_refused_with_where_they_were() -> None:
    with pytest.raises(StateError, match=r"root\['x'\]\[1\]: a .*Unknown is not registered"):
        dumps({"x": [1, Unknown()]})
    with pytest.raises(StateError, match="callback"):
        dumps(Careless())  # its callback is a function: not state, and not declared transient
    with pytest.raises(StateError, match="objects"):
        dumps(np.array([object()], dtype=object))


def test_versions_upgrade_older_and_refuse_newer() -> None:
    data = dumps(Point(1.0, 2.0, 3.0))
    assert loads(data) == Point(1.0, 2.0, 3.0)
    older = data.replace(b'"test.Point":2', b'"test.Point":1')
    assert loads(older) == Point(1.0, 2.0, 0.0)  # upgraded from version 1
    newer = data.replace(b'"test.Point":2', b'"test.Point":3')
    with pytest.raises(StateError, match="newer"):
        loads(newer)
    with pytest.raises(StateError, match="does not know"):
        loads(data.replace(b'"test.Point"', b'"test.Gone!"'))


def test_corrupt_or_foreign_data_is_a_state_error() -> None:
    import pickle

    with pytest.raises(StateError, match="COEXSTATE"):
        loads(pickle.dumps({"a": 1}))
    data = dumps({"a": np.arange(3)})
    for bad in (data[:20], data[:-10], data[:15] + b"x" + data[16:]):
        with pytest.raises(StateError):
            loads(bad)


class SubBox(Box):
    """A subclass of a registered class, not registered itself."""


@persistent("test.SubBoxOwn")
class SubBoxOwn(Box):
    pass


@persistent("test.FrozenSlots")
@dataclass(frozen=True, slots=True)
class FrozenSlots:
    a: int
    b: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
@persistent("test.SlotsBelow")
class SlotsBelow:  # @persistent below @dataclass(slots=True): the class registered is not this one
    a: int


@dataclass(frozen=True)
@persistent("test.FrozenBelow")
class FrozenBelow:  # without slots, @dataclass keeps the class: either order works
    a: int


def test_registration_is_not_inherited_and_the_error_says_so() -> None:
    """docs/plugins.md: a subclass of a registered sender needs a name of its own; the error
    names the registered base class and says so."""
    with pytest.raises(StateError, match=r"SubBox is not registered state .*its base class Box is registered as "
                                         r"'test.Box', but @persistent is not inherited"):
        dumps(SubBox(1))
    back = loads(dumps(SubBoxOwn(2)))
    assert type(back) is SubBoxOwn and back.value == 2


def test_frozen_and_slotted_dataclasses_are_state_with_persistent_outermost() -> None:
    """docs/plugins.md: @persistent works on frozen dataclasses (slots too) when it is the
    outermost decorator, above @dataclass; below @dataclass(slots=True) it registered a class
    that @dataclass then replaced, and the error says where to put it."""
    assert loads(dumps(FrozenSlots(1, (2, 3)))) == FrozenSlots(1, (2, 3))
    assert loads(dumps(FrozenBelow(4))) == FrozenBelow(4)
    with pytest.raises(StateError, match=r"put @persistent above @dataclass"):
        dumps(SlotsBelow(5))

"""Hypothesis strategies derived from the construct schemas themselves (so they follow any schema change)."""

from __future__ import annotations

from typing import Any

import construct as cs
from hypothesis import strategies as st

from coex_core._wire import _primitives as P
from coex_core._wire._codec import _from_container
from coex_core._wire._registry import SPECS_BY_ID, MessageSpec
from coex_core._wire._subgrid_code import CodedCells, encode_cells, table_for
from coex_core._wire.bathymetry import MAX_PREDICTED_CELL_BITS, ArithCells
from coex_core.messages import Message

MAX_LIST = 6


def _eval(expr: Any, ctx: cs.Container) -> Any:
    return expr(ctx) if callable(expr) else expr


def _unwrap(con: Any) -> Any:
    while isinstance(con, cs.Renamed):
        con = con.subcon
    return con


def _draw_field(draw: Any, con: Any, ctx: cs.Container) -> Any:
    con = _unwrap(con)
    if isinstance(con, P.Bounded):
        k = draw(st.integers(0, con.steps))
        value = con._decode(k + (1 if con.optional else 0), ctx, "")
        if con.optional and draw(st.booleans()):
            return None
        return value
    if isinstance(con, P.SInt):
        return draw(st.integers(-(1 << (con.bits - 1)), (1 << (con.bits - 1)) - 1))
    if isinstance(con, P.Bool):
        return draw(st.booleans())
    if isinstance(con, P.OptBool):
        return draw(st.sampled_from([None, False, True]))
    if isinstance(con, P.Enum):
        return draw(st.sampled_from(list(con.enum_cls)))
    if isinstance(con, P.Choice):
        return draw(st.sampled_from(con.table))
    if isinstance(con, P.UInt):
        return draw(st.integers(0, (1 << con._width(ctx)) - 1))
    if isinstance(con, P._Float32):
        return draw(st.floats(width=32, allow_nan=False, allow_infinity=False))
    if isinstance(con, P._Text):
        return draw(st.text(max_size=con.max_len).filter(lambda s: len(s.encode()) <= con.max_len))
    if isinstance(con, cs.Transformed | cs.Restreamed):
        inner = _unwrap(con.subcon)
        if isinstance(inner, P._MaxLen):
            return draw(st.binary(max_size=inner.max_len))
        if isinstance(inner, cs.Bytes):
            n = _eval(inner.length, ctx)
            return draw(st.binary(min_size=n, max_size=n))
    if isinstance(con, cs.IfThenElse):
        return _draw_field(draw, con.thensubcon, ctx) if _eval(con.condfunc, ctx) else None
    if isinstance(con, ArithCells):  # presence (when partial) and residuals, small or huge
        n = int(ctx.side) ** 2
        mask = draw(st.integers(0, (1 << n) - 1)) if ctx.partial else None
        count = n if mask is None else mask.bit_count()
        big = st.integers(-(1 << 20), (1 << 20))
        return {"mask": mask, "residuals": draw(st.lists(st.one_of(st.integers(-4, 4), big), min_size=count,
                                                        max_size=count))}
    if isinstance(con, cs.Rebuild):  # a derived count under a condition: choose the length here
        sub = _unwrap(con.subcon)
        return draw(st.integers(sub.lo, min(sub.hi, sub.lo + MAX_LIST)))
    if isinstance(con, cs.Array):
        n = _eval(con.count, ctx)
        return [_draw_element(draw, con.subcon, ctx) for _ in range(n)]
    raise TypeError(f"no strategy for {con!r}")


def _draw_element(draw: Any, con: Any, ctx: cs.Container) -> Any:
    inner = _unwrap(con)
    if isinstance(inner, cs.Struct):
        return _draw_struct(draw, inner, ctx)
    return _draw_field(draw, inner, ctx)


def _draw_struct(draw: Any, struct: Any, parent: cs.Container | None = None) -> cs.Container:
    ctx = cs.Container()
    ctx._ = parent
    for sc in struct.subcons:
        name = getattr(sc, "name", None)
        inner = _unwrap(sc)
        if isinstance(inner, P.Align8 | cs.Check | cs.Padded) or name is None:
            continue
        if isinstance(inner, cs.Rebuild):
            sub = _unwrap(inner.subcon)
            if isinstance(sub, P.Bounded):  # a derived count: choose the array length here
                ctx[name] = draw(st.integers(sub.lo, min(sub.hi, sub.lo + MAX_LIST)))
            else:
                ctx[name] = draw(st.booleans())
            continue
        ctx[name] = _draw_field(draw, inner, ctx)
    return ctx


def _body_struct(spec: MessageSpec) -> Any:
    con = spec.body
    while not isinstance(con, cs.Struct):
        con = con.subcon
    return con


def _fragment_rule(ctx: cs.Container) -> None:
    """ImageFragment: packet starts strictly increase and stay within the data (a rule of the
    spec that random fields almost never meet)."""
    marks = sorted({min(int(p), len(ctx.data)) for p in ctx.packets or ()})
    ctx.packets = marks
    ctx.marked = bool(marks)
    ctx.n_packets = len(marks) if marks else None
    if marks and ctx.packet is None:
        ctx.packet = 0
    if not marks:
        ctx.packet = None


def _region_rule(ctx: cs.Container) -> None:
    """ImageRegionRequest: the region is not empty."""
    ctx.x0, ctx.x1 = min(ctx.x0, ctx.x1 - 1), max(ctx.x1, ctx.x0 + 1)
    ctx.y0, ctx.y1 = min(ctx.y0, ctx.y1 - 1), max(ctx.y1, ctx.y0 + 1)


def _survey_rule(ctx: cs.Container) -> None:
    """SurveyCommand: the fields its kind needs are present, only WAYPOINTS carries points, and
    altitude and depth are not both given."""
    kind = int(ctx.kind)
    need = {1: ("heading", "length"), 2: ("heading", "length", "width", "spacing")}.get(kind, ())
    for name in need:
        if ctx[name] is None:
            ctx[name] = 10.0
    if kind != 3:
        ctx.points, ctx.n_points = [], 0
    if ctx.altitude is not None:
        ctx.depth = None


def _predicted_rule(ctx: cs.Container) -> None:
    """PredictedSubgrid: the coded cells take at most 1536 bits (residuals zeroed from the end
    until they do)."""
    res = list(ctx.cells["residuals"])
    n = int(ctx.side) ** 2
    mask = ctx.cells["mask"]
    present = None if mask is None else [bool((mask >> (n - 1 - k)) & 1) for k in range(n)]
    table = table_for(int(ctx.context) == 1, int(ctx.level))
    k = len(res)
    while k > 0 and len(encode_cells(int(ctx.side), CodedCells(present, res), int(ctx.shift), table)) \
            > MAX_PREDICTED_CELL_BITS:
        k = k * 3 // 4
        res = res[:k] + [0] * (len(res) - k)
    ctx.cells = {"mask": mask, "residuals": res}


#: per message type, the rules a drawn message is made to follow (the table's "MUST reject when")
_RULES: dict[str, Any] = {"ImageFragment": _fragment_rule, "SurveyCommand": _survey_rule,
                          "ImageRegionRequest": _region_rule, "PredictedSubgrid": _predicted_rule}


def message_strategy(spec: MessageSpec) -> st.SearchStrategy[Message]:
    struct = _body_struct(spec)

    @st.composite
    def build(draw: Any) -> Message:
        ctx = _draw_struct(draw, struct)
        fix = _RULES.get(spec.cls.__name__)
        if fix is not None:
            fix(ctx)
        return _from_container(spec.cls, ctx)  # type: ignore[no-any-return]

    return build()


ALL_SPECS = sorted(SPECS_BY_ID.values(), key=lambda s: s.type_id)
any_message = st.one_of([message_strategy(s) for s in ALL_SPECS])

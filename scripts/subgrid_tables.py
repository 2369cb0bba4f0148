"""Fit the initial probability tables of PredictedSubgrid (spec/payloads.md 1.10) on the
development scenes of bench/bathymetry.py (never on the held-out ones it reports).

Run: ``.venv/bin/python scripts/subgrid_tables.py [--quick] [--rounds N]``. Every subgrid of
every level goes through the sender as the benchmark sends them (each packet acknowledged);
each decision of each PredictedSubgrid's coded cells is counted by context, and each context's
initial probability of a 0 is its frequency, ``4096 (zeros + 1) / (all + 2)`` within 16..4080.
The first round codes with flat tables (2048 everywhere), each next round with the tables the
previous one fitted (the sender's choices depend on them); the tables in the code are those of
two rounds. Prints them as the code (``coex_core/_wire/_subgrid_code.py``) and the spec's table
write them; copying them in changes the wire format (regenerate the vectors).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))

from bathymetry import DEVELOPMENT, _scene  # noqa: E402

import coex_core._wire._subgrid_code as code  # noqa: E402
from coex.messages import PredictedSubgrid  # noqa: E402
from coex_core._wire._subgrid_code import CodedCells, Table, encode_cells, table_for  # noqa: E402
from coex_plugins.bathymetry import BathymetrySender  # noqa: E402

Counts = dict[tuple[str, int, int], list[int]]


def count(survey: Any, tables: dict[int, Counts]) -> None:
    sender = BathymetrySender({"levels": 5})
    for t, xyz in survey.pings(batch=50):
        sender.ingest(xyz, t)
    sender.map.flush(force=True)
    now = float(survey.times[-1]) + 60.0
    while out := sender.fill(240, now):
        for m in out:
            sender.acked(m, now)
            if isinstance(m, PredictedSubgrid):
                n = m.side * m.side
                mask = m.cells.mask
                present = None if mask is None else [bool((mask >> (n - 1 - k)) & 1) for k in range(n)]
                table = table_for(m.check is not None, m.level)
                encode_cells(m.side, CodedCells(present, m.cells.residuals), m.shift, table,
                             tables.setdefault(table, {}))
        now += 1.0


def p0(c: list[int]) -> int:
    zeros, ones = c
    return int(min(4080, max(16, round(4096 * (zeros + 1) / (zeros + ones + 2)))))


def fit(tables: dict[int, Counts]) -> list[Table]:
    out = []
    for t in range(4):
        c = tables.get(t, {})

        def get(kind: str, a: int, b: int = 0, c: Counts = c) -> int:
            return p0(c.get((kind, a, b), [1, 1]))

        out.append(Table([get("z", k) for k in range(4)], [[get("u", k, j) for j in range(4)] for k in range(4)],
                         get("s", 0), [get("p", k) for k in range(4)]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="256 m simulated scenes")
    ap.add_argument("--rounds", type=int, default=2, help="fitting rounds from flat tables (default 2)")
    args = ap.parse_args()
    size, beams = (256.0, 256) if args.quick else (512.0, 400)
    scenes = [(name, *_scene(kind, params, size, beams)) for name, (kind, params) in DEVELOPMENT.items()]
    fitted = [Table([2048] * 4, [[2048] * 4] * 4, 2048, [2048] * 4) for _ in range(4)]
    for r in range(args.rounds):
        code.INITIAL = tuple(fitted)  # this process only: the sender codes with these
        code._encode_cached.cache_clear()
        tables: dict[int, Counts] = {}
        for name, survey, what in scenes:
            print(f"round {r + 1}: counting {name}: {what}", file=sys.stderr)
            count(survey, tables)
        fitted = fit(tables)
    uses = ["PARENT, level 0", "PARENT, level 1", "PARENT, levels 2+", "NONE"]
    f = ", ".join
    for tab in fitted:
        print(f"    Table({list(tab.z)}, {[list(u) for u in tab.u]}, {tab.s}, {list(tab.p)}),")
    print()
    for t, tab in enumerate(fitted):
        print(f"| {t} | {uses[t]} | {f(map(str, tab.z))} | " + " | ".join(f(map(str, u)) for u in tab.u)
              + f" | {tab.s} | {f(map(str, tab.p))} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

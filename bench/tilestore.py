"""Tile store benchmark: the bathymetry plugin's stored tiles (coex_plugins.bathymetry.tilestore),
bytes and codec time per tile, for the vehicle's map, the topside receiver and its overview chunks.

Run: ``python bench/tilestore.py [--area KM2]``. Prints the numbers and writes
``bench/results/tilestore.json``.

* The survey of ``bench/scale.py`` (1 km² by default: lawnmower lines, 2 soundings per 1 m cell)
  into a vehicle's map, and every subgrid of every level to a topside receiver.
* Per kind of tile (map tile of 128 x 128 cells with its sums, receiver tile of 16 x 16
  subgrids, overview chunk of 128 x 128 cells): mean stored bytes, encode and decode time
  (best of 3 over every tile).
* Out of core: the map (32 MB budget) and the receiver (8 MB budget, tiles spilled as a survey
  goes) with NodeStore storage: bytes on disk after ``sync``, receive rate.

Measured on the 2-core machine at 1 km² (shared, so times vary by about a third), before the
tile store (commit 72f34b5: CXT1, zlib CXRT and CXOV) and with it:

| tile | before: KiB, encode / decode ms | with the tile store |
|---|---|---|
| map | 173.8, 0.63-0.68 / 0.26-0.34 | 173.9, 0.41-0.83 / 0.24-0.32 |
| receiver | 9.4, 0.35-0.48 / 0.22-0.31 | 6.5, 0.16-0.26 / 0.11-0.14 |
| overview chunk | 8.9, 0.31 / - | 6.1, 0.21 / - |

On disk: the map 12.22 MB both; the receiver 1.85 MB before, 1.28 MB with it.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.scale import survey  # noqa: E402
from coex import NodeStore  # noqa: E402
from coex_plugins.bathymetry import BathymetryReceiver, BathymetrySender, tilestore  # noqa: E402
from coex_plugins.bathymetry.tiles import decode_tile, encode_tile  # noqa: E402


def codec(items: list[Any], enc: Callable[[Any], bytes], dec: Callable[[bytes], Any]) -> dict[str, float]:
    best_e = best_d = float("inf")
    blobs: list[bytes] = []
    for _ in range(3):
        t0 = time.perf_counter()
        blobs = [enc(x) for x in items]
        best_e = min(best_e, time.perf_counter() - t0)
        t0 = time.perf_counter()
        for b in blobs:
            dec(b)
        best_d = min(best_d, time.perf_counter() - t0)
    n = max(len(items), 1)
    return {"tiles": len(items), "kib_per_tile": round(sum(map(len, blobs)) / n / 1024, 2),
            "encode_ms": round(best_e / n * 1e3, 3), "decode_ms": round(best_d / n * 1e3, 3)}


def run(area: float, workdir: Path) -> dict[str, Any]:
    vstore, tstore = NodeStore(workdir / "vehicle.db"), NodeStore(workdir / "topside.db")
    sender = BathymetrySender({"levels": 5, "memory_budget": 32 * 2**20})
    sender.attach_storage(vstore.storage().child("tx/bathymetry/"))
    t = 0.0
    for t, xyz in survey(area):
        sender.ingest(xyz, t)
    m = sender.map
    m.flush(force=True)
    m.sync()
    rx = BathymetryReceiver({"auto_fill": False, "memory_budget": 8 * 2**20})
    rx.attach_storage(tstore.storage().child("rx/bathymetry/"))
    now, sent, spent = t + 100.0, 0, 0.0
    while out := sender.fill(1 << 20, now):
        t0 = time.perf_counter()
        for msg in out:
            rx.receive(msg, now)
        spent += time.perf_counter() - t0
        sent += len(out)
    rx.sync_storage()
    # the codec on every tile (read back from the storage as the caches do)
    cells = [m._cells(n).copy() for n in range(len(m.tiles))]
    res: dict[str, Any] = {"area_km2": area}
    res["map"] = codec(cells, lambda c: m._encode_cells(0, c), lambda d: m._decode_cells(0, d))
    side = rx.tile_subgrids
    tiles = [rx._tile(lv, int(tx), int(ty)) for lv, ix in rx._index.items() for tx, ty in ix.keys[:ix.n]]
    res["receiver"] = codec(tiles, lambda x: encode_tile(x, 1), lambda d: decode_tile(d, side, 8, "bench"))
    chunks = [(ov, c) for ov in rx._overviews.values() for c in ov.chunks()]
    res["overview"] = codec(chunks, lambda oc: oc[0].encode_chunk(*oc[1], 1), tilestore.decode)
    res["map_disk_mb"] = round(m.disk_bytes() / 2**20, 2)
    res["receiver_disk_mb"] = round(rx.disk_bytes() / 2**20, 2)
    res["receive_per_s"] = round(sent / spent) if spent else None
    vstore.close()
    tstore.close()
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--area", type=float, default=1.0, help="surveyed area, km²")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "tilestore.json")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="coex-tiles-") as tmp:
        res = run(args.area, Path(tmp))
    for kind in ("map", "receiver", "overview"):
        r = res[kind]
        print(f"{kind:9s} {r['tiles']:5d} tiles  {r['kib_per_tile']:8.2f} KiB/tile  "
              f"encode {r['encode_ms']:.3f} ms  decode {r['decode_ms']:.3f} ms")
    print(f"on disk: map {res['map_disk_mb']} MB, receiver {res['receiver_disk_mb']} MB "
          f"(tiles spilled under an 8 MB budget); receive {res['receive_per_s']:,} subgrids/s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

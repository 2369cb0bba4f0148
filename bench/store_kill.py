"""The store's kill -9 loop, hundreds of times: a writer process (both nodes of the fault suite's
dive, journaling, snapshotting, spilling map tiles, deleting chunks no snapshot names) is killed
with SIGKILL at random moments; after every kill both stores must open (SQLite's page check) and
restore their nodes, read-only looks taken while the writer ran must restore too, and every dive
the writer finishes across the kills must end with topside holding everything the vehicle sent
(``tests/_store_kill.py``; ``tests/test_store_kill.py`` runs a few dozen in CI).

    python bench/store_kill.py [--kills 300] [--seed 1] [--max-alive 1.2]

Prints the counts and writes ``bench/results/store_kill.json``. Exit status 1 when anything
failed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tests._store_kill import kill_loop  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kills", type=int, default=300)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--max-alive", type=float, default=1.2,
                   help="seconds a writer lives at most after its dive moved on (default 1.2)")
    args = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="coex-store-kill-"))
    try:
        r = kill_loop(work, args.kills, seed=args.seed, max_alive=args.max_alive,
                      log=lambda t: print(t, flush=True))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = asdict(r)
    out.update(date=time.strftime("%Y-%m-%d"),
               command=f"python bench/store_kill.py --kills {args.kills} --seed {args.seed}")
    results = ROOT / "bench" / "results"
    results.mkdir(parents=True, exist_ok=True)
    (results / "store_kill.json").write_text(json.dumps(out, indent=1))
    print(f"{r.kills} kills: {r.reopened} stores reopened and restored, {r.looks} read-only looks while the "
          f"writer ran, {r.dives} dives finished and checked whole; {len(r.failures)} failures "
          f"({r.seconds:.0f} s)")
    for f in r.failures[:20]:
        print("  failure:", f)
    return 1 if r.failures else 0


if __name__ == "__main__":
    sys.exit(main())

"""``coex timeseries``: run the time-series modality on a CSV file.

``coex timeseries synth --out CSV [--hours H]`` writes the synthetic record the benchmark uses.

``coex timeseries roundtrip CSV --out DIR --budgets B1,B2,...`` reads a CSV whose first column
is ``time`` (absolute seconds) and whose other columns are channels, runs the vehicle side
(overview of every block, then successive "finer detail" refinements of the whole record as a
topside would request them) and writes:

* ``DIR/messages.jsonl``: every vehicle message in sending order, as its JSON form plus
  ``hex`` (its wire bytes), ``bytes`` (its size) and ``total`` (wire bytes up to and including it);
* ``DIR/recon_<B>.csv`` per budget: the topside reconstruction from the longest prefix of those
  messages of at most ``B`` wire bytes, at the input's times: ``time``, one column per channel,
  then ``<channel>_bound`` (the error bound; ``inf`` while a pass is incomplete; empty where
  nothing was received).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from coex import ConfigError, RoundTrip, to_json, wire
from coex.messages import Message

from . import synth
from .receiver import TimeSeriesReceiver, sample_series
from .sender import TimeSeriesSender

__all__ = ["register", "read_csv", "roundtrip"]

FRAME_PAYLOAD = 251


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("timeseries", help="time-series modality tools")
    sub = p.add_subparsers(dest="ts_command", metavar="ACTION")
    r = sub.add_parser("roundtrip", help="encode a CSV progressively and reconstruct it at byte budgets")
    r.add_argument("csv", metavar="CSV", help="columns: time, then one column per channel")
    r.add_argument("--out", required=True, metavar="DIR", help="output directory")
    r.add_argument("--budgets", required=True, metavar="B1,B2,...", help="wire-byte budgets")
    r.add_argument("--wavelet", default="bior4.4", help="haar, bior2.2, bior4.4 or db4 (default bior4.4)")
    r.add_argument("--block-samples", type=int, default=4096, help="samples per block (16..4096)")
    r.add_argument("--overview-factor", type=float, default=12.0,
                   help="overview error target in noise sigmas (default 12)")
    r.add_argument("--resolution", type=float, default=None,
                   help="sensor resolution of every channel (default: from the CSV's decimals)")
    r.set_defaults(func=_cmd_roundtrip)
    g = sub.add_parser("synth", help="write a realistic synthetic CSV (methane with spikes, temperature)")
    g.add_argument("--out", required=True, metavar="CSV", help="output file")
    g.add_argument("--hours", type=float, default=6.0, help="duration (default 6 h)")
    g.add_argument("--period", type=float, default=1.0, help="sample period in seconds (default 1)")
    g.add_argument("--jitter", type=float, default=0.0,
                   help="sample time jitter as a fraction of the period (default 0)")
    g.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    g.add_argument("--t0", type=float, default=1_700_000_000.0, help="time of the first sample")
    g.set_defaults(func=_cmd_synth)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _budgets(text: str) -> list[int]:
    try:
        budgets = [int(b) for b in text.split(",") if b.strip()]
    except ValueError as exc:
        raise ConfigError(f"--budgets must be integers separated by commas: {text!r}") from exc
    if not budgets or any(b < 0 for b in budgets):
        raise ConfigError(f"--budgets must be non-negative integers: {text!r}")
    return budgets


def read_csv(path: str | Path) -> tuple[list[str], np.ndarray, np.ndarray, list[float]]:
    """Channel names, times, values (samples x channels, NaN where empty) and each channel's
    resolution guessed from the most decimals written in its column."""
    path = Path(path)
    try:
        with path.open(newline="") as f:
            header = next(csv.reader(f))
    except (OSError, StopIteration, csv.Error) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc
    names = [h.strip() for h in header]
    if len(names) < 2 or names[0].lower() != "time":
        raise ConfigError(f"{path}: the first column must be 'time', then one column per channel")
    try:
        text = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=str, ndmin=2)
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    if text.size == 0:
        raise ConfigError(f"{path}: no samples")
    if text.shape[1] != len(names):
        raise ConfigError(f"{path}: {text.shape[1]} columns for {len(names)} names")
    text = np.char.strip(text)
    empty = text == ""
    try:
        values = np.where(empty, "nan", text).astype(np.float64)
    except ValueError as exc:
        raise ConfigError(f"{path}: not a number: {exc}") from exc
    if empty[:, 0].any() or not np.isfinite(values[:, 0]).all():
        raise ConfigError(f"{path}: every row needs a finite time")
    dot = np.char.find(text, ".")
    decimals = np.where(dot >= 0, np.char.str_len(text) - dot - 1, 0)
    decimals = np.where(empty, 0, decimals)
    resolution = [float(10.0 ** -min(int(decimals[:, j].max()), 9)) for j in range(1, len(names))]
    return names[1:], values[:, 0], values[:, 1:], resolution


def roundtrip(csv_path: str | Path, out: str | Path, budgets: list[int], *, wavelet: str = "bior4.4",
              block_samples: int = 4096, overview_factor: float = 12.0,
              resolution: float | None = None) -> dict[str, Any]:
    """The ``roundtrip`` command as a function; returns its summary."""
    names, times, values, res = read_csv(csv_path)
    order = np.argsort(times, kind="stable")
    times, values = times[order], values[order]
    channels: list[dict[str, Any]] = []
    for j, name in enumerate(names):
        r = resolution or res[j]
        col = values[:, j][np.isfinite(values[:, j])]
        lo, hi = (float(col.min()), float(col.max())) if col.size else (0.0, 1.0)
        channels.append({"name": name, "unit": "", "lo": lo - r, "hi": max(hi + r, lo), "resolution": r})
    sender = TimeSeriesSender({"channels": channels, "wavelet": wavelet, "block_samples": block_samples,
                               "overview_factor": overview_factor})
    now = float(times[-1])
    sender.ingest({name: (times, values[:, j]) for j, name in enumerate(names)}, now)
    sender.flush(now)

    topside = TimeSeriesReceiver()
    # a lossless link of whole frames; acks go back at once
    link = RoundTrip(sender, topside, mtu=FRAME_PAYLOAD + wire.header_size(), round_seconds=1.0, now=now)
    limit = max(budgets)
    link.drain()
    # refine the whole record as a topside asking for "finer detail" would, until each channel
    # reaches half its resolution or the largest budget is spent
    finished: set[str] = set()
    while sum(wire.encoded_size(m) for m in link.sent) < limit and len(finished) < len(names):
        for j, name in enumerate(names):
            if name in finished:
                continue
            worst = max((b for _, _, b in topside.bounds(name)), default=math.inf)
            floor = float(channels[j]["resolution"]) / 2
            if worst <= floor * 1.0001:
                finished.add(name)
                continue
            topside.request(name, float(times[0]), float(times[-1]), max(worst / 4, floor))
        link.poll()
        if not link.drain():
            break
    sent = link.sent
    total = sum(wire.encoded_size(m) for m in sent)

    outdir = Path(out)
    outdir.mkdir(parents=True, exist_ok=True)
    with (outdir / "messages.jsonl").open("w") as f:
        running = 0
        for m in sent:
            data = wire.encode(m)
            running += len(data)
            row = to_json(m)
            row.update(hex=data.hex(), bytes=len(data), total=running)
            f.write(json.dumps(row) + "\n")
    summary: dict[str, Any] = {"messages": len(sent), "bytes": total, "budgets": {}}
    sizes = np.cumsum([wire.encoded_size(m) for m in sent]) if sent else np.zeros(0, dtype=np.int64)
    for b in budgets:
        rx = TimeSeriesReceiver()
        n = int(np.searchsorted(sizes, b, side="right"))
        t_rx = float(times[-1])
        for m in sent[:n]:
            rx.receive(m, t_rx)
        # channel ids follow the CSV's column order; columns stay empty until data arrives
        rx.to_csv(outdir / f"recon_{b}.csv", times=times, channels=list(range(len(names))), names=names)
        entry: dict[str, Any] = {"bytes": int(sizes[n - 1]) if n else 0, "messages": n}
        for j, name in enumerate(names):
            s = rx.series(j)
            got, _ = sample_series(s, times)
            ok = np.isfinite(values[:, j]) & np.isfinite(got)
            err = float(np.max(np.abs(got[ok] - values[ok, j]))) if ok.any() else None
            entry[name] = {"bound": s.max_bound if s.times.size else None, "max_error": err,
                           "covered": float(ok.sum() / max(1, np.isfinite(values[:, j]).sum()))}
        summary["budgets"][str(b)] = entry
    return summary


def _cmd_synth(args: argparse.Namespace) -> int:
    if not (args.hours > 0 and args.period > 0 and 0 <= args.jitter < 0.5):
        raise ConfigError("--hours and --period must be positive and --jitter in [0, 0.5)")
    series = synth.dataset(duration=args.hours * 3600.0, period=args.period, seed=args.seed,
                           t0=args.t0, jitter=args.jitter)
    synth.write_csv(args.out, series)
    spikes = ", ".join(f"{s.height:.1f} nM at {s.time - args.t0:.0f} s" for s in series[0].spikes)
    print(f"wrote {args.out}: {series[0].times.size} samples of {', '.join(s.name for s in series)}; "
          f"methane spikes: {spikes}")
    return 0


def _cmd_roundtrip(args: argparse.Namespace) -> int:
    budgets = _budgets(args.budgets)
    summary = roundtrip(args.csv, args.out, budgets, wavelet=args.wavelet, block_samples=args.block_samples,
                        overview_factor=args.overview_factor, resolution=args.resolution)
    print(f"{summary['messages']} messages, {summary['bytes']} wire bytes -> {args.out}/messages.jsonl")
    for b, entry in summary["budgets"].items():
        parts = [f"budget {b:>7} B: used {entry['bytes']:>6} B"]
        for key, val in entry.items():
            if isinstance(val, dict):
                bound = "-" if val["bound"] is None else f"{val['bound']:.4g}"
                err = "-" if val["max_error"] is None else f"{val['max_error']:.4g}"
                parts.append(f"{key}: {100 * val.get('covered', 0):.0f}% covered, bound {bound} "
                             f"(actual max error {err})")
        print("  ".join(parts), file=sys.stdout)
    return 0

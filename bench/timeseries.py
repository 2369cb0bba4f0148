"""Benchmark of the time-series modality against naive quantised deltas.

On a realistic synthetic record (6 h at 1 Hz: methane with drift, noise and six short spikes of
2..40 nM; temperature with drift and noise), measures:

* bytes to reach a maximum absolute error E: the wavelet code (overview, then one request for
  the whole record down to E, i.e. progressive) and a single pass straight to E (direct), against
  naive quantised deltas (step 2E, so the error is at most E) coded two ways: Rice codes with the
  best parameter per 1024 samples (a practical prefix code) and the order-0 entropy of the deltas
  (the best any memoryless entropy coder of deltas can do);
* the spike check: the wire bytes of the default stream (alert passes, then overviews) after which
  every spike higher than the threshold is visible (the reconstruction at the spike's peak stands
  at least half the spike's height above the true baseline), against 10 % of what deltas need for
  the same error bound.

Bytes are whole CoEx messages (type id, length, header and data), the frame header excluded.
Run: ``.venv/bin/python bench/timeseries.py [--quick]``; writes ``bench/results/timeseries.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from coex_core import wire
from coex_core.loopback import RoundTrip
from coex_core.messages import Message
from coex_plugins.timeseries import TimeSeriesReceiver, TimeSeriesSender, synth
from coex_plugins.timeseries.codec import _rice_k
from coex_plugins.timeseries.receiver import sample_series

T0 = 1_700_000_000.0
ERRORS = {"methane": (0.01, 0.02, 0.05, 0.1, 0.2, 0.5), "temperature": (0.001, 0.002, 0.005, 0.01, 0.05)}
SPIKE_THRESHOLD = 1.0  # nM: every spike higher than this must show
TARGET_FRACTION = 0.10


# ------------------------------------------------------------------------ deltas baseline


def delta_codes(x: np.ndarray, error: float) -> np.ndarray:
    q = np.round(x / (2 * error)).astype(np.int64)
    d = np.diff(q, prepend=0)
    return np.where(d >= 0, 2 * d, -2 * d - 1)  # zigzag


def deltas_rice_bytes(x: np.ndarray, error: float, block: int = 1024) -> int:
    z = delta_codes(x, error)
    bits = 0
    for s in range(0, z.size, block):  # per block of 1024, not per sample
        zz = z[s:s + block]
        k = _rice_k(zz)
        bits += int((zz >> k).sum()) + zz.size * (k + 1) + 5
    return math.ceil(bits / 8)


def deltas_entropy_bytes(x: np.ndarray, error: float) -> int:
    z = delta_codes(x, error)
    _, counts = np.unique(z, return_counts=True)
    p = counts / counts.sum()
    return math.ceil(float(-(counts * np.log2(p)).sum()) / 8)


# ---------------------------------------------------------------------------- our code


def _link(sender: TimeSeriesSender, receiver: TimeSeriesReceiver, now: float) -> RoundTrip:
    """A lossless link of 251-byte fills, one round a second; acks go back at once."""
    return RoundTrip(sender, receiver, mtu=251 + wire.header_size(), round_seconds=1.0, now=now)


def _stream(sender: TimeSeriesSender, receiver: TimeSeriesReceiver, now: float,
            sent: list[Message]) -> float:
    """Lossless link: fill whole messages until the sender is idle; acks go back at once."""
    link = _link(sender, receiver, now)
    link.drain()
    sent.extend(link.sent)
    return link.now


def live_sender(series: synth.SynthSeries, config: dict[str, Any], batch: int = 60) -> tuple[TimeSeriesSender, float]:
    """A sender fed like on a dive: ``batch`` seconds of samples at a time, then flushed."""
    sender = TimeSeriesSender({"channels": [series.channel()], **config})
    for i in range(0, series.times.size, batch):
        j = min(i + batch, series.times.size)
        sender.ingest({series.name: (series.times[i:j], series.values[i:j])}, float(series.times[j - 1]))
    now = float(series.times[-1])
    sender.flush(now)
    return sender, now


def spike_visible(series: synth.SynthSeries, rx: TimeSeriesReceiver, threshold: float) -> list[bool]:
    try:
        s = rx.series(series.name)
    except Exception:
        return [False for sp in series.spikes if sp.height > threshold]
    out = []
    for sp in series.spikes:
        if sp.height <= threshold:
            continue
        i = int(np.argmin(np.abs(series.times - sp.time)))
        lo, hi = max(0, i - 2), min(series.times.size, i + 3)
        got, _ = sample_series(s, series.times[lo:hi])
        above = got - series.baseline[lo:hi]
        out.append(bool(np.isfinite(above).any() and np.nanmax(above) >= 0.5 * sp.height))
    return out


def spike_bytes(series: synth.SynthSeries, config: dict[str, Any], threshold: float) -> dict[str, Any]:
    """Wire bytes of the default stream after which every spike above ``threshold`` shows."""
    sender, now = live_sender(series, config)
    sent: list[Message] = []
    _stream(sender, TimeSeriesReceiver(), now, sent)
    rx = TimeSeriesReceiver()
    total = 0
    needed = None
    for m in sent:
        total += wire.encoded_size(m)
        rx.receive(m, now)
        if needed is None and all(spike_visible(series, rx, threshold)):
            needed = total
    return {"bytes_all_spikes": needed, "default_stream_bytes": total,
            "spikes": sum(1 for sp in series.spikes if sp.height > threshold)}


def alert_latency(series: synth.SynthSeries, config: dict[str, Any], batch: int = 60) -> list[float]:
    """Seconds from each spike's peak until topside holds a block covering it, when samples
    arrive ``batch`` seconds at a time and the link is never the bottleneck."""
    sender = TimeSeriesSender({"channels": [series.channel()], **config})
    rx = TimeSeriesReceiver()
    seen: dict[int, float] = {}
    for i in range(0, series.times.size, batch):
        j = min(i + batch, series.times.size)
        now = float(series.times[j - 1])
        sender.ingest({series.name: (series.times[i:j], series.values[i:j])}, now)
        _stream(sender, rx, now, [])
        held = rx.bounds(series.name) if rx.products() else []
        for k, sp in enumerate(series.spikes):
            if k not in seen and any(s <= sp.time <= e for s, e, _ in held):
                seen[k] = now - sp.time
    return [round(seen.get(k, math.inf), 1) for k in range(len(series.spikes))]


def bytes_to_error(series: synth.SynthSeries, config: dict[str, Any], error: float) -> dict[str, Any]:
    """Progressive (default stream, then a request down to ``error``) and direct bytes."""
    sender, now = live_sender(series, config)
    rx = TimeSeriesReceiver()
    link = _link(sender, rx, now)
    link.drain()
    overview = sum(wire.encoded_size(m) for m in link.sent)
    rx.request(series.name, float(series.times[0]), float(series.times[-1]), error)
    link.poll()
    link.drain()
    progressive = sum(wire.encoded_size(m) for m in link.sent)
    s = rx.series(series.name)
    got, _ = sample_series(s, series.times)
    achieved = float(np.max(np.abs(got - series.values)))
    direct_sender, now2 = live_sender(series, {**config, "alert_fraction": 0.0},)
    # direct: the overview itself aimed at the error bound
    direct_sender = TimeSeriesSender({"channels": [{**series.channel(), "overview_error": error}],
                                      **{**config, "alert_fraction": 0.0}})
    for i in range(0, series.times.size, 60):
        j = min(i + 60, series.times.size)
        direct_sender.ingest({series.name: (series.times[i:j], series.values[i:j])}, float(series.times[j - 1]))
    direct_sender.flush(now2)
    dsent: list[Message] = []
    _stream(direct_sender, TimeSeriesReceiver(), now2, dsent)
    direct = sum(wire.encoded_size(m) for m in dsent)
    return {"overview": overview, "progressive": progressive, "direct": direct,
            "achieved_max_error": achieved, "bound": s.max_bound}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="2 h of data instead of 6 h, fewer bounds")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "timeseries.json"))
    args = ap.parse_args()
    duration = 7200.0 if args.quick else 21600.0
    methane, temperature = synth.dataset(duration=duration, t0=T0, seed=0)
    configs = {
        "live": {},  # defaults: 4096-sample blocks closed after at most 120 s
        "live_1200": {"max_latency": 1200.0},  # the default before issue 51: blocks of up to 20 min
        "archive": {"max_latency": 1e9, "spike_close": 0},  # full 4096-sample blocks
    }
    t_start = time.perf_counter()
    results: dict[str, Any] = {"duration_s": duration, "samples": int(methane.times.size),
                               "spike_threshold": SPIKE_THRESHOLD, "target_fraction": TARGET_FRACTION,
                               "channels": {}}
    met_rice = met_entropy = True
    for series in (methane, temperature):
        errors = ERRORS[series.name][::2] if args.quick else ERRORS[series.name]
        ch: dict[str, Any] = {"rows": [], "spikes": {}}
        print(f"\n{series.name} ({series.unit}), {series.times.size} samples, "
              f"{len(series.spikes)} spikes {[round(sp.height, 1) for sp in series.spikes]}")
        for cname, cfg in configs.items():
            if series.spikes:
                ch["spikes"][cname] = spike_bytes(series, cfg, SPIKE_THRESHOLD)
                ch["spikes"][cname]["alert_latency_s"] = alert_latency(series, cfg)
        print(f"{'E':>7} {'deltas rice':>11} {'deltas H0':>9} | " + " | ".join(
            f"{c + ' prog':>12} {c + ' direct':>13} {'ovw':>5}" for c in configs)
            + (" | spikes within 10% of deltas: rice / H0" if series.spikes else ""))
        for e in errors:
            row: dict[str, Any] = {"error": e, "deltas_rice": deltas_rice_bytes(series.values, e),
                                   "deltas_entropy": deltas_entropy_bytes(series.values, e)}
            for cname, cfg in configs.items():
                row[cname] = bytes_to_error(series, cfg, e)
            line = f"{e:>7g} {row['deltas_rice']:>11} {row['deltas_entropy']:>9} | " + " | ".join(
                f"{row[c]['progressive']:>12} {row[c]['direct']:>13} {row[c]['overview']:>5}" for c in configs)
            if series.spikes:
                row["spikes_within_budget"] = {}
                cells = []
                for base in ("rice", "entropy"):
                    budget = TARGET_FRACTION * row[f"deltas_{base}"]
                    verdicts = {}
                    for cname in configs:
                        need = ch["spikes"][cname]["bytes_all_spikes"]
                        verdicts[cname] = need is not None and need <= budget
                    row["spikes_within_budget"][base] = {"budget": budget, **verdicts}
                    if base == "rice":
                        met_rice &= all(verdicts.values())
                    else:
                        met_entropy &= all(verdicts.values())
                    cells.append(f"{budget:.0f} B " + "/".join("yes" if v else "NO" for v in verdicts.values()))
                line += " | " + " ; ".join(cells)
            print(line)
            ch["rows"].append(row)
        for cname, sp in ch["spikes"].items():
            print(f"  {cname}: every spike > {SPIKE_THRESHOLD} {series.unit} visible after "
                  f"{sp['bytes_all_spikes']} B (default stream {sp['default_stream_bytes']} B); "
                  f"seconds from each peak to topside (samples every 60 s): {sp['alert_latency_s']}")
        results["channels"][series.name] = ch
    results["target_met_vs_rice_deltas"] = met_rice
    results["target_met_vs_entropy_deltas"] = met_entropy
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    print(f"\ntarget: every spike within {TARGET_FRACTION:.0%} of the bytes deltas need for the same bound, "
          f"at every E, live and archive:")
    print(f"  against Rice-coded deltas (naive prefix code):         {'MET' if met_rice else 'NOT MET'}")
    print(f"  against the order-0 entropy of deltas (ideal coder):   {'MET' if met_entropy else 'NOT MET'}"
          f"  (see the per-E columns)")
    print(f"({results['seconds']} s)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1, default=float) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

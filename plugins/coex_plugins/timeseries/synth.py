"""Realistic synthetic sensor series: slow drift, sensor noise, a few short spikes.

Used by the tests, the benchmark and the demo (``coex demo``). Deterministic for a given seed.
Two channels model a methane sensor over a seep field (baseline drift of a few tenths of nM,
noise near 0.01 nM, six short spikes of a few to tens of nM) and a CTD temperature (slow
drift of tenths of a degree, 1 mK noise).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Spike", "SynthSeries", "dataset", "methane", "temperature", "write_csv"]


@dataclass(frozen=True)
class Spike:
    """One anomaly: peak time, height above the baseline, width (s, full width at half height)."""

    time: float
    height: float
    width: float


@dataclass(frozen=True)
class SynthSeries:
    """A channel: registration (name, unit, range, resolution) and its samples.

    ``baseline`` is the series without noise and spikes (the truth a spike stands out from)."""

    name: str
    unit: str
    lo: float
    hi: float
    resolution: float
    times: np.ndarray
    values: np.ndarray
    baseline: np.ndarray
    spikes: tuple[Spike, ...]

    def channel(self) -> dict[str, object]:
        """The channel registration as a sender configuration entry."""
        return {"name": self.name, "unit": self.unit, "lo": self.lo, "hi": self.hi,
                "resolution": self.resolution}


def _times(n: int, period: float, t0: float, jitter: float, rng: np.random.Generator) -> np.ndarray:
    t = t0 + period * np.arange(n, dtype=np.float64)
    if jitter > 0:
        t = t + rng.uniform(-jitter, jitter, n) * period
        t = np.maximum.accumulate(t)
    return t


def _drift(t: np.ndarray, scale: float, hours: tuple[float, ...], rng: np.random.Generator) -> np.ndarray:
    """A smooth drift: a few slow sinusoids plus a smoothed random walk."""
    rel = t - t[0]
    d = np.zeros_like(rel)
    for h in hours:
        d += scale * rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * rel / (h * 3600.0) + rng.uniform(0, 2 * np.pi))
    walk = np.cumsum(rng.normal(0.0, 1.0, rel.size))
    kernel = np.hanning(min(601, rel.size))  # "same" mode needs a kernel no longer than the series
    smooth = np.convolve(walk, kernel / kernel.sum(), mode="same")
    smooth -= smooth.mean()
    out: np.ndarray = d + 0.2 * scale * smooth / max(float(np.std(smooth)), 1e-12)
    return out


def _quantise(x: np.ndarray, res: float) -> np.ndarray:
    return np.round(x / res) * res


def methane(duration: float = 21600.0, period: float = 1.0, seed: int = 0, t0: float = 0.0,
            jitter: float = 0.0, n_spikes: int = 6) -> SynthSeries:
    """Dissolved methane (nmol/L): drift around 3 nM, 0.01 nM noise, ``n_spikes`` short spikes."""
    rng = np.random.default_rng(seed)
    n = round(duration / period)
    t = _times(n, period, t0, jitter, rng)
    base = 3.0 + _drift(t, 0.4, (5.0, 1.7), rng)
    spikes = []
    values = base + rng.normal(0.0, 0.01, n)
    edges = np.linspace(t[0], t[-1], n_spikes + 1)
    heights = np.geomspace(2.0, 40.0, n_spikes)
    rng.shuffle(heights)
    for i in range(n_spikes):
        centre = float(rng.uniform(edges[i] + 0.1 * (edges[i + 1] - edges[i]),
                                   edges[i + 1] - 0.1 * (edges[i + 1] - edges[i])))
        width = float(rng.uniform(3.0, 25.0))
        h = float(heights[i])
        sigma = width / 2.355
        values = values + h * np.exp(-0.5 * ((t - centre) / sigma) ** 2)
        spikes.append(Spike(centre, h, width))
    res = 0.001
    return SynthSeries("methane", "nmol/L", 0.0, 1000.0, res, t, _quantise(values, res),
                       base, tuple(spikes))


def temperature(duration: float = 21600.0, period: float = 1.0, seed: int = 0, t0: float = 0.0,
                jitter: float = 0.0) -> SynthSeries:
    """Temperature (degC): drift around 4 degC of a few tenths, 1 mK noise, no spikes."""
    rng = np.random.default_rng(seed + 1)
    n = round(duration / period)
    t = _times(n, period, t0, jitter, rng)
    base = 4.0 + _drift(t, 0.15, (6.0, 2.3, 0.7), rng)
    values = base + rng.normal(0.0, 0.001, n)
    res = 0.0001
    return SynthSeries("temperature", "degC", -2.0, 40.0, res, t, _quantise(values, res), base, ())


def dataset(duration: float = 21600.0, period: float = 1.0, seed: int = 0, t0: float = 0.0,
            jitter: float = 0.0) -> list[SynthSeries]:
    """Methane and temperature on the same sample times."""
    m = methane(duration, period, seed, t0, jitter)
    tmp = temperature(duration, period, seed, t0, 0.0)
    tmp = SynthSeries(tmp.name, tmp.unit, tmp.lo, tmp.hi, tmp.resolution, m.times, tmp.values,
                      tmp.baseline, tmp.spikes)
    return [m, tmp]


def write_csv(path: str | Path, series: Sequence[SynthSeries]) -> Path:
    """Write ``time`` then one column per channel (the ``coex timeseries roundtrip`` input)."""
    path = Path(path)
    times = series[0].times
    cols = [np.char.mod("%.3f", times)]
    for s in series:
        decimals = max(0, -int(np.floor(np.log10(s.resolution) + 1e-9)))
        cols.append(np.char.mod(f"%.{decimals}f", s.values))
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time", *(s.name for s in series)])
        w.writerows(np.stack(cols, axis=1).tolist())
    return path

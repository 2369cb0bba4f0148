"""``coex timeseries roundtrip CSV --out DIR --budgets B1,B2,...``."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from coex_core import wire
from coex_core.cli import main
from coex_core.jsonfmt import from_json
from coex_plugins.timeseries import synth

T0 = 1_700_000_000.0


@pytest.fixture(scope="module")
def csv_path(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[synth.SynthSeries]]:
    series = synth.dataset(duration=3600.0, t0=T0, seed=2, jitter=0.1)
    path = tmp_path_factory.mktemp("ts") / "in.csv"
    synth.write_csv(path, series)
    return path, series


def _read(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    rows = [[float(x) if x else np.nan for x in line.split(",")] for line in lines[1:]]
    return header, np.array(rows)


def test_roundtrip_writes_messages_and_budgeted_reconstructions(
        tmp_path: Path, csv_path: tuple[Path, list[synth.SynthSeries]], capsys: pytest.CaptureFixture[str]) -> None:
    path, series = csv_path
    out = tmp_path / "out"
    budgets = [100, 400, 1500, 6000]
    assert main(["timeseries", "roundtrip", str(path), "--out", str(out),
                 "--budgets", ",".join(map(str, budgets))]) == 0
    assert "wire bytes" in capsys.readouterr().out
    rows = [json.loads(line) for line in (out / "messages.jsonl").read_text().splitlines()]
    assert rows[0]["type"] == "TimeSeriesChannel"
    total = 0
    messages = []
    for row in rows:
        data = bytes.fromhex(row.pop("hex"))
        size, running = row.pop("bytes"), row.pop("total")
        m = from_json(row)
        assert wire.decode(data) == m and wire.encode(m) == data
        total += len(data)
        assert size == len(data) and running == total
        messages.append(m)
    assert total >= 6000  # refinement continued up to the largest budget
    errors = []
    for b in budgets:
        header, table = _read(out / f"recon_{b}.csv")
        assert header == ["time", "methane", "temperature", "methane_bound", "temperature_bound"]
        assert table.shape == (series[0].times.size, 5)
        if b == 100:  # only the registrations and the first chunk fit: most cells are still empty
            assert np.isnan(table[:, 1:]).mean() > 0.5
            continue
        np.testing.assert_allclose(table[:, 0], series[0].times, atol=1e-3)
        err = []
        for j, s in enumerate(series):
            got, bound = table[:, 1 + j], table[:, 3 + j]
            ok = np.isfinite(got)
            assert ok.any()
            # gridding a jittered sample moves it by at most 10% of a period; the bound is on the grid
            slack = np.max(np.abs(np.diff(s.values))) * 0.15
            assert np.all(np.abs(got[ok] - s.values[ok]) <= bound[ok] + slack)
            err.append(float(np.nanmax(bound)))
        errors.append(err)
    # more bytes never make the reconstruction worse, and the largest budget refines it
    for a, b in itertools.pairwise(errors):
        assert all(y <= x for x, y in zip(a, b))
    assert errors[-1][0] < errors[0][0]


def test_roundtrip_rejects_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("depth,methane\n1,2\n")
    assert main(["timeseries", "roundtrip", str(bad), "--out", str(tmp_path / "o"), "--budgets", "10"]) == 2
    assert "time" in capsys.readouterr().err
    good = tmp_path / "good.csv"
    good.write_text("time,methane\n0,1.5\n1,1.6\n")
    assert main(["timeseries", "roundtrip", str(good), "--out", str(tmp_path / "o"), "--budgets", "x"]) == 2
    assert main(["timeseries", "roundtrip", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "o"),
                 "--budgets", "10"]) == 2


def test_synth_writes_the_roundtrip_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s.csv"
    assert main(["timeseries", "synth", "--out", str(out), "--hours", "0.5", "--seed", "3"]) == 0
    assert "methane spikes" in capsys.readouterr().out
    header, table = _read(out)
    assert header == ["time", "methane", "temperature"] and table.shape == (1800, 3)
    expected = synth.dataset(duration=1800.0, seed=3, t0=1_700_000_000.0)
    np.testing.assert_allclose(table[:, 1], expected[0].values, atol=1e-9)
    assert main(["timeseries", "synth", "--out", str(out), "--hours", "0"]) == 2

"""Whole demo dives shared by the tests that only read their outputs: one dive per set of
parameters per ``pytest`` run, whichever test (of whichever file, on whichever xdist worker)
asks first; the others wait for it and read the same directory (docs/testing.md).

A dive is found by its configuration (every :class:`DemoConfig` field but ``out``), so two tests
share one only when they ask for the very same dive. The directory lives under the run's own
base temporary directory (the parent of the workers' directories under xdist), so nothing is
kept from one ``pytest`` run to the next. A test that changes the dive (monkeypatching its
modules, replacing its eye, zeroing its labels to compare) runs its own."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from coex_apps.demo import DemoConfig, run_demo
from coex_apps.demo.scenario import ObjectSpec, Scenario, scenario_from_dict

__all__ = ["QUICK_SHORT", "SMALL", "codestreams_at", "codestreams_dir", "codestreams_shared", "coex_command", "dark_rock_site", "encodes_remembered", "quick_short", "quick_short_file", "shared_dive", "small", "small_file"]

#: a small, short dive (a 64 m site, one car, 25 minutes): a whole dive, camera pass included,
#: for tests whose subject needs one but not the default site
SMALL: dict[str, Any] = {"name": "small", "area": 64.0, "duration": 1500.0, "seafloor": {"random_targets": 1}}


def small(base: Scenario | None = None, **sections: Any) -> Scenario:
    """:data:`SMALL` with ``sections`` added (``navigation={"drift": 0.0}``, ``modem={...}``), on
    ``base`` (a preset's link and ship; default: preset ``default``)."""
    return scenario_from_dict({**SMALL, **sections}, base=base)


def dark_rock_site() -> Scenario:
    """A pale car, a dark car, a container and a dark rock as dark as a car on the quick site
    (``quick=True, seed=3``): test_demo_eye.py's dive with the labels zeroed is compared with
    this one, and the dark-decoy test there reads it (the rock looked at, never
    confirmed). Perfect navigation: these tests' subjects are who reads the labels and what the
    eye makes of a decoy (issue 56's drift is tested in test_navigation_demo.py; docs/demo.md
    says what this scene did with it). A 25-minute dive (the quick preset's is 50): its last
    decision falls at 18 minutes (the rock called natural), and the half hour after it only moves
    bytes, about a third of each of the two dives' CPU."""
    return Scenario(area=96.0, duration=1500.0, targets=(
        ObjectSpec(26.0, 30.0, 4.4, 1.8, 1.5, 20.0, "box", "car", 0.07),
        ObjectSpec(70.0, 26.0, 3.2, 1.6, 1.4, -50.0, "box", "car", 0.4),
        ObjectSpec(28.0, 70.0, 6.06, 2.44, 2.59, 70.0, "box", "container", 0.2)),
        decoys=(ObjectSpec(70.0, 70.0, 3.4, 2.5, 1.5, 10.0, "dome", "dark rock", 0.08),),
        drift=0.0)


#: the quick site (preset ``default`` at ``quick=True``, seed 1) in a 20-minute dive instead of 50:
#: for the dives whose subject is over when the survey is (at 332 s: nobody operating, or a
#: geofence refusing every camera line); the half hour after only moves bytes
QUICK_SHORT: dict[str, Any] = {"duration": 1200.0}


def quick_short() -> Scenario:
    """:data:`QUICK_SHORT` as a scenario (``DemoConfig(quick=True, scenario=quick_short())``)."""
    return scenario_from_dict(QUICK_SHORT)


def quick_short_file(path: Path) -> Path:
    """:data:`QUICK_SHORT` as a scenario file (``coex demo --quick --scenario PATH``): the same
    scenario as :func:`quick_short` but for its name (the file's), so the two dives' frames are the
    same and coded once."""
    return _scenario_file(path, QUICK_SHORT)


def small_file(path: Path, **top: Any) -> Path:
    """:data:`SMALL` as a scenario file (``coex demo --scenario PATH``), written to ``path``, with
    the top-level keys ``top`` replaced (``duration=1000.0``)."""
    return _scenario_file(path, {**SMALL, **top})


def _scenario_file(path: Path, data: dict[str, Any]) -> Path:
    """``data`` (a scenario's top-level keys and its one-level sections) as TOML at ``path``."""
    def lines(table: dict[str, Any]) -> list[str]:
        return [f"{k} = {json.dumps(v)}" for k, v in table.items() if not isinstance(v, dict)]

    text = lines(data) + [f"[{k}]\n" + "\n".join(lines(v)) for k, v in data.items() if isinstance(v, dict)]
    path.write_text("\n".join(text) + "\n")
    return path


def _root(factory: pytest.TempPathFactory) -> Path:
    """The directory every worker of this run shares: under xdist each worker's base temporary
    directory is ``<the run's>/popen-gwN``; without xdist the run's own."""
    base = factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared-dives"
    root.mkdir(parents=True, exist_ok=True)
    return root


def shared_dive(factory: pytest.TempPathFactory, config: DemoConfig) -> tuple[Path, dict[str, Any]]:
    """``run_demo(config)`` once for this ``pytest`` run (``config.out`` is ignored): the
    directory holding its outputs and its ``metrics.json``. Concurrent callers wait on a file
    lock; a dive that failed is run again by the next caller (and fails there too)."""
    key = hashlib.sha256(repr(replace(config, out=Path("-"))).encode()).hexdigest()[:16]
    root = _root(factory)
    out, done = root / key, root / f"{key}.done"
    with open(root / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(out, ignore_errors=True)  # what a failed attempt left
            run_demo(replace(config, out=out))
            done.touch()
    return out, json.loads((out / "metrics.json").read_text())


@contextmanager
def encodes_remembered() -> Iterator[dict[str, int]]:
    """Image encodes remembered while the block runs (in this process): an image coded again with
    the same pixels, base and parameters gets the codestream it got the first time, without
    OpenJPEG (the coding is deterministic: the same bytes). For a test that runs one dive twice
    to compare what changes but the frames (test_demo_eye.py's labels-zeroed dive): the second
    dive's image coding, about 60 % of a dive's CPU, is not paid again. Yields the counts
    ``encodes`` (coded here) and ``reused`` (served from memory)."""
    from coex_plugins.imagery import codec

    real = codec._encode
    memo: dict[str, codec.Encoded] = {}
    counts = {"encodes": 0, "reused": 0}

    def remembered(data: npt.NDArray[np.uint8], cp: codec.CodingParams,
                   base: npt.NDArray[np.uint8] | None = None,
                   reference: npt.NDArray[np.uint8] | None = None) -> codec.Encoded:
        key = _encode_key(data, cp, base, reference)
        if key in memo:
            counts["reused"] += 1
        else:
            counts["encodes"] += 1
            memo[key] = real(data, cp, base, reference)
        return memo[key]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(codec, "_encode", remembered)
        yield counts


def _encode_key(data: npt.NDArray[np.uint8], cp: Any, base: npt.NDArray[np.uint8] | None,
                reference: npt.NDArray[np.uint8] | None) -> str:
    """What an image's coding depends on: its coding parameters and the three arrays (pixels,
    base, reference), each with its shape and type."""
    h = hashlib.sha256(repr(cp).encode())
    for a in (data, base, reference):
        h.update(b"-" if a is None else repr((a.shape, a.dtype.str)).encode() + np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def codestreams_dir(factory: pytest.TempPathFactory) -> Path:
    """Where this run's dives share their codings (:func:`codestreams_shared`)."""
    root = _root(factory) / "codestreams"
    root.mkdir(exist_ok=True)
    return root


@contextmanager
def codestreams_shared(factory: pytest.TempPathFactory) -> Iterator[dict[str, int]]:
    """Image codings shared by every dive of this ``pytest`` run, on every xdist worker, while
    the block runs: :func:`encodes_remembered` on disk, under the run's own base temporary
    directory (so nothing is kept from one run to the next). An image coded with the same
    pixels, base and parameters (calibration and tightening included) as one some dive of this
    run coded already gets that codestream without OpenJPEG (the coding is deterministic:
    ``tests/test_imagery_calibration.py`` codes one image twice and compares the bytes). Two
    dives that photograph the same scene (the small site's dives at seed 1 with and without
    spare traffic, with and without the navigation code) code each frame once. One file lock a
    frame: a worker that wants a frame another is coding waits for it instead of coding it
    again. Yields the counts ``encodes`` (coded here) and ``reused`` (read from disk), and
    appends them to ``codestreams.jsonl`` in the shared directory when the block ends. A dive
    run as a ``coex`` process shares them too: :func:`coex_command`."""
    with codestreams_at(codestreams_dir(factory)) as counts:
        yield counts


def coex_command(factory: pytest.TempPathFactory, *args: str) -> list[str]:
    """The command line of ``coex ARGS`` (as ``python -m coex_core.cli ARGS``) whose dive codes
    its images with the run's shared codings (``python tests/_coex_shared.py DIR ARGS``)."""
    return [sys.executable, str(Path(__file__).with_name("_coex_shared.py")), str(codestreams_dir(factory)), *args]


@contextmanager
def codestreams_at(root: Path) -> Iterator[dict[str, int]]:
    """:func:`codestreams_shared` in the directory ``root``."""
    from coex_plugins.imagery import codec

    real = codec._encode
    counts = {"encodes": 0, "reused": 0}

    def read(path: Path, data: npt.NDArray[np.uint8]) -> codec.Encoded:
        raw = path.read_bytes()
        head, body = raw.split(b"\n", 1)
        meta = json.loads(head)
        return codec.Encoded(body, np.asarray(meta["starts"], np.int64), meta["params"], meta["width"],
                             meta["height"], meta["grey"], data)

    def shared(data: npt.NDArray[np.uint8], cp: codec.CodingParams,
               base: npt.NDArray[np.uint8] | None = None,
               reference: npt.NDArray[np.uint8] | None = None) -> codec.Encoded:
        key = _encode_key(data, cp, base, reference)
        path = root / key
        if path.exists():
            counts["reused"] += 1
            return read(path, data)
        with open(root / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
            if path.exists():  # another worker coded it while this one waited
                counts["reused"] += 1
                return read(path, data)
            enc = real(data, cp, base, reference)
            head = json.dumps({"starts": enc.packet_starts.tolist(), "params": enc.params, "width": enc.width,
                               "height": enc.height, "grey": enc.grey}).encode()
            part = root / f"{key}.part"
            part.write_bytes(head + b"\n" + enc.body)
            os.replace(part, path)
            counts["encodes"] += 1
            return enc

    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(codec, "_encode", shared)
            yield counts
    finally:
        with open(root.parent / "codestreams.jsonl", "a") as log:
            log.write(json.dumps({"worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
                                  "test": os.environ.get("PYTEST_CURRENT_TEST", ""), **counts}) + "\n")

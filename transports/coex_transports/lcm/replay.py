"""Offline re-analysis of a dive: replay an ``lcm-logger`` log of a CoEx session.

:func:`replay_log` reads the log with ``lcm.EventLog``, decodes every ``coex.frame_t`` event,
unpacks the CoEx frame and routes each message to the topside receiver of the modality that
declares it (``Modality.messages``). Modalities come from the ``coex.modalities`` entry points
(:mod:`coex_core.registry`); one that cannot load is skipped with a warning and listed in the
summary. ``now`` given to the receivers is the event's log time in seconds since 1970.

With an output directory it writes:

``summary.json``      the summary returned by :func:`replay_log`
``products/<modality>/<kind>-<key>.npy|.npz|.bin|.txt`` (+ ``.json`` with version and meta)
                      every product whose data is a numpy array, bytes, text, or a dataclass
                      or mapping holding arrays (saved as .npz)
``decoded.lcmlog``    an LCM log of ``coex.vehicle_status_t`` (channel ``COEX_VEHICLE_STATUS``)
                      and ``coex.map_level_t`` (``COEX_MAP_LEVEL``) events, for LCM tools
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lcm
import numpy as np

from coex_core import registry
from coex_core.errors import ConfigError, DecodeError
from coex_core.jsonfmt import to_json
from coex_core.messages import Message, SubgridMessage, VehicleStatus
from coex_core.modality import Modality, ModalityReceiver, Product

from ._codec import is_frame_t, unpack_event
from .products import (
    MAP_LEVEL_CHANNEL,
    VEHICLE_STATUS_CHANNEL,
    MapLevelSummary,
    vehicle_status_to_lcm,
)

__all__ = ["load_modalities", "modality_names", "replay_log", "write_products"]

log = logging.getLogger(__name__)


def modality_names() -> list[str]:
    """Names registered in the ``coex.modalities`` entry-point group."""
    return registry.names(registry.MODALITY_GROUP)


def load_modalities() -> tuple[dict[str, Modality], dict[str, str]]:
    """Instantiate every registered modality; return ``(loaded, unavailable name -> reason)``."""
    loaded: dict[str, Modality] = {}
    unavailable: dict[str, str] = {}
    for name in modality_names():
        try:
            loaded[name] = registry.load_modality(name)()
        except Exception as exc:  # a broken or uninstallable plugin must not stop a replay
            unavailable[name] = f"{type(exc).__name__}: {exc}"
            log.warning("modality %s unavailable, its messages are not replayed: %s", name, exc)
    return loaded, unavailable


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "product"


def _jsonable(value: Any) -> Any:
    try:
        json.dumps(value, allow_nan=True)
        return value
    except (TypeError, ValueError):
        if isinstance(value, Mapping):
            return {str(k): _jsonable(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [_jsonable(v) for v in value]
        if isinstance(value, np.generic):
            return value.item()
        return repr(value)


def _describe(product: Product) -> dict[str, Any]:
    data = product.data
    shape = list(data.shape) if isinstance(data, np.ndarray) else None
    return {
        "kind": product.kind,
        "key": product.key,
        "version": product.version,
        "data": type(data).__name__,
        "shape": shape,
        "meta": _jsonable(dict(product.meta)),
    }


def _arrays_of(data: Any) -> dict[str, np.ndarray]:
    """The numpy-array fields of a dataclass instance or the array values of a mapping."""
    if dataclasses.is_dataclass(data) and not isinstance(data, type):
        items = {f.name: getattr(data, f.name) for f in dataclasses.fields(data)}
    elif isinstance(data, Mapping):
        items = {str(k): v for k, v in data.items()}
    else:
        return {}
    return {k: v for k, v in items.items() if isinstance(v, np.ndarray)}


def write_products(products: Mapping[str, list[Product]], out_dir: Path) -> list[str]:
    """Write exportable products below ``out_dir/products``: a numpy array as ``.npy``, bytes as
    ``.bin``, text as ``.txt``, a dataclass or mapping holding arrays as ``.npz`` (its arrays);
    each with a ``.json`` side file. Return the paths written, relative to ``out_dir``."""
    written: list[str] = []
    for modality, items in products.items():
        for product in items:
            data = product.data
            stem = out_dir / "products" / _safe(modality) / f"{_safe(product.kind)}-{_safe(product.key)}"
            if isinstance(data, np.ndarray):
                path = stem.with_name(stem.name + ".npy")
                path.parent.mkdir(parents=True, exist_ok=True)
                np.save(path, data, allow_pickle=False)
            elif isinstance(data, bytes | bytearray):
                path = stem.with_name(stem.name + ".bin")
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(bytes(data))
            elif isinstance(data, str):
                path = stem.with_name(stem.name + ".txt")
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(data)
            elif arrays := _arrays_of(data):
                path = stem.with_name(stem.name + ".npz")
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez(path, **arrays)
            else:
                continue
            side = stem.with_name(stem.name + ".json")
            side.write_text(json.dumps(_describe(product), indent=2, allow_nan=True))
            written.append(str(path.relative_to(out_dir)))
    return written


def _open_log(path: Path) -> lcm.EventLog:
    if not path.is_file():
        raise ConfigError(f"no such LCM log: {path}")
    try:
        return lcm.EventLog(str(path), "r")
    except Exception as exc:
        raise ConfigError(f"cannot open LCM log {path}: {exc}") from exc


def replay_log(
    path: str | Path,
    out_dir: str | Path | None = None,
    *,
    channel: str | None = None,
    modalities: Mapping[str, Modality] | None = None,
) -> dict[str, Any]:
    """Replay an LCM log into the topside receivers; return (and write) the summary.

    ``channel`` is a regular expression a channel must match in full (default: every channel,
    recognising ``coex.frame_t`` events by their fingerprint); ``modalities`` overrides the
    registry (name -> instance)."""
    path = Path(path)
    pattern = re.compile(channel) if channel else None
    unavailable: dict[str, str] = {}
    if modalities is None:
        modalities, unavailable = load_modalities()
    replay = _Replay(modalities, unavailable)
    eventlog = _open_log(path)
    try:
        replay.read(eventlog, pattern, path)
    finally:
        eventlog.close()
    products = replay.products()
    summary = replay.summary(path, products)
    if out_dir is not None:
        summary["files"] = _write_outputs(Path(out_dir), products, replay.decoded_events, summary)
    return summary


class _Replay:
    """One replay: the topside receivers, the routes of the messages to them, and what was
    counted and decoded along the way."""

    def __init__(self, modalities: Mapping[str, Modality], unavailable: dict[str, str]) -> None:
        self.unavailable = unavailable
        self.receivers: dict[str, ModalityReceiver] = {}
        #: message type -> the modalities whose receivers take it; the types receivers send
        self.routes: dict[type[Message], list[str]] = {}
        self.requests: set[type[Message]] = set()
        for name, modality in modalities.items():
            try:
                self.receivers[name] = modality.receiver()
            except Exception as exc:
                unavailable[name] = f"{type(exc).__name__}: {exc}"
                log.warning("modality %s: cannot create its receiver: %s", name, exc)
                continue
            for cls in modality.messages:
                self.routes.setdefault(cls, []).append(name)
            self.requests.update(modality.requests)
        self.counts: Counter[str] = Counter()
        self.by_type: Counter[str] = Counter()
        self.routed: Counter[str] = Counter()
        self.unrouted: Counter[str] = Counter()
        self.receiver_errors: Counter[str] = Counter()
        self.channels: Counter[str] = Counter()
        self.errors: list[str] = []
        self.first_utime: int | None = None
        self.last_utime: int | None = None
        self.last_status: VehicleStatus | None = None
        self.maps = MapLevelSummary()
        #: ``(utime, channel, bytes)`` of the LCM events written to ``decoded.lcmlog``
        self.decoded_events: list[tuple[int, str, bytes]] = []

    def read(self, eventlog: lcm.EventLog, pattern: re.Pattern[str] | None, path: Path) -> None:
        """Every event of the log: the ``coex.frame_t`` ones (on a channel ``pattern`` matches)
        unpacked and their messages routed; a truncated or corrupt log keeps what was read."""
        while True:
            try:
                event = eventlog.read_next_event()
            except StopIteration:
                break
            except Exception as exc:  # a truncated or corrupt log: keep what was read
                self.errors.append(f"log read stopped: {exc}")
                log.warning("%s: log read stopped: %s", path, exc)
                break
            if event is None:
                break
            self.counts["events"] += 1
            if pattern is not None and not pattern.fullmatch(event.channel):
                continue
            if not is_frame_t(event.data):
                if pattern is not None:
                    self.counts["bad_events"] += 1
                    self.errors.append(f"event {event.eventnum} on {event.channel}: not a coex.frame_t")
                continue
            self._event(event)

    def _event(self, event: Any) -> None:
        """One ``coex.frame_t`` event: its frame's messages to the receivers that take them."""
        try:
            lcm_frame, frame = unpack_event(event.data)
        except DecodeError as exc:
            self.counts["bad_events"] += 1
            self.errors.append(f"event {event.eventnum} on {event.channel}: {exc}")
            log.warning("event %d on %s: %s", event.eventnum, event.channel, exc)
            return
        self.counts["frames"] += 1
        self.counts["frame_bytes"] += len(lcm_frame.data)
        self.channels[event.channel] += 1
        utime = int(event.timestamp)
        self.first_utime = utime if self.first_utime is None else min(self.first_utime, utime)
        self.last_utime = utime if self.last_utime is None else max(self.last_utime, utime)
        levels: set[int] = set()
        for message in frame.messages:
            self._message(message, utime, levels)
        for level in sorted(levels):
            self.decoded_events.append((utime, MAP_LEVEL_CHANNEL, self.maps.summary(level, utime).encode()))

    def _message(self, message: Message, utime: int, levels: set[int]) -> None:
        """One message, counted, decoded for LCM tools (status, map levels) and routed."""
        kind = type(message).__name__
        self.by_type[kind] += 1
        self.counts["messages"] += 1
        if isinstance(message, VehicleStatus):
            self.last_status = message
            self.decoded_events.append(
                (utime, VEHICLE_STATUS_CHANNEL, vehicle_status_to_lcm(message, utime).encode()))
        elif isinstance(message, SubgridMessage):
            levels.add(self.maps.add(message))
        targets = self.routes.get(type(message), [])
        if not targets:
            self.unrouted["request" if type(message) in self.requests else kind] += 1
        for name in targets:
            try:
                self.receivers[name].receive(message, utime / 1e6)
                self.routed[name] += 1
            except Exception as exc:  # a receiver bug must not end the re-analysis
                self.receiver_errors[name] += 1
                log.warning("modality %s failed on %s: %s", name, kind, exc)

    def products(self) -> dict[str, list[Product]]:
        """Every receiver's products (a receiver whose ``products()`` fails is counted)."""
        products: dict[str, list[Product]] = {}
        for name, receiver in self.receivers.items():
            try:
                products[name] = list(receiver.products())
            except Exception as exc:
                self.receiver_errors[name] += 1
                log.warning("modality %s: products() failed: %s", name, exc)
        return products

    def summary(self, path: Path, products: Mapping[str, list[Product]]) -> dict[str, Any]:
        first, last = self.first_utime, self.last_utime
        return {
            "log": str(path),
            "events": self.counts["events"],
            "frames": self.counts["frames"],
            "frame_bytes": self.counts["frame_bytes"],
            "bad_events": self.counts["bad_events"],
            "messages": self.counts["messages"],
            "channels": dict(sorted(self.channels.items())),
            "first_utime": first,
            "last_utime": last,
            "duration_s": (last - first) / 1e6 if first is not None and last else 0.0,
            "messages_by_type": dict(sorted(self.by_type.items())),
            "routed": dict(sorted(self.routed.items())),
            "unrouted": dict(sorted(self.unrouted.items())),
            "modalities": sorted(self.receivers),
            "unavailable": dict(sorted(self.unavailable.items())),
            "receiver_errors": dict(sorted(self.receiver_errors.items())),
            "vehicle_status": to_json(self.last_status) if self.last_status is not None else None,
            "map_levels": [
                {k: (None if isinstance(v, float) and math.isnan(v) else v)
                 for k, v in ((s, getattr(m, s)) for s in m.__slots__)}
                for m in self.maps.summaries(last or 0)
            ],
            "products": {name: [_describe(p) for p in items] for name, items in sorted(products.items())},
            "errors": self.errors[:100],
            "files": [],
        }


def _write_outputs(out: Path, products: Mapping[str, list[Product]], decoded_events: list[tuple[int, str, bytes]],
                   summary: dict[str, Any]) -> list[str]:
    """The replay's files in ``out``: the products, ``decoded.lcmlog`` (when anything was
    decoded for LCM tools) and ``summary.json`` (with these files); returns their names."""
    out.mkdir(parents=True, exist_ok=True)
    files = write_products(products, out)
    if decoded_events:
        decoded = out / "decoded.lcmlog"
        writer = lcm.EventLog(str(decoded), "w", overwrite=True)
        try:
            for utime, chan, data in decoded_events:
                writer.write_event(utime, chan, data)
        finally:
            writer.close()
        files.append(decoded.name)
    files.append("summary.json")
    (out / "summary.json").write_text(json.dumps({**summary, "files": files}, indent=2, default=str))
    return files

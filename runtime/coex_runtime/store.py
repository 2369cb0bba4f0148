"""Persistence of a node (SQLite, WAL): nothing received or captured is lost when a process is
killed (``kill -9``) and restarted, and transfers resume where they were.

The core is sans-I/O, so the store lives here, next to the runner. One SQLite file per node:

* ``journal``: every frame the node **received** (``rx``: link, time, bytes) and every input a
  sender **captured** (``input``: modality name, time, the data in :mod:`coex_core.state`
  form), and every frame it **sent** (``tx``, for the record), each committed before the node
  sees it;
* ``snapshot``: the whole sans-I/O state of the node (channel manager with its queues, pending
  acks, sequence numbers, command ids and authentication counters, operator settings; every
  modality sender and receiver with what it has captured, sent, acked and built) as
  :meth:`Node.export_parts <coex_core.node.Node.export_parts>` gives it (explicit, versioned
  state: never pickle), with the id of the last journal row it includes. It is written in one
  transaction before every transmission leaves (so a restarted node knows what it already sent)
  and after received frames, at most every ``snapshot_interval`` seconds; the journal rows it
  includes are deleted in the same transaction. **Incremental** (schemas 2 and 3): the
  snapshot row holds a manifest, the ids of the document text's content-defined chunks; the
  ``chunk`` table holds those chunks and the state's arrays (named by their content),
  zlib-compressed, each written once and deleted (together with others) when no snapshot uses
  it, so a snapshot writes only what changed since the last one (``docs/persistence.md``,
  "Incremental snapshots").

:meth:`NodeStore.restore` builds the node (the application's ``build()``), loads the snapshot into
it, and replays the journal rows written after it, in order: received frames go through
``Node.receive`` again and inputs through the sender's ``ingest``, so the node is exactly where
it was when it died, minus nothing. SQLite in WAL mode with ``synchronous=NORMAL`` keeps every
committed row across a process crash.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import shutil
import sqlite3
import time
import zlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from coex_core import state
from coex_core.errors import ConfigError
from coex_core.node import Node
from coex_core.storage import Storage

__all__ = ["MIGRATIONS", "SCHEMA_VERSION", "JournalRow", "NodeStore", "SqliteStorage", "StoreError", "check_store",
           "chunk_text", "migrate", "snapshot_text", "store_error"]

#: Stores written before the explicit state format held pickled snapshots, which this version
#: refuses (it never unpickles).
_PICKLE_PROTOCOL_5 = b"\x80\x05"


class StoreError(ConfigError):
    """The node's store cannot be opened, read or written. ``str()`` is one sentence that names
    the file, says what is wrong and what to do; ``kind`` says which:

    * ``"full"``: the disk is full (SQLite's ``SQLITE_FULL``, ``ENOSPC``);
    * ``"read-only"``: the file, its folder or its file system is not writable;
    * ``"damaged"``: the file is not a store, or a page of it is corrupt;
    * ``"in use"``: another process has the store open for writing;
    * ``"no folder"``: the folder the store should be in does not exist;
    * ``"io"``: the disk failed to read or write (``SQLITE_IOERR``);
    * ``"error"``: anything else SQLite refused.

    A :class:`~coex_core.errors.ConfigError` (the daemons print it without a traceback); a
    running node that meets one keeps its link and commands running (``docs/persistence.md``,
    "When the disk fails")."""

    def __init__(self, text: str, *, kind: str, path: Path) -> None:
        super().__init__(text)
        self.kind = kind
        self.path = path


# SQLite's primary result codes (https://sqlite.org/rescode.html)
_SQLITE_PERM, _SQLITE_BUSY, _SQLITE_LOCKED, _SQLITE_READONLY, _SQLITE_IOERR = 3, 5, 6, 8, 10
_SQLITE_CORRUPT, _SQLITE_FULL, _SQLITE_CANTOPEN, _SQLITE_NOTADB = 11, 13, 14, 26


def _free(path: Path) -> str:
    """" (N bytes free)", or "" when the disk cannot be asked."""
    try:
        free = shutil.disk_usage(path.parent if path.parent.exists() else Path.cwd()).free
    except OSError:
        return ""
    if free < 10**6:
        return f" ({free} bytes free)"
    return f" ({free / 1e6:.0f} MB free on it: a quota or a size limit refuses more)"


def _no_room(path: Path) -> bool:
    """Whether the disk holding ``path`` has no room left (less than 64 KiB)."""
    try:
        return shutil.disk_usage(path.parent).free < 65536
    except OSError:
        return False


def store_error(path: Path, exc: BaseException, doing: str) -> StoreError:
    """``exc`` (an :class:`sqlite3.Error` or :class:`OSError` met while ``doing`` something to
    the store ``path``) as the :class:`StoreError` that names the file and the remedy."""
    if isinstance(exc, StoreError):
        return exc
    code = getattr(exc, "sqlite_errorcode", None)
    primary = code & 0xFF if isinstance(code, int) else None
    if isinstance(exc, OSError):
        primary = {errno.ENOSPC: _SQLITE_FULL, errno.EDQUOT: _SQLITE_FULL, errno.EROFS: _SQLITE_READONLY,
                   errno.EACCES: _SQLITE_READONLY, errno.EPERM: _SQLITE_READONLY,
                   errno.ENOENT: _SQLITE_CANTOPEN, errno.EIO: _SQLITE_IOERR}.get(exc.errno or 0, primary)
    why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    if primary in (_SQLITE_IOERR, _SQLITE_CANTOPEN) and _no_room(path):
        primary = _SQLITE_FULL  # SQLite could not make or grow its -shm or -wal file: no room
    if primary == _SQLITE_FULL:
        return StoreError(f"{path}: the disk is full{_free(path)} ({doing}): free space on it; until then "
                          "the node runs on (link and commands) but keeps nothing new across a restart",
                          kind="full", path=path)
    if primary in (_SQLITE_READONLY, _SQLITE_PERM):
        return StoreError(f"{path} is read-only ({doing}: {why}): make the file and its folder writable by "
                          "this user, or give another node.store", kind="read-only", path=path)
    if primary in (_SQLITE_CORRUPT, _SQLITE_NOTADB):
        return _damaged(path, f"{doing}: {why}")
    if primary in (_SQLITE_BUSY, _SQLITE_LOCKED):
        return StoreError(f"{path} is in use by another process ({doing}: {why}): stop the other "
                          "coex process that has it open, or give this node another store",
                          kind="in use", path=path)
    if primary == _SQLITE_CANTOPEN and not path.parent.is_dir():
        return _no_folder(path)
    if primary == _SQLITE_CANTOPEN:
        return StoreError(f"cannot open {path} ({doing}: {why}): its folder must be writable by this "
                          "user (SQLite writes its -wal and -shm files beside it)", kind="read-only", path=path)
    if primary == _SQLITE_IOERR:
        return StoreError(f"{path}: the disk failed ({doing}: {why}): check the disk (dmesg); if the "
                          f"file is damaged, move it away (mv {path} {path}.damaged) to start afresh",
                          kind="io", path=path)
    return StoreError(f"{path}: {doing} failed: {why}", kind="error", path=path)

#: Version 1 of the file's tables (what 0.1 wrote, without setting ``user_version``).
_SCHEMA_1 = """
CREATE TABLE IF NOT EXISTS journal (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL CHECK (kind IN ('rx', 'tx', 'input')),
    t REAL NOT NULL,
    link INTEGER,
    name TEXT,
    data BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS snapshot (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    journal_id INTEGER NOT NULL,
    t REAL NOT NULL,
    state BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS storage (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    key TEXT NOT NULL,
    gen INTEGER NOT NULL,
    data BLOB NOT NULL,
    UNIQUE (key, gen)
);
"""

#: The file's schema, versioned with SQLite's ``PRAGMA user_version``: migration ``k`` (SQL, run
#: in order in one transaction each) takes a store from version ``k`` to ``k + 1``. A store of
#: 0.1 has version 0 and already the tables of version 1 (``IF NOT EXISTS``). A store newer than
#: :data:`SCHEMA_VERSION` is refused: an older CoEx must not write into it.
MIGRATIONS: tuple[str, ...] = (
    _SCHEMA_1,  # 0 -> 1: journal, snapshot, meta, storage
    # 1 -> 2: incremental snapshots. The snapshot row's state becomes a manifest (the text's
    # chunk hashes); the chunks (pieces of the document's text, and its arrays by content;
    # zlib-compressed) are rows of their own, written once and kept while a snapshot uses them. A store of version 1
    # keeps its last snapshot (a whole container) until the next snapshot replaces it.
    """CREATE TABLE IF NOT EXISTS chunk (
        hash BLOB PRIMARY KEY,
        dtype TEXT,
        shape TEXT,
        data BLOB NOT NULL
    )""",
    # 2 -> 3: chunks by row id, in the order written, with no index on their hash (the store
    # keeps the hash -> id map in memory); a manifest lists the text's chunk ids (compressed).
    # A snapshot's new chunks then fill pages at the end of the table, where a hash key put each
    # on a page of its own, and its manifest is a few hundred bytes, not 16 per chunk: the pages
    # a snapshot writes (bench/disk_writes.py). Manifests of version 2 (hashes) are still read.
    """CREATE TABLE chunk3 (
        id INTEGER PRIMARY KEY,
        hash BLOB NOT NULL,
        dtype TEXT,
        shape TEXT,
        data BLOB NOT NULL
    );
    INSERT INTO chunk3 (hash, dtype, shape, data) SELECT hash, dtype, shape, data FROM chunk;
    DROP TABLE chunk;
    ALTER TABLE chunk3 RENAME TO chunk""",
)
SCHEMA_VERSION = len(MIGRATIONS)


def migrate(db: sqlite3.Connection, path: Path) -> int:
    """Bring the store's schema to :data:`SCHEMA_VERSION`; returns the version it had."""
    found = int(db.execute("PRAGMA user_version").fetchone()[0])
    if found > SCHEMA_VERSION:
        raise ConfigError(f"{path} was written by a newer CoEx (store schema {found}; this one knows up to "
                          f"{SCHEMA_VERSION}): open it with that version, or give another store")
    for k in range(found, SCHEMA_VERSION):
        db.execute("BEGIN IMMEDIATE")
        try:
            for statement in filter(None, (x.strip() for x in MIGRATIONS[k].split(";"))):
                db.execute(statement)
            db.execute(f"PRAGMA user_version = {k + 1}")
            db.execute("COMMIT")
        except BaseException:
            _rollback(db)
            raise
    return found


def _no_folder(path: Path) -> StoreError:
    return StoreError(f"{path}: no folder {path.parent}: create it, or give another node.store",
                      kind="no folder", path=path)


def _damaged(path: Path, why: str) -> StoreError:
    return StoreError(f"{path} is damaged ({why}): move it away (mv {path} {path}.damaged) to start afresh; "
                      "the node then starts empty", kind="damaged", path=path)


def check_store(path: str | Path) -> list[StoreError]:
    """What :class:`NodeStore` would refuse when the daemon opens ``path`` (``coex config
    check`` asks this, writing nothing): its folder missing or not writable, the file
    read-only, damaged (SQLite's ``quick_check``) or written by a newer CoEx. A file that is not
    there yet is no problem (it is created)."""
    path = Path(path)
    if not path.parent.is_dir():
        return [_no_folder(path)]
    if not os.access(path.parent, os.W_OK | os.X_OK):
        return [StoreError(f"{path} is read-only: its folder {path.parent} cannot be written (SQLite writes "
                           f"{path.name}-wal and -shm beside it): make the folder writable by this user, or give "
                           "another node.store", kind="read-only", path=path)]
    if not path.exists():
        return []
    if not path.is_file() or not os.access(path, os.R_OK | os.W_OK):
        return [StoreError(f"{path} is read-only (or not a file): make it writable by this user, or give "
                           "another node.store", kind="read-only", path=path)]
    try:
        db = sqlite3.connect(f"file:{quote(str(path))}?mode=ro", uri=True, isolation_level=None)
    except sqlite3.Error as exc:
        return [store_error(path, exc, "opening it")]
    try:
        rows = [str(r[0]) for r in db.execute("PRAGMA quick_check(5)")]
        if rows != ["ok"]:
            return [_damaged(path, f"SQLite's check: {'; '.join(rows)}")]
        found = int(db.execute("PRAGMA user_version").fetchone()[0])
        if found > SCHEMA_VERSION:
            return [StoreError(f"{path} was written by a newer CoEx (store schema {found}; this one knows up to "
                               f"{SCHEMA_VERSION}): open it with that version, or give another store",
                               kind="error", path=path)]
    except sqlite3.Error as exc:
        return [store_error(path, exc, "reading it")]
    finally:
        db.close()
    return []


#: seconds a store waits for another process to let go of it before it is "in use"
LOCK_WAIT = 2.0

#: WAL pages (of 4 KiB) between two checkpoints; the WAL file is kept to that size
WAL_PAGES = 2048

#: chunks no manifest names any more, or their bytes (uncompressed, of those this process saw),
#: at least, before a snapshot deletes them (together, in its transaction)
GARBAGE_CHUNKS = 2048
GARBAGE_BYTES = 2**20

#: a snapshot row's state in version 2: this, then the 16-byte hashes of the text's chunks
_MANIFEST = b"COEXPARTS\n"
#: in version 3: this, then the text's chunk ids (their differences, int64, zlib)
_MANIFEST3 = b"COEXPART3\n"
#: content-defined chunking of the text: a cut where the hash of the last 32 bytes has its low
#: bits zero (512 bytes apart on average), at least 128 bytes and at most 4 KiB apart
_WINDOW, _MASK, _MIN_CHUNK, _MAX_CHUNK = 32, 511, 128, 4096
_GEAR = np.random.default_rng(0xC0E5).integers(0, 2**32, 256, dtype=np.uint64).astype(np.uint32)
_MIX = np.random.default_rng(0xC0E6).integers(1, 2**32, _WINDOW, dtype=np.uint64).astype(np.uint32) | np.uint32(1)


def chunk_text(data: bytes, mask: int = _MASK, min_chunk: int = _MIN_CHUNK, max_chunk: int = _MAX_CHUNK) -> list[bytes]:
    """``data`` cut where its content says (content-defined chunking): an edit changes the
    chunks around it, and the rest cut as before, whatever moved."""
    b = np.frombuffer(data, np.uint8)
    n = b.size
    if n <= min_chunk:
        return [bytes(data)] if n else []
    g = _GEAR[b]
    h = np.zeros(n, np.uint32)
    for j in range(_WINDOW):  # h[i] = sum_j MIX[j] * GEAR[b[i - j]] (mod 2^32)
        h[j:] += _MIX[j] * g[: n - j]
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x2C1B3C6D)
    h ^= h >> np.uint32(12)
    candidates = np.flatnonzero((h & np.uint32(mask)) == 0) + 1
    out: list[bytes] = []
    start = 0
    for c in candidates.tolist():
        while c - start > max_chunk:
            out.append(bytes(data[start:start + max_chunk]))
            start += max_chunk
        if c - start >= min_chunk and c < n:
            out.append(bytes(data[start:c]))
            start = c
    while n - start > max_chunk:
        out.append(bytes(data[start:start + max_chunk]))
        start += max_chunk
    out.append(bytes(data[start:]))
    return out


def _digest(data: bytes) -> bytes:
    return hashlib.blake2b(data, digest_size=16).digest()


def _chunk_ids(db: sqlite3.Connection) -> dict[bytes, int]:
    """Every chunk the file holds: its hash -> its row id (a scan: the table has no index on
    the hash)."""
    return {bytes(h): int(i) for i, h in db.execute("SELECT id, hash FROM chunk")}


class _ChunkArrays(Mapping[str, np.ndarray]):
    """A snapshot's arrays by name, read from the store's chunks when the state asks for them."""

    def __init__(self, db: sqlite3.Connection, ids: Mapping[bytes, int]) -> None:
        self.db, self.ids = db, ids

    def __getitem__(self, name: str) -> np.ndarray:
        i = self.ids.get(bytes.fromhex(name.split(".")[0]))
        row = None if i is None else self.db.execute("SELECT dtype, shape, data FROM chunk WHERE id = ?",
                                                     (i,)).fetchone()
        if row is None or row[0] is None:
            raise KeyError(f"array {name} is not in the store")
        shape = tuple(int(x) for x in str(row[1]).split(",") if x)
        return np.frombuffer(zlib.decompress(bytes(row[2])), np.dtype(str(row[0]))).reshape(shape)

    def __iter__(self) -> Iterator[str]:
        return iter(())

    def __len__(self) -> int:
        return 0


def _manifest_ids(blob: bytes) -> list[int]:
    """The chunk ids a version-3 manifest lists (zlib of their differences, int64)."""
    deltas = np.frombuffer(zlib.decompress(blob[len(_MANIFEST3):]), "<i8")
    return [int(x) for x in np.cumsum(deltas)]


def _encode_manifest(ids: list[int]) -> bytes:
    return _MANIFEST3 + zlib.compress(np.diff(np.asarray(ids, np.int64), prepend=0).astype("<i8").tobytes(), 6)


def _manifest_text(db: sqlite3.Connection, blob: bytes, ids: Mapping[bytes, int] | None = None) -> bytes:
    """The document text a snapshot row's manifest lists (version 3: chunk ids; version 2:
    chunk hashes, found through ``ids``, the hash -> id map, read when not given)."""
    if blob.startswith(_MANIFEST3):
        wanted: list[int | None] = list(_manifest_ids(blob))
        names = [f"#{i}" for i in wanted]
    else:
        hashes = [blob[i:i + 16] for i in range(len(_MANIFEST), len(blob), 16)]
        ids = _chunk_ids(db) if ids is None else ids
        wanted = [ids.get(h) for h in hashes]
        names = [h.hex() for h in hashes]
    parts = []
    for i, name in zip(wanted, names, strict=True):
        row = None if i is None else db.execute("SELECT data FROM chunk WHERE id = ?", (i,)).fetchone()
        if row is None:
            raise state.StateError(f"text chunk {name} is missing")
        parts.append(zlib.decompress(bytes(row[0])))
    return b"".join(parts)


def _rollback(db: sqlite3.Connection) -> None:
    """Roll back the open transaction, if SQLite has not already (it may have, on a full disk or
    an I/O error): never an error of its own that would hide the one being handled."""
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")


@contextlib.contextmanager
def _read_transaction(db: sqlite3.Connection) -> Iterator[None]:
    """One read transaction: every SELECT inside sees the same committed state of the file,
    whatever another process commits meanwhile (WAL). Without it, a reader that read the
    snapshot's manifest and then its chunks could see a newer snapshot's transaction delete
    chunks in between, and take a sound store for a damaged one."""
    if db.in_transaction:  # already in one (the caller's)
        yield
        return
    db.execute("BEGIN")
    try:
        yield
    finally:
        _rollback(db)  # nothing was written: ending it is all


def snapshot_text(db: sqlite3.Connection) -> bytes | None:
    """The JSON text of the snapshot an open store file holds (the document of
    :func:`coex_core.state.dumps_parts`, or of the whole container a version-1 store kept;
    None without a snapshot): for a look from outside the node's process, which may be
    writing it meanwhile (read in one transaction)."""
    with _read_transaction(db):
        row = db.execute("SELECT state FROM snapshot WHERE id = 1").fetchone()
        if row is None:
            return None
        blob = bytes(row[0])
        if blob.startswith((_MANIFEST, _MANIFEST3)):
            return _manifest_text(db, blob)
    n = int.from_bytes(blob[len(state.MAGIC):len(state.MAGIC) + 4], "big")
    return blob[len(state.MAGIC) + 4:len(state.MAGIC) + 4 + n]


class SqliteStorage(Storage):
    """The modalities' out-of-core storage (:mod:`coex_core.storage`) in the node's SQLite file,
    consistent with its snapshots.

    Rows carry a *generation*: the snapshot that last committed is generation ``g`` (``meta``
    key ``storage_gen``); what is put after it is written as generation ``g + 1`` at once (so a
    spilled tile leaves memory) but counts only once the next snapshot commits, in the
    snapshot's own transaction, which also deletes the rows it supersedes. Opening the store
    discards rows newer than the last snapshot: the snapshot and the journal replayed after it
    rebuild them, so nothing is counted twice after a crash.

    When the file cannot be written (a full disk, ``on_error`` is told), what is put stays in
    memory and is written with the next snapshot that commits: nothing is lost while the node
    runs. A read-only look (``NodeStore(path, read_only=True)``) holds the committed rows in
    memory (:meth:`load_committed`), so the node it restored reads what its snapshot named
    whatever the writing process does next."""

    def __init__(self, db: sqlite3.Connection, path: Path | None = None, *,
                 on_error: Callable[[BaseException, str], None] | None = None, read_only: bool = False) -> None:
        self.db = db
        self.path = path
        self.on_error = on_error
        #: after :meth:`detach`: what was put since (the file is only read then)
        self._overlay: dict[str, bytes] | None = None
        #: put while the file could not be written: written with the next snapshot
        self._unsaved: dict[str, bytes] = {}
        #: rows of a generation newer than the last snapshot (left by a crash) could not be
        #: deleted at open (a full disk): the next snapshot deletes them first, and until then
        #: nothing is written to the file's generation ``committed + 1``
        self._stale = False
        #: every committed row is in :attr:`_overlay` (:meth:`load_committed`)
        self._loaded = False
        row = db.execute("SELECT value FROM meta WHERE key = 'storage_gen'").fetchone()
        self.committed = int(row[0]) if row is not None else 0
        if not read_only:
            try:
                db.execute("DELETE FROM storage WHERE gen > ?", (self.committed,))
            except sqlite3.Error as exc:
                self._stale = True
                self._failed(exc, "discarding what was put after the last snapshot")
        self.writes = 0

    def _failed(self, exc: BaseException, doing: str) -> None:
        if self.on_error is None:
            raise store_error(self.path or Path("store"), exc, doing) from exc
        self.on_error(exc, doing)

    def load_committed(self) -> None:
        """Hold every row of the last committed snapshot in memory and read the file no more
        (a read-only look at a store another process writes)."""
        rows = self.db.execute("SELECT key, data FROM storage WHERE gen <= ? ORDER BY gen", (self.committed,))
        self._overlay = {str(k): bytes(d) for k, d in rows}
        self._loaded = True

    def detach(self) -> None:
        """The store closes: a node restored from it may still be used (a look at a stopped or
        running node's state). Reads go on from the file through a read-only connection; puts
        stay in memory and are never written."""
        if self._overlay is not None:
            return  # already in memory
        self._overlay = dict(self._unsaved)
        if self.path is not None:
            self.db = sqlite3.connect(f"file:{quote(str(self.path))}?mode=ro", uri=True, isolation_level=None,
                                      check_same_thread=False)

    def get(self, key: str) -> bytes | None:
        if self._overlay is not None and key in self._overlay:
            return self._overlay[key]
        if key in self._unsaved:
            return self._unsaved[key]
        if self._loaded:
            return None  # a look holds the committed rows: what is not there was not committed
        newest = self.committed if self._stale else self.committed + 1
        try:
            row = self.db.execute("SELECT data FROM storage WHERE key = ? AND gen <= ? ORDER BY gen DESC LIMIT 1",
                                  (key, newest)).fetchone()
        except sqlite3.Error as exc:
            raise store_error(self.path or Path("store"), exc, f"reading {key}") from exc
        return None if row is None else bytes(row[0])

    def put(self, key: str, data: bytes) -> None:
        if self._overlay is not None:
            self._overlay[key] = bytes(data)
            return
        if self._unsaved or self._stale:  # the file is failing: keep the order of what was put
            self._unsaved[key] = bytes(data)
            return
        try:
            self.db.execute("INSERT OR REPLACE INTO storage (key, gen, data) VALUES (?, ?, ?)",
                            (key, self.committed + 1, sqlite3.Binary(data)))
        except sqlite3.Error as exc:
            self._unsaved[key] = bytes(data)
            self._failed(exc, f"writing {key}")
            return
        self.writes += 1

    def keys(self, prefix: str = "") -> list[str]:
        rows = self.db.execute("SELECT DISTINCT key FROM storage WHERE substr(key, 1, ?) = ?",
                               (len(prefix), prefix))
        out = {str(r[0]) for r in rows}
        out.update(k for k in self._unsaved if k.startswith(prefix))
        if self._overlay is not None:
            out.update(k for k in self._overlay if k.startswith(prefix))
        return sorted(out)

    def nbytes(self) -> int:
        held = int(self.db.execute("SELECT COALESCE(SUM(length(data)), 0) FROM storage").fetchone()[0])
        return held + sum(len(v) for v in self._unsaved.values())

    def commit(self) -> None:
        """Make what was put count (inside the snapshot's transaction; :meth:`committed_now`
        once it committed, :meth:`rolled_back` if it did not)."""
        g = self.committed + 1
        if self._stale:
            self.db.execute("DELETE FROM storage WHERE gen > ?", (self.committed,))
        if self._unsaved:
            self.db.executemany("INSERT OR REPLACE INTO storage (key, gen, data) VALUES (?, ?, ?)",
                                [(k, g, sqlite3.Binary(v)) for k, v in self._unsaved.items()])
        self.db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('storage_gen', ?)", (str(g),))
        self.db.execute("DELETE FROM storage WHERE gen < ? AND key IN (SELECT key FROM storage WHERE gen = ?)",
                        (g, g))

    def committed_now(self) -> None:
        """The snapshot's transaction committed: what was put is generation ``committed``."""
        self.committed += 1
        self.writes += len(self._unsaved)
        self._unsaved.clear()
        self._stale = False


@dataclass(frozen=True)
class JournalRow:
    id: int
    kind: str
    t: float
    link: int | None
    name: str | None
    data: bytes


class NodeStore:
    """The persistent state of one node in the SQLite file ``path`` (created if missing).

    One process writes a store at a time: a second one is refused (:class:`StoreError`, ``"in
    use"``), as two daemons on one file would undo each other's snapshots. ``read_only=True``
    opens it for a look (another process may be writing it): nothing is written, and
    :meth:`restore` reads the last committed snapshot whole.

    Anything the file cannot do is a :class:`StoreError` naming it, what is wrong and what to do:
    at open, a damaged file (SQLite's ``quick_check``), a read-only one, a missing folder; while
    the node runs, a write that fails (a full disk) raises it too, and :attr:`problem` holds it
    until a snapshot commits again."""

    def __init__(self, path: str | Path, *, snapshot_interval: float = 5.0,
                 journal_tx: bool = True, compact: bool = True, read_only: bool = False) -> None:
        self.path = Path(path)
        #: drop the journal rows a snapshot includes, in the snapshot's transaction (the file
        #: stays the size of one snapshot plus what came since); ``False`` keeps the whole
        #: journal as a record (a test that audits what was sent and received)
        self.compact = compact
        self.snapshot_interval = float(snapshot_interval)
        #: journal every frame sent (``tx`` rows, a record, never replayed): only a store that
        #: keeps its journal (``compact=False``) keeps them; a compacted one would delete each at
        #: the snapshot that follows it at once, so it does not write them (they were a fifth of
        #: the vehicle's disk writes: ``bench/disk_writes.py``)
        self.journal_tx = journal_tx and not compact
        #: a look at the file, never a write (see the class docstring)
        self.read_only = read_only
        #: the newest write that failed (None: the store keeps everything); cleared when a
        #: snapshot commits
        self.problem: StoreError | None = None
        self._lock_fd: int | None = None
        #: the disk was full at open: the node runs from the file as it is (read only) and
        #: every write is refused, until a snapshot finds room to open it for writing
        self.degraded = False
        self.db: sqlite3.Connection
        try:
            if read_only:
                self._open_read_only()
            else:
                try:
                    self._open()
                except (sqlite3.Error, OSError) as exc:
                    err = store_error(self.path, exc, "opening it")
                    if err.kind != "full" or self._lock_fd is None:
                        raise err from exc
                    self._open_degraded(err)
        except StoreError:
            self._close_quietly()
            raise
        except (sqlite3.Error, OSError) as exc:
            self._close_quietly()
            raise store_error(self.path, exc, "opening it") from exc
        self._last_snapshot: float | None = None
        self._dirty = False
        #: ``extra()`` is saved with every snapshot, in the same document as the node (objects
        #: shared with the node stay shared): an application's own state, e.g. the console's.
        self.extra: Callable[[], Any] | None = None
        #: What ``extra()`` returned at the snapshot :meth:`restore` loaded (None without one).
        self.restored_extra: Any = None
        #: rows journaled by kind, snapshots written (``snapshot_bytes``: their total size, what
        #: the file's disk takes in writes), rows replayed at :meth:`restore`; ``failed``:
        #: writes the file refused (a full disk)
        self.stats = {"rx": 0, "tx": 0, "input": 0, "snapshots": 0, "snapshot_bytes": 0, "state_bytes": 0,
                      "replayed": 0, "failed": 0}
        self._storage: SqliteStorage | None = None
        #: the chunks the file holds, hash -> row id (None: not read yet); the next row id
        self._held: dict[bytes, int] | None = None
        self._next_id = 1
        #: chunks the file holds that no committed manifest names any more: deleted together
        #: once there are :data:`GARBAGE_CHUNKS` of them (or as many as the state has), in the
        #: transaction of a snapshot that does not name them either
        self._garbage: set[bytes] = set()
        #: the size of the chunks this store saw (uncompressed), for :data:`GARBAGE_BYTES`
        self._sizes: dict[bytes, int] = {}

    def _open(self) -> None:
        if not self.path.parent.is_dir():
            raise _no_folder(self.path)
        # one writer at a time: an advisory lock on the file, held while the store is open
        # (released by the kernel if the process dies, kill -9 included)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        self._lock_fd = fd
        deadline = time.monotonic() + LOCK_WAIT
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                # a process that was killed a moment ago may have left a child of its own between
                # fork and exec (a library running a command), which holds the lock until it execs
                if time.monotonic() >= deadline:
                    raise StoreError(f"{self.path} is in use by another process (a second coex vehicle or topside "
                                     "on the same store?): stop it, or give this node another store",
                                     kind="in use", path=self.path) from None
                time.sleep(0.05)
        # a daemon opens its store in one thread and may run its loop in another (one at a
        # time: the runner's steps and the final snapshot never overlap)
        self.db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        mode = self.db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise StoreError(f"{self.path}: SQLite refused WAL mode ({mode})", kind="error", path=self.path)
        self.db.execute("PRAGMA synchronous=NORMAL")
        # a checkpoint every WAL_PAGES pages (8 MiB), and the WAL file shrinks back to that size
        # after one (it kept its high-water size, about four times the snapshot, before 0.3). A
        # checkpoint copies each page the WAL holds into the file once, however many snapshots
        # changed it: every 256 pages (1 MiB) it copied the pages every snapshot touches (the
        # manifest's, the chunk index's) ten times as often (bench/disk_writes.py: a fifth of
        # the vehicle's disk writes)
        self.db.execute(f"PRAGMA wal_autocheckpoint={WAL_PAGES}")
        self.db.execute(f"PRAGMA journal_size_limit={WAL_PAGES * 4096}")
        self._check_pages()
        #: the schema version the file had when opened (0: a store of CoEx 0.1)
        self.schema_found = migrate(self.db, self.path)

    def _open_degraded(self, err: StoreError) -> None:
        """The disk is full at open (SQLite cannot even make its ``-shm`` file): read the file as
        it is, with no WAL (a store closed cleanly has none; one with a WAL still there cannot
        be read without it: refused), and refuse every write with ``err`` until
        :meth:`snapshot` finds room to open it for writing (:meth:`_reopen`)."""
        with contextlib.suppress(Exception):
            self.db.close()
        wal = Path(f"{self.path}-wal")
        if wal.exists() and wal.stat().st_size > 0:
            raise err
        self.db = sqlite3.connect(f"file:{quote(str(self.path))}?mode=ro&immutable=1", uri=True,
                                  isolation_level=None, check_same_thread=False)
        self._check_pages()
        found = int(self.db.execute("PRAGMA user_version").fetchone()[0])
        if found > SCHEMA_VERSION:
            raise ConfigError(f"{self.path} was written by a newer CoEx (store schema {found}; this one knows up to "
                              f"{SCHEMA_VERSION}): open it with that version, or give another store")
        self.schema_found = found
        self.degraded = True
        self.problem = StoreError(f"{err} (at start: the node runs from the store as it was, and writes it "
                                  "again once there is room)", kind="full", path=self.path)

    def _reopen(self) -> None:
        """Degraded: open the file for writing now, if the disk has room (:class:`StoreError`
        if not); the storage and the snapshots go on with the new connection."""
        try:
            db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            try:
                if str(db.execute("PRAGMA journal_mode=WAL").fetchone()[0]).lower() != "wal":
                    raise StoreError(f"{self.path}: SQLite refused WAL mode", kind="error", path=self.path)
                db.execute("PRAGMA synchronous=NORMAL")
                db.execute(f"PRAGMA wal_autocheckpoint={WAL_PAGES}")
                db.execute(f"PRAGMA journal_size_limit={WAL_PAGES * 4096}")
                migrate(db, self.path)
            except BaseException:
                db.close()
                raise
        except sqlite3.Error as exc:
            raise self._failed(exc, "opening it for writing") from exc
        old, self.db = self.db, db
        old.close()
        if self._storage is not None:
            self._storage.db = db  # still stale: the next snapshot discards rows of no snapshot
        self.degraded = False
        self._held = None

    def _open_read_only(self) -> None:
        if not self.path.is_file():
            raise StoreError(f"no store {self.path}", kind="no folder" if not self.path.parent.is_dir() else "error",
                             path=self.path)
        self.db = sqlite3.connect(f"file:{quote(str(self.path))}?mode=ro", uri=True, isolation_level=None,
                                  check_same_thread=False)
        found = int(self.db.execute("PRAGMA user_version").fetchone()[0])
        if found > SCHEMA_VERSION:
            raise ConfigError(f"{self.path} was written by a newer CoEx (store schema {found}; this one knows up to "
                              f"{SCHEMA_VERSION}): open it with that version")
        self.schema_found = found

    def _check_pages(self) -> None:
        """A damaged file is named now, at start, not by a crash in the middle of the dive
        (``PRAGMA quick_check``: every page of every table and index read; a few ms for a
        node's store)."""
        rows = [str(r[0]) for r in self.db.execute("PRAGMA quick_check(5)")]
        if rows != ["ok"]:
            raise _damaged(self.path, f"SQLite's check: {'; '.join(rows)}")

    def _close_quietly(self) -> None:
        with contextlib.suppress(Exception):
            if getattr(self, "db", None) is not None:
                self.db.close()
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._lock_fd)
            self._lock_fd = None

    # --------------------------------------------------------------------- failures
    def _failed(self, exc: BaseException, doing: str) -> StoreError:
        """A write that failed: :attr:`problem`, counted; the error to raise."""
        err = store_error(self.path, exc, doing)
        self.problem = err
        self.stats["failed"] += 1
        return err

    def _storage_failed(self, exc: BaseException, doing: str) -> None:
        self._failed(exc, doing)

    def _writable(self) -> None:
        if self.read_only:
            raise StoreError(f"{self.path} was opened read-only (a look): it is not written",
                             kind="read-only", path=self.path)
        if self.degraded:
            assert self.problem is not None
            self.stats["failed"] += 1
            raise self.problem

    def storage(self) -> SqliteStorage:
        """The modalities' out-of-core storage in this file (:class:`SqliteStorage`); what
        :meth:`restore` attaches to the node."""
        if self._storage is None:
            try:
                self._storage = SqliteStorage(self.db, self.path, on_error=self._storage_failed,
                                              read_only=self.read_only or self.degraded)
            except sqlite3.Error as exc:
                raise store_error(self.path, exc, "reading its storage") from exc
            if self.degraded:
                self._storage._stale = True  # puts kept in memory; the first snapshot discards the rest
        return self._storage

    # ------------------------------------------------------------------------- journal
    def _append(self, kind: str, t: float, data: bytes, link: int | None = None,
                name: str | None = None, mark: str | None = None) -> int:
        self._writable()
        try:
            if mark is None:
                cur = self.db.execute("INSERT INTO journal (kind, t, link, name, data) VALUES (?, ?, ?, ?, ?)",
                                      (kind, float(t), link, name, sqlite3.Binary(data)))
            else:  # the row and the mark, in one transaction: both or neither
                self.db.execute("BEGIN IMMEDIATE")
                try:
                    cur = self.db.execute("INSERT INTO journal (kind, t, link, name, data) VALUES (?, ?, ?, ?, ?)",
                                          (kind, float(t), link, name, sqlite3.Binary(data)))
                    self.db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (mark, str(t)))
                    self.db.execute("COMMIT")
                except BaseException:
                    _rollback(self.db)
                    raise
        except sqlite3.Error as exc:
            raise self._failed(exc, f"journaling {'a received frame' if kind == 'rx' else 'a sent frame' if kind == 'tx' else 'an input of ' + str(name)}") from exc
        self.stats[kind] += 1
        return int(cur.lastrowid or 0)

    def record_rx(self, link: int, frame: bytes, t: float) -> int:
        """Journal a received frame (before the node sees it)."""
        row = self._append("rx", t, bytes(frame), link=link)
        self._dirty = True
        return row

    def record_tx(self, link: int, frame: bytes, t: float) -> int:
        """Journal a sent frame (a record; nothing when :attr:`journal_tx` is off: 0)."""
        if not self.journal_tx:
            return 0
        return self._append("tx", t, bytes(frame), link=link)

    def record_input(self, name: str, data: Any, t: float, *, mark: str | None = None) -> int:
        """Journal an input of sender ``name`` (before the sender ingests it). ``mark``: a
        ``meta`` key set in the same transaction (an application's record that it took this
        input, e.g. an image file: :meth:`marked`), so the two never disagree after a crash."""
        row = self._append("input", t, state.dumps(data), name=name, mark=mark)
        self._dirty = True
        return row

    def marked(self, prefix: str) -> list[str]:
        """The ``meta`` keys that start with ``prefix`` (the marks of :meth:`record_input`), oldest
        first."""
        rows = self.db.execute("SELECT key FROM meta WHERE substr(key, 1, ?) = ? ORDER BY rowid",
                               (len(prefix), prefix))
        return [str(r[0]) for r in rows]

    def journal(self, kind: str | None = None, after: int = 0) -> Iterator[JournalRow]:
        """Journal rows after id ``after`` (all kinds, or one), in order."""
        q = "SELECT id, kind, t, link, name, data FROM journal WHERE id > ?"
        args: tuple[Any, ...] = (after,)
        if kind is not None:
            q += " AND kind = ?"
            args += (kind,)
        for row in self.db.execute(q + " ORDER BY id", args):
            yield JournalRow(int(row[0]), row[1], float(row[2]), row[3], row[4], bytes(row[5]))

    def count(self, kind: str) -> int:
        return int(self.db.execute("SELECT COUNT(*) FROM journal WHERE kind = ?", (kind,)).fetchone()[0])

    def last_input(self, name: str) -> JournalRow | None:
        row = self.db.execute("SELECT id, kind, t, link, name, data FROM journal WHERE kind = 'input' "
                              "AND name = ? ORDER BY id DESC LIMIT 1", (name,)).fetchone()
        return None if row is None else JournalRow(int(row[0]), row[1], float(row[2]), row[3], row[4], bytes(row[5]))

    # ------------------------------------------------------------------------ snapshots
    def snapshot(self, node: Node, t: float) -> None:
        """Save the node's state, consistent with the journal so far (one transaction).

        Incremental: the state (:meth:`Node.export_parts <coex_core.node.Node.export_parts>`)
        is its document's text, cut into content-defined chunks, and its arrays, named by their
        content; only the chunks the file does not hold yet are written, with the snapshot row
        (the list of the text's chunks), and the chunks no longer used are deleted, all in the
        same transaction: a manifest is never committed without its chunks, nor a chunk deleted
        while the committed manifest names it, wherever the process dies.
        ``stats["snapshot_bytes"]`` counts what was written, ``stats["state_bytes"]`` the size
        of the states saved. :class:`StoreError` when the file refuses (a full disk): nothing
        of this snapshot is in the file, the previous one stands."""
        if self.read_only:
            self._writable()
        if self.degraded:
            self._reopen()
        extra = self.extra() if self.extra is not None else None
        text, arrays = node.export_parts(extra)
        pieces = chunk_text(text)
        digests = [_digest(p) for p in pieces]
        wanted: dict[bytes, tuple[str | None, str | None, Any]] = {
            d: (None, None, p) for d, p in zip(digests, pieces, strict=True)}
        for name, a in arrays.items():
            a = np.ascontiguousarray(a)
            wanted[bytes.fromhex(name.split(".")[0])] = (a.dtype.str, ",".join(map(str, a.shape)),
                                                         a.reshape(-1).view(np.uint8) if a.size else b"")
        storage = self.storage()
        written = 0
        try:
            self.db.execute("BEGIN IMMEDIATE")
            if self._held is None:  # the first snapshot since the file was opened
                self._held = _chunk_ids(self.db)
                self._next_id = int(self.db.execute("SELECT COALESCE(MAX(id), 0) FROM chunk").fetchone()[0]) + 1
            held = self._held
            garbage = (self._garbage | (held.keys() - wanted.keys())) - wanted.keys()
            gone: set[bytes] = set()
            if len(garbage) >= GARBAGE_CHUNKS or sum(self._sizes.get(h, 0) for h in garbage) >= GARBAGE_BYTES:
                # a chunk no manifest names is deleted together with others (deleting each at
                # the snapshot that dropped it rewrote as many pages of the file every time)
                gone = garbage
                self.db.executemany("DELETE FROM chunk WHERE id = ?", [(held[h],) for h in gone])
            ids = {h: held[h] for h in wanted if h in held}
            rows = []
            for h, (dt, sh, d) in wanted.items():
                if h not in ids:  # new: at the end of the table, in the order written
                    ids[h] = self._next_id
                    self._next_id += 1
                    rows.append((ids[h], h, dt, sh, zlib.compress(d, 1)))
            if rows:
                self.db.executemany("INSERT INTO chunk (id, hash, dtype, shape, data) VALUES (?, ?, ?, ?, ?)", rows)
                written += sum(len(r[4]) for r in rows)
            manifest = _encode_manifest([ids[d] for d in digests])
            written += len(manifest)
            last = self.db.execute("SELECT COALESCE(MAX(id), 0) FROM journal").fetchone()[0]
            self.db.execute("INSERT OR REPLACE INTO snapshot (id, journal_id, t, state) VALUES (1, ?, ?, ?)",
                            (int(last), float(t), sqlite3.Binary(manifest)))
            if self.compact:
                self.db.execute("DELETE FROM journal WHERE id <= ?", (int(last),))
            storage.commit()
            self.db.execute("COMMIT")
        except BaseException as exc:
            _rollback(self.db)
            self._held = None  # read again from the file
            self._garbage = set()  # (what the file holds and no manifest names: found again)
            if isinstance(exc, sqlite3.Error):
                raise self._failed(exc, "saving a snapshot") from exc
            raise
        storage.committed_now()
        self._garbage = garbage - gone
        self._held = {**ids, **{h: held[h] for h in self._garbage}}
        for h, (_, _, d) in wanted.items():
            self._sizes[h] = len(d)
        for h in gone:
            self._sizes.pop(h, None)
        self._last_snapshot = t
        self._dirty = False
        self.problem = None
        self.stats["snapshots"] += 1
        self.stats["snapshot_bytes"] += written
        self.stats["state_bytes"] += len(text) + sum(int(a.nbytes) for a in arrays.values())

    def maybe_snapshot(self, node: Node, t: float, *, force: bool = False) -> bool:
        """Snapshot when ``force`` (a transmission is about to leave) or when something was
        journaled and ``snapshot_interval`` has passed since the last one (or a write failed
        since: the next snapshot writes what could not be written)."""
        if force or ((self._dirty or self.problem is not None)
                     and (self._last_snapshot is None or t - self._last_snapshot >= self.snapshot_interval)):
            self.snapshot(node, t)
            return True
        return False

    def saved_text(self) -> bytes | None:
        """The JSON text of the snapshot in the file (:func:`snapshot_text`)."""
        return snapshot_text(self.db)

    def has_state(self) -> bool:
        return self.db.execute("SELECT COUNT(*) FROM snapshot").fetchone()[0] > 0 or self.count("input") > 0 \
            or self.count("rx") > 0

    def restore(self, build: Callable[[], Node], *, log: Callable[[str], None] | None = None,
                clock: Callable[[], float] | None = None,
                before_replay: Callable[[Node, Any], Any] | None = None) -> Node:
        """The node as it was: ``build()`` (the node's structure: modalities, streams, links,
        keys), the last snapshot's state loaded into it, then every journal row written after
        it, replayed in order. ``log`` and ``clock`` (not saved), when given, are attached to the
        restored node. ``before_replay(node, extra)`` runs between the two (``extra``: what
        :attr:`extra` returned at that snapshot, or None), so an application can re-attach its
        own state and see the replayed frames too.

        The snapshot, its chunks, the storage's generation and the journal are read in one read
        transaction: what another process commits meanwhile (a look at a running node's
        store) is not half seen."""
        try:
            if not self.read_only:
                # discards what was put after the last snapshot: a write, before the reads
                self.storage()
            with _read_transaction(self.db):
                node, extra, rows = self._load(build)
        except sqlite3.Error as exc:
            raise store_error(self.path, exc, "reading it") from exc
        node.attach_storage(self.storage())
        if log is not None:
            node.set_log(log)
        if clock is not None:
            node.manager.clock = clock
        self.restored_extra = extra
        if before_replay is not None:
            before_replay(node, extra)
        for r in rows:
            if r.kind == "rx":
                node.receive(int(r.link or 0), r.data, r.t)
            elif r.kind == "input":
                try:
                    node.sender(str(r.name)).ingest(state.loads(r.data), r.t)
                except Exception as exc:  # it failed the first time too; the rest still counts
                    if log is not None:
                        log(f"journaled input {r.id} of {r.name} not taken again: {exc}")
            else:
                continue
            self.stats["replayed"] += 1
        return node

    def _load(self, build: Callable[[], Node]) -> tuple[Node, Any, list[JournalRow]]:
        """In one read transaction: the node built and its snapshot loaded, what ``extra`` was,
        and the journal rows after the snapshot (a look also reads the storage's committed rows)."""
        row = self.db.execute("SELECT journal_id, state FROM snapshot WHERE id = 1").fetchone()
        extra: Any = None
        node, after = build(), 0
        if row is not None:
            blob = bytes(row[1])
            if blob.startswith(_PICKLE_PROTOCOL_5):
                raise ConfigError(f"{self.path}: written by an older CoEx (a pickled snapshot), "
                                  "which this version does not read; move the file away to "
                                  "start afresh")
            try:
                if blob.startswith((_MANIFEST, _MANIFEST3)):
                    ids = _chunk_ids(self.db)
                    extra = node.restore_parts(_manifest_text(self.db, blob, ids), _ChunkArrays(self.db, ids))
                else:  # a whole container (a store of schema 1, not saved since)
                    extra = node.restore_state(blob)
            except Exception as exc:  # a damaged or foreign file: a clear error, never a crash
                if not isinstance(exc, state.StateError | KeyError | TypeError | ValueError |
                                  AttributeError | zlib.error):
                    raise
                raise StoreError(f"{self.path}: unreadable snapshot ({exc}); move the file away "
                                 f"(mv {self.path} {self.path}.damaged) to start afresh",
                                 kind="damaged", path=self.path) from exc
            after = int(row[0])
        if self.read_only:
            self.storage().load_committed()
        return node, extra, list(self.journal(after=after))

    # ----------------------------------------------------------------------------- meta
    def get(self, key: str, default: str | None = None) -> str | None:
        """A small persistent value of the application (e.g. an operator action done)."""
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return default if row is None else str(row[0])

    def set(self, key: str, value: str) -> None:
        """Set a small persistent value (:class:`StoreError` when the file refuses it)."""
        self._writable()
        try:
            self.db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, value))
        except sqlite3.Error as exc:
            raise self._failed(exc, f"setting {key}") from exc

    def delete(self, keys: list[str]) -> None:
        """Delete ``meta`` keys (one transaction; :class:`StoreError` when the file refuses)."""
        self._writable()
        try:
            self.db.execute("BEGIN IMMEDIATE")
            self.db.executemany("DELETE FROM meta WHERE key = ?", [(k,) for k in keys])
            self.db.execute("COMMIT")
        except sqlite3.Error as exc:
            _rollback(self.db)
            raise self._failed(exc, "deleting keys") from exc

    def close(self) -> None:
        with contextlib.suppress(sqlite3.Error):
            self.db.close()
        if self._lock_fd is not None:  # after SQLite's own descriptors of the file are closed
            with contextlib.suppress(OSError):
                os.close(self._lock_fd)
            self._lock_fd = None
        if self._storage is not None:
            self._storage.detach()

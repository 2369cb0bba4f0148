"""A real MOOSDB for the MOOS tests: found on PATH or where ``make moos`` builds it
(``coex_transports.moos.testing``, shared with the soak benchmark), and the fixtures.

``make moos`` (a step of ``make test``) runs ``../shared/vendor/moos/build_moos.sh``, which
builds MOOSDB under ``$WORK`` (default ``~/.cache/coex-moos``) and the pymoos wheel that the
step installs into ``.venv``. Without either, the tests that need them are skipped with the
reason.
"""

from __future__ import annotations

import os
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from coex_transports.moos.testing import MoosDB, find_moosdb, free_port

__all__ = ["MoosDB", "find_moosdb", "free_port", "moos_entry_points", "moosdb", "moosdb_path", "unique"]


def moos_entry_points() -> str | None:
    """Make the ``moos`` input and autonomy output findable as entry points when the installed
    metadata predates them (an environment installed from an older checkout, a git worktree):
    a small ``.dist-info`` holding them, taken from ``pyproject.toml``, is put on ``sys.path``.
    Returns its directory (for a child process's ``PYTHONPATH``), or None when not needed."""
    import sys
    import tomllib
    from importlib import metadata

    groups = {"coex.inputs", "coex.autonomy"}
    if all("moos" in {ep.name for ep in metadata.entry_points(group=g)} for g in groups):
        return None
    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    eps = project["project"]["entry-points"]
    root = Path(tempfile.gettempdir()) / f"coex-moos-eps-{os.getuid()}"
    info = root / "coex_moos_shim-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: coex-moos-shim\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text("".join(
        f"[{g}]\nmoos = {eps[g]['moos']}\n\n" for g in sorted(groups)))
    if str(root) not in sys.path:
        sys.path.append(str(root))
    return str(root)


def unique(prefix: str) -> str:
    """A MOOS variable or client name no other test uses."""
    return f"{prefix}_{uuid.uuid4().hex[:8].upper()}"


@pytest.fixture(scope="session")
def moosdb_path() -> str:
    exe, why = find_moosdb()
    if exe is None:
        pytest.skip(why)
    return exe


@pytest.fixture(scope="session")
def moosdb(moosdb_path: str) -> Iterator[MoosDB]:
    """A MOOSDB shared by the tests of a session (or xdist worker), killed at the end."""
    db = MoosDB(moosdb_path)
    db.start()
    yield db
    db.close()

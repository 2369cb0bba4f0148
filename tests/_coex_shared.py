"""``coex`` with the test run's shared image codings (``tests/_dives.py`` ``coex_command``):
``python tests/_coex_shared.py DIR ARGS...`` is ``python -m coex_core.cli ARGS...`` whose image
coding reads and writes the codings in ``DIR`` (the run's shared directory, ``codestreams_at``)."""

from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: ``tests`` importable
    from coex_core.cli import main
    from tests._dives import codestreams_at

    with codestreams_at(Path(sys.argv[1])):
        code = main(sys.argv[2:])
    sys.exit(code)

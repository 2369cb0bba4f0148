"""Declared options: the one schema of CoEx's configuration (a modality's sender and receiver
options, a detector's, an input's and an autonomy output's, a transport URI's query, the
deployment file's numbers, a demo scenario's).

The public face of the option schema in :mod:`coex_core.config` (``from coex.options import
...``): a module of its own, so that a plugin author's type checker finds it; the names are the
core's (the same objects). ``docs/plugins.md`` ("Options") shows how a plugin declares them.
"""

from __future__ import annotations

from coex_core.config import (
    REQUIRED,
    Option,
    OptionKind,
    Options,
    Problem,
    Problems,
    anything,
    flag,
    inferred,
    integer,
    merged_config,
    number,
    shown,
    text,
)

__all__ = [
    "REQUIRED",
    "Option",
    "OptionKind",
    "Options",
    "Problem",
    "Problems",
    "anything",
    "flag",
    "inferred",
    "integer",
    "merged_config",
    "number",
    "shown",
    "text",
]

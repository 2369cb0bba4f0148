"""The autonomy-output contract now lives in :mod:`coex_core.adapters` (exported from
:mod:`coex`); this module re-exports it for code written against 0.1's path."""

from coex_core.adapters import Autonomy, check_autonomy_options

__all__ = ["Autonomy", "check_autonomy_options"]

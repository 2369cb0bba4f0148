"""The input contract now lives in :mod:`coex_core.adapters` (exported from :mod:`coex`); this
module re-exports it for code written against 0.1's path."""

from coex_core.adapters import (
    FEEDS,
    Adapter,
    Image,
    Input,
    InputContext,
    Item,
    Nav,
    Points,
    Samples,
    adapter_problems,
    check_options,
)

__all__ = ["FEEDS", "Adapter", "Image", "Input", "InputContext", "Item", "Nav", "Points", "Samples",
           "adapter_problems", "check_options"]

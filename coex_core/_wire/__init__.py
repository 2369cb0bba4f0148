"""All construct definitions of the CoEx wire format live in this sub-package.

Nothing outside ``coex_core._wire`` imports construct. The public face of the wire format is
:mod:`coex_core.wire` (encode/decode/pack/unpack) and the frozen dataclasses of
:mod:`coex_core.messages`.
"""

"""Sub-properties of a vector value: ``location.x``, ``location.yaw``, ``location.2``."""

from __future__ import annotations

import re

from services.kernel.errors import NotFound

__all__ = ["vector_index"]

_AXES = {"x": 0, "y": 1, "z": 2, "roll": 3, "pitch": 4, "yaw": 5}
_INDEX = re.compile(r"0|[1-9][0-9]{0,8}")


def vector_index(name: str, length: int) -> int:
    """Index of sub-property ``name`` (``x y z roll pitch yaw`` or a decimal) in a vector of ``length``."""
    index = _AXES.get(name)
    if index is None:
        if _INDEX.fullmatch(name) is None:
            raise NotFound(
                f"a vector has no element {name!r}: use x, y, z, roll, pitch, yaw or an index from 0"
            )
        index = int(name)
    if index >= length:
        raise NotFound(f"a vector of {length} elements has no element {name!r} (index {index})")
    return index

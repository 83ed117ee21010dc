"""The kinds of in-process services a gateway configuration (or a device CLI) can create by name.

``[[services]] name = "scout1", type = "sim-robot", options = {start = [1, 2]}``
becomes ``create("sim-robot", start=[1, 2])``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from services.core import Resource
from services.errors import InvalidArgument
from services.simulators import SimRobot, SimSensor

__all__ = ["CATALOG", "create"]

CATALOG: dict[str, Callable[..., Resource]] = {
    "sim-robot": SimRobot,
    "sim-sensor": SimSensor,
}


def _accepted(factory: Callable[..., Resource]) -> str:
    try:
        names = [
            p.name
            for p in inspect.signature(factory).parameters.values()
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
        ]
    except (TypeError, ValueError):
        return "see its documentation"
    return ", ".join(names) or "none"


def create(kind: str, **options: Any) -> Resource:
    """Create a service object of ``kind``; InvalidArgument for an unknown kind or bad options."""
    factory = CATALOG.get(kind)
    if factory is None:
        raise InvalidArgument(f"unknown service type {kind!r}: known types are {', '.join(sorted(CATALOG))}")
    try:
        bound = inspect.signature(factory).bind(**options)
    except TypeError as e:
        raise InvalidArgument(f"bad options for {kind!r}: {e}; it accepts: {_accepted(factory)}") from None
    except ValueError:
        bound = None
    try:
        return factory(**options) if bound is None else factory(*bound.args, **bound.kwargs)
    except InvalidArgument as e:
        raise InvalidArgument(f"bad options for {kind!r}: {e.message}") from None
    except (TypeError, ValueError) as e:
        raise InvalidArgument(f"bad options for {kind!r}: {e}") from None

"""The options of an ``environment`` service, checked and put in shape (docs/configuration.md).

```
markers  = ["camera1"]                  # SERVICE [PATH]: PATH (default markers) lists markers seen
robots   = ["swarm"]                    # SERVICE [PATTERN]: default robots.*.location for a group
readings = [{ selector = "swarm robots.*.sensors.temperature", layer = "temperature" }]
grid     = { origin = [-10, -10], cell = 0.5, shape = [40, 40] }
```
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.apps.environment.grid import GridSpec
from services.kernel.errors import InvalidArgument
from services.kernel.paths import compile_pattern, validate_path, validate_pattern, validate_service_name

__all__ = [
    "MAX_SOURCES",
    "Reading",
    "Selector",
    "grid_spec",
    "location_depth",
    "location_path",
    "number",
    "readings",
    "selectors",
]

#: Sources of one kind a config may name: each is a task and a few Listens.
MAX_SOURCES = 64
_LAYER = re.compile(r"[A-Za-z0-9_-]{1,64}")


@dataclass(frozen=True, slots=True)
class Selector:
    """A service and the path pattern followed on it; ``pattern`` None: chosen from its properties."""

    service: str
    pattern: str | None

    def text(self, default: str) -> str:
        return f"{self.service} {self.pattern or default}"


@dataclass(frozen=True, slots=True)
class Reading:
    """Readings to put on a layer: where they are read, and where their location is (None: found)."""

    selector: Selector
    layer: str
    location: str | None


def _selector(text: Any, what: str) -> Selector:
    if not isinstance(text, str) or not text.split():
        raise InvalidArgument(f"{what}: expected 'SERVICE' or 'SERVICE PATH', got {text!r}")
    parts = text.split()
    if len(parts) > 2:
        raise InvalidArgument(f"{what}: expected 'SERVICE' or 'SERVICE PATH', got {text!r}")
    service = validate_service_name(parts[0])
    pattern = validate_pattern(parts[1]) if len(parts) == 2 else None
    return Selector(service, pattern)


def _listed(value: Any, what: str) -> list[Any]:
    if isinstance(value, str | Mapping) or not isinstance(value, Sequence):
        raise InvalidArgument(f"{what} must be a list, got {value!r}")
    if len(value) > MAX_SOURCES:
        raise InvalidArgument(f"{what} names {len(value)} sources; the limit is {MAX_SOURCES}")
    return list(value)


def selectors(value: Any, what: str) -> list[Selector]:
    """``["camera1", "camera2 seen"]`` → selectors; InvalidArgument saying which entry is wrong."""
    return [_selector(item, f"{what}[{i}]") for i, item in enumerate(_listed(value, what))]


def readings(value: Any) -> list[Reading]:
    """``[{selector = "S PATTERN", layer = "temperature", location = "PATTERN"}]`` (or "S PATTERN")."""
    out = []
    for i, entry in enumerate(_listed(value, "readings")):
        what = f"readings[{i}]"
        item = {"selector": entry} if isinstance(entry, str) else entry
        if not isinstance(item, Mapping):
            raise InvalidArgument(f"{what}: expected a table {{ selector = 'SERVICE PATH', layer = ... }}")
        unknown = set(item) - {"selector", "layer", "location"}
        if unknown:
            raise InvalidArgument(f"{what}: unknown keys {sorted(unknown)}; use selector, layer, location")
        selector = _selector(item.get("selector"), f"{what}.selector")
        if selector.pattern is None:
            raise InvalidArgument(f"{what}.selector: name the reading, e.g. 'thermo1 data'")
        layer = item.get("layer", "temperature")
        if not isinstance(layer, str) or not _LAYER.fullmatch(layer) or layer == "occupancy":
            raise InvalidArgument(
                f"{what}.layer: a name of letters, digits, _ and - (not occupancy, the cameras' layer), "
                f"got {layer!r}"
            )
        location = item.get("location")
        if location is not None:
            if not isinstance(location, str):
                raise InvalidArgument(f"{what}.location: a path pattern, got {location!r}")
            validate_pattern(location)
            if location.split(".")[-1] != "location":
                raise InvalidArgument(f"{what}.location: a pattern ending in location, got {location!r}")
            if location.count(".") > selector.pattern.count("."):
                raise InvalidArgument(f"{what}.location: deeper than the reading's own path")
        out.append(Reading(selector, layer, location))
    return out


def number(value: Any, what: str, low: float, high: float, *, low_open: bool = False) -> float:
    """A finite number within [low, high] (or (low, high] with ``low_open``)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InvalidArgument(f"{what} must be a number, got {value!r}")
    if value > high or value < low or (low_open and value == low):
        bound = f"more than {low:g}" if low_open else f"at least {low:g}"
        raise InvalidArgument(f"{what} must be {bound} and at most {high:g}, got {value!r}")
    return float(value)


def grid_spec(value: Any) -> GridSpec:
    """``{ origin = [x0, y0], cell = m, shape = [rows, cols] }``, each key optional."""
    if value is None:
        return GridSpec()
    if not isinstance(value, Mapping):
        raise InvalidArgument("grid must be a table { origin = [x0, y0], cell = 0.5, shape = [rows, cols] }")
    unknown = set(value) - {"origin", "cell", "shape"}
    if unknown:
        raise InvalidArgument(f"grid: unknown keys {sorted(unknown)}; use origin, cell, shape")
    default = GridSpec()
    try:
        return GridSpec.from_options(
            value.get("origin", default.origin),
            value.get("cell", default.cell),
            value.get("shape", default.shape),
        )
    except ValueError as e:
        raise InvalidArgument(str(e)) from None


def location_depth(reading_pattern: str, location: str | None, names: list[str]) -> int | None:
    """How many leading segments of a reading's path name the thing whose ``location`` it is.

    With ``location`` given, its segment count less one. Otherwise the deepest ``<prefix>.location``
    above the reading that the service lists: ``robots.*.sensors.temperature`` →
    ``robots.*.location`` (2), ``data`` → ``location`` (0). None when there is none.
    """
    if location is not None:
        return location.count(".")
    segments = reading_pattern.split(".")
    for depth in range(len(segments) - 1, -1, -1):
        candidate = compile_pattern(".".join([*segments[:depth], "location"]))
        if any(candidate(n) for n in names):
            return depth
    return None


def location_path(reading_path: str, depth: int) -> str:
    """The ``location`` beside the first ``depth`` segments of ``reading_path``."""
    head = reading_path.split(".")[:depth]
    return validate_path(".".join([*head, "location"]))

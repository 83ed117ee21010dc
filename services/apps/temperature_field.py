"""The simulated world's temperature: a base temperature plus warm (or cold) spots.

Each spot adds ``delta`` degrees at its centre, falling off as a Gaussian of standard
deviation ``radius`` metres: ``T(x, y) = base + Σ delta·exp(−d² / (2·radius²))``. The
simulated robots read it with their ``sensors.temperature`` (services.apps.simulators), so a
swarm driving around fills the environment model's ``temperature`` grid.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.kernel.errors import InvalidArgument

__all__ = ["DEFAULT_FIELD", "MAX_SPOTS", "TemperatureField", "WarmSpot"]

#: Spots one field may hold: each reading sums over all of them.
MAX_SPOTS = 64


@dataclass(frozen=True, slots=True)
class WarmSpot:
    """``delta`` degrees more at (x, y), fading over ``radius`` metres (a negative delta is a cold spot)."""

    x: float
    y: float
    delta: float
    radius: float


@dataclass(frozen=True, slots=True)
class TemperatureField:
    """The temperature at any point of the plane, degrees Celsius."""

    base: float = 20.0
    spots: tuple[WarmSpot, ...] = ()

    def at(self, x: float, y: float) -> float:
        """The temperature at (x, y)."""
        total = self.base
        for s in self.spots:
            d2 = (x - s.x) ** 2 + (y - s.y) ** 2
            total += s.delta * math.exp(-d2 / (2.0 * s.radius * s.radius))
        return total

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None) -> TemperatureField:
        """``{ base = 20, spots = [[x, y, delta, radius], ...] }``; a key left out keeps the default's."""
        if options is None:
            return DEFAULT_FIELD
        if not isinstance(options, Mapping):
            raise InvalidArgument(
                "a temperature field is a table { base = 20, spots = [[x, y, delta, radius]] }, "
                f"got {options!r}"
            )
        unknown = set(options) - {"base", "spots"}
        if unknown:
            raise InvalidArgument(f"a temperature field has base and spots, not {', '.join(sorted(unknown))}")
        base = options.get("base", DEFAULT_FIELD.base)
        if isinstance(base, bool) or not isinstance(base, int | float) or not -273.15 <= base <= 1e4:
            raise InvalidArgument(f"the field's base is a temperature in degrees Celsius, got {base!r}")
        spots = DEFAULT_FIELD.spots if "spots" not in options else _spots(options["spots"])
        return cls(float(base), spots)


def _spots(value: Any) -> tuple[WarmSpot, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence) or len(value) > MAX_SPOTS:
        raise InvalidArgument(f"spots is a list of at most {MAX_SPOTS} [x, y, delta, radius], got {value!r}")
    out = []
    for i, spot in enumerate(value):
        numbers = spot if isinstance(spot, Sequence) and not isinstance(spot, str) else ()
        good = len(numbers) == 4 and all(
            isinstance(n, int | float) and not isinstance(n, bool) and math.isfinite(n) for n in numbers
        )
        if not good or numbers[3] <= 0:
            raise InvalidArgument(f"spots[{i}] is [x, y, delta, radius] with a positive radius, got {spot!r}")
        out.append(WarmSpot(*(float(n) for n in numbers)))
    return tuple(out)


#: The demo world: 20 °C, a warm spot of +8 °C near (3, 2) and a milder one of +5 °C near (−2, −3).
DEFAULT_FIELD = TemperatureField(20.0, (WarmSpot(3.0, 2.0, 8.0, 1.5), WarmSpot(-2.0, -3.0, 5.0, 1.0)))

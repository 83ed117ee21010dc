"""Formations of a group of robots: where each member goes around a target.

A formation is a set of ``n`` offsets in the x-y plane whose centroid is the
origin, so the members' centroid lands exactly on the target. Offsets are
assigned to members in natural name order (``scout2`` before ``scout10``),
which makes the same group always take the same places.

* ``line``: along the x axis, neighbours ``spacing`` apart.
* ``grid``: rows along x, ``ceil(sqrt(n))`` columns, ``spacing`` apart; a short
  last row is kept and the whole grid is centred on the filled places.
* ``circle``: evenly on a circle whose neighbours are ``spacing`` apart
  (radius ``spacing / (2 sin(pi/n))``); member 0 on the +x axis.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence

import numpy as np
import numpy.typing as npt

from services.kernel.errors import InvalidArgument

__all__ = [
    "FORMATIONS",
    "MAX_MEMBERS",
    "centroid",
    "formation_offsets",
    "formation_targets",
    "natural_key",
]

FORMATIONS = ("line", "grid", "circle")
#: A formation is computed in one numpy call; the limit only keeps a hostile
#: request from allocating gigabytes.
MAX_MEMBERS = 1_000_000

Array = npt.NDArray[np.float64]

_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key that orders ``scout2`` before ``scout10``."""
    return tuple((0, int(part)) if part.isdigit() else (1, part) for part in _DIGITS.split(name) if part)


def _check(formation: str, n: int, spacing: float) -> None:
    if formation not in FORMATIONS:
        raise InvalidArgument(f"unknown formation {formation!r}: use one of {', '.join(FORMATIONS)}")
    if not 0 <= n <= MAX_MEMBERS:
        raise InvalidArgument(f"a formation holds 0 to {MAX_MEMBERS} members, not {n}")
    if not (math.isfinite(spacing) and spacing > 0):
        raise InvalidArgument(f"spacing must be a positive number of metres, not {spacing}")


def formation_offsets(formation: str, n: int, spacing: float = 1.0) -> Array:
    """An ``(n, 2)`` array of x-y offsets whose mean is the origin.

    Raises InvalidArgument for an unknown formation or a spacing that is not
    a positive finite number.
    """
    _check(formation, n, spacing)
    if n == 0:
        return np.zeros((0, 2))
    i = np.arange(n, dtype=np.float64)
    if formation == "line":
        xy = np.stack([i * spacing, np.zeros(n)], axis=1)
    elif formation == "grid":
        cols = math.ceil(math.sqrt(n))
        xy = np.stack([(i % cols) * spacing, (i // cols) * spacing], axis=1)
    else:
        if n == 1:
            return np.zeros((1, 2))
        radius = spacing / (2.0 * math.sin(math.pi / n))
        angle = 2.0 * math.pi * i / n
        xy = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
    offsets: Array = xy - xy.mean(axis=0)
    return offsets


def formation_targets(
    names: Iterable[str], target: Sequence[float] | Array, formation: str = "line", spacing: float = 1.0
) -> dict[str, Array]:
    """Where each named member goes: ``target`` plus its formation offset in x and y.

    ``target`` is a location vector of at least two elements (``(x y)``,
    ``(x y z)`` or a 6-vector); every returned vector has the same length,
    and elements past y are copied from the target. Members take places in
    natural name order.
    """
    ordered = sorted(set(names), key=natural_key)
    base = np.asarray(target, dtype=np.float64)
    if base.ndim != 1 or base.size < 2:
        raise InvalidArgument(
            f"a formation target needs a location of at least (x y), got {base.size} numbers"
        )
    offsets = formation_offsets(formation, len(ordered), spacing)
    places = np.tile(base, (len(ordered), 1))
    places[:, :2] += offsets
    return {name: places[k] for k, name in enumerate(ordered)}


def centroid(locations: Sequence[Sequence[float] | Array]) -> Array:
    """The centroid of member locations.

    Positions (elements 0–2) are averaged; orientation elements of a
    6-vector (roll, pitch, yaw, 3–5) take the circular mean so that headings
    of 179° and -179° average to 180°, not 0°. Shorter vectors are padded
    with zeros to the longest. Raises InvalidArgument when there are none.
    """
    if len(locations) == 0:
        raise InvalidArgument("no member locations to average")
    widths = {len(v) for v in locations}
    width = max(widths)
    if len(widths) == 1:
        stacked = np.asarray(locations, dtype=np.float64).reshape(len(locations), width)
    else:
        stacked = np.zeros((len(locations), width))
        for k, v in enumerate(locations):
            stacked[k, : len(v)] = v
    result: Array = stacked.mean(axis=0)
    if width > 3:
        angles = stacked[:, 3:]
        result[3:] = np.arctan2(np.sin(angles).mean(axis=0), np.cos(angles).mean(axis=0))
    return result

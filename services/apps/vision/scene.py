"""What a camera can see: the static objects of its configuration and the robots it follows.

A :class:`Thing` is one of them, with its place in the world, its class, colour
and size; :func:`look` turns the things and a camera's pose into
:class:`Sighting` values (those in view, nearest first).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.apps.vision.geometry import confidence, in_view, to_camera_frame
from services.kernel.errors import InvalidArgument
from services.kernel.values import Marker, Vector, format_number

__all__ = [
    "COLOURS",
    "MAX_OBJECTS",
    "Sighting",
    "Thing",
    "colour_of",
    "look",
    "parse_objects",
    "robot_colour",
]

#: Static objects one camera's configuration may hold: a room's furniture, not a point cloud.
MAX_OBJECTS = 1000
#: Colour names a configuration may use, as r g b from 0 to 1.
COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.9, 0.1, 0.1),
    "green": (0.1, 0.7, 0.2),
    "blue": (0.15, 0.3, 0.9),
    "yellow": (0.95, 0.85, 0.1),
    "orange": (1.0, 0.55, 0.0),
    "purple": (0.55, 0.2, 0.7),
    "cyan": (0.0, 0.8, 0.85),
    "magenta": (0.9, 0.2, 0.7),
    "white": (0.95, 0.95, 0.95),
    "grey": (0.5, 0.5, 0.5),
    "black": (0.08, 0.08, 0.08),
}
#: Robots get one of these by their name (the same robot, the same colour, in every camera).
_ROBOT_PALETTE = ("orange", "cyan", "magenta", "yellow", "purple", "white")
#: Size of a robot as a camera draws it, m: the footprint's width and its height.
ROBOT_SIZE = 0.4
#: Bounds of an object's size, m.
MIN_SIZE, MAX_SIZE = 0.01, 100.0
_OBJECT_KEYS = ("id", "class", "location", "colour", "size")


@dataclass(frozen=True, slots=True)
class Thing:
    """Something a camera may see: ``location`` is x y z in the world (z: where it stands)."""

    id: str
    cls: str
    location: Vector
    colour: tuple[float, float, float]
    size: float


@dataclass(frozen=True, slots=True)
class Sighting:
    """A thing in view: where it is in the world and in the camera frame, how far, how sure."""

    thing: Thing
    world: Vector
    camera: Vector
    distance: float
    bearing: float
    confidence: float

    def marker(self, frame: str) -> Marker:
        """The ``<marker>`` of this sighting, its location in ``frame`` (``world`` or ``camera``)."""
        where = self.world if frame == "world" else self.camera
        return Marker.at(
            np.round(where, 3),
            id=self.thing.id,
            **{"class": self.thing.cls},
            color=np.asarray(self.thing.colour),
            confidence=round(self.confidence, 2),
        )


def colour_of(value: Any, what: str) -> tuple[float, float, float]:
    """A colour from a name (``red``) or three numbers from 0 to 1."""
    if isinstance(value, str):
        found = COLOURS.get(value.lower())
        if found is None:
            raise InvalidArgument(
                f"{what}: unknown colour {value!r}; use one of {', '.join(COLOURS)}, or [r, g, b]"
            )
        return found
    if isinstance(value, Sequence) and len(value) == 3:
        numbers = [v for v in value if isinstance(v, int | float) and not isinstance(v, bool)]
        if len(numbers) == 3 and all(0.0 <= v <= 1.0 for v in numbers):
            return (float(numbers[0]), float(numbers[1]), float(numbers[2]))
    raise InvalidArgument(f"{what}: a colour is a name or [r, g, b] with each from 0 to 1, got {value!r}")


def robot_colour(name: str) -> tuple[float, float, float]:
    """The colour a robot named ``name`` is drawn and reported in."""
    return COLOURS[_ROBOT_PALETTE[zlib.crc32(name.encode()) % len(_ROBOT_PALETTE)]]


def _location(value: Any, what: str) -> Vector:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) not in (2, 3):
        raise InvalidArgument(f"{what}: location must be [x, y] or [x, y, z] in metres, got {value!r}")
    numbers = np.zeros(3)
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise InvalidArgument(f"{what}: location must be finite numbers, got {value!r}")
        numbers[i] = v
    return numbers


def parse_objects(objects: Iterable[Mapping[str, Any]]) -> list[Thing]:
    """The static objects of a configuration: ``[{id, class, location = [x, y], colour, size}]``.

    ``class`` defaults to ``object``, ``colour`` to grey, ``size`` to 0.5 m.
    """
    if isinstance(objects, str | bytes) or not isinstance(objects, Iterable):
        raise InvalidArgument(
            "objects must be a list of tables like {id, class, location = [x, y], colour, size}"
        )
    things: list[Thing] = []
    seen: set[str] = set()
    for i, obj in enumerate(objects):
        what = f"objects[{i}]"
        if len(things) >= MAX_OBJECTS:
            raise InvalidArgument(f"objects: at most {MAX_OBJECTS} static objects per camera")
        if not isinstance(obj, Mapping):
            raise InvalidArgument(
                f"{what} must be a table like {{id, class, location = [x, y], colour, size}}"
            )
        unknown = sorted(str(k) for k in obj if k not in _OBJECT_KEYS)
        if unknown:
            raise InvalidArgument(
                f"{what}: unknown key {unknown[0]!r}; an object has {', '.join(_OBJECT_KEYS)}"
            )
        ident = obj.get("id")
        if not isinstance(ident, str) or not ident or len(ident) > 64:
            raise InvalidArgument(f"{what}: id must be a name of 1 to 64 characters, got {ident!r}")
        if ident in seen:
            raise InvalidArgument(f"{what}: the id {ident!r} is used twice")
        seen.add(ident)
        cls = obj.get("class", "object")
        if not isinstance(cls, str) or not cls or len(cls) > 64:
            raise InvalidArgument(f"{what}: class must be a name of 1 to 64 characters, got {cls!r}")
        if "location" not in obj:
            raise InvalidArgument(f"{what}: an object needs a location [x, y]")
        size = obj.get("size", 0.5)
        if isinstance(size, bool) or not isinstance(size, int | float) or not MIN_SIZE <= size <= MAX_SIZE:
            bounds = f"from {format_number(MIN_SIZE)} to {format_number(MAX_SIZE)} m"
            raise InvalidArgument(f"{what}: size must be {bounds}, got {size!r}")
        things.append(
            Thing(
                id=ident,
                cls=cls,
                location=_location(obj["location"], what),
                colour=colour_of(obj.get("colour", "grey"), what),
                size=float(size),
            )
        )
    return things


def look(pose: Vector, range_m: float, fov_rad: float, things: Sequence[Thing]) -> list[Sighting]:
    """The things in view of a camera at ``pose``, nearest first (ties by id)."""
    if not things:
        return []
    world = np.array([t.location for t in things], dtype=np.float64)
    local = to_camera_frame(pose, world)
    seen, distance, bearing = in_view(local, range_m, fov_rad)
    sure = confidence(distance, bearing, range_m, fov_rad)
    found = [
        Sighting(things[i], world[i], local[i], float(distance[i]), float(bearing[i]), float(sure[i]))
        for i in np.flatnonzero(seen).tolist()
    ]
    found.sort(key=lambda s: (s.distance, s.thing.id))
    return found

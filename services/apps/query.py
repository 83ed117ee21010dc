"""Registry queries: the parameters of ``find`` and a numpy index that answers them.

A query is the parameter map of a ``find`` request (or of a group's
``query``)::

    type    = mobile_robot           one type, or a list "(mobile_robot sensor)"
    near    = (5 5 0)                a location: (x y) for planar distance, (x y z) for 3-D
    radius  = 3                      metres around ``near``; without it, results are sorted by distance
    state   = up                     up or down
    limit   = 10                     at most this many names
    where   = speed=0.5&mode=auto    the service's property ``speed`` equals ``0.5`` and ``mode``
                                     equals ``auto`` (query-string syntax, %-escapes allowed;
                                     numbers and vectors compare by value: 0.5 == 0.50)

Every parameter is optional; an unknown one is an INVALID_ARGUMENT that
lists the known ones. :class:`ServiceIndex` keeps type, state and location
of every service in numpy arrays, so the cheap part of a query is a few
vectorised comparisons even for tens of thousands of services; property
equality needs the services' answers and is left to the caller
(:func:`values_equal` compares them).
"""

from __future__ import annotations

import math
import urllib.parse
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from services.apps.formations import natural_key
from services.kernel.errors import InvalidArgument
from services.kernel.paths import validate_path
from services.kernel.values import Value, ValueFormatError, parse_int, parse_list, parse_number, parse_vector

__all__ = ["QUERY_PARAMETERS", "Query", "ServiceIndex", "parse_where", "values_equal"]

#: Parameter name → (type, default) as ``find.parameters`` lists them.
QUERY_PARAMETERS: dict[str, tuple[str, str]] = {
    "type": ("names", ""),
    "near": ("vector", ""),
    "radius": ("float", ""),
    "state": ("str", ""),
    "limit": ("int", ""),
    "where": ("str", ""),
}
_STATES = ("up", "down")

Vector = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Query:
    """A parsed ``find`` request; build it with :meth:`parse`."""

    types: frozenset[str] | None = None
    near: Vector | None = None
    radius: float | None = None
    state: str | None = None
    limit: int | None = None
    props: dict[str, str] = field(default_factory=dict)

    @classmethod
    def parse(cls, params: Mapping[str, str]) -> Query:
        """Parse request parameters; raises InvalidArgument naming the bad one."""
        types: frozenset[str] | None = None
        near: Vector | None = None
        radius: float | None = None
        state: str | None = None
        limit: int | None = None
        props: dict[str, str] = {}
        for name, text in params.items():
            try:
                if name == "type":
                    types = _parse_types(text)
                elif name == "near":
                    near = parse_vector(text)
                    if not 2 <= near.size <= 6:
                        raise InvalidArgument(
                            f"near: expected a location of 2 to 6 numbers ((x y), (x y z) or a pose;"
                            f" only x y z count), got {near.size} numbers"
                        )
                    near = near[:3]
                elif name == "radius":
                    radius = parse_number(text)
                    if radius < 0:
                        raise InvalidArgument(f"a radius cannot be negative ({text.strip()})")
                elif name == "state":
                    state = text.strip()
                    if state not in _STATES:
                        raise InvalidArgument(f"expected up or down, got {text[:40]!r}")
                elif name == "limit":
                    limit = parse_int(text)
                    if limit < 1:
                        raise InvalidArgument(f"expected a positive count, got {limit}")
                elif name == "where":
                    props = parse_where(text)
                else:
                    known = ", ".join(QUERY_PARAMETERS)
                    raise InvalidArgument(
                        f"unknown query parameter {name[:64]!r}: the known ones are {known}"
                    )
            except InvalidArgument as e:
                if e.message.startswith("unknown query parameter"):
                    raise
                raise InvalidArgument(f"bad query parameter {name}: {e.message}") from None
        if radius is not None and near is None:
            raise InvalidArgument("query parameter radius needs near, the location to measure from")
        return cls(types, near, radius, state, limit, props)

    def is_empty(self) -> bool:
        """True when the query selects every service."""
        return (
            self.types is None
            and self.near is None
            and self.radius is None
            and self.state is None
            and self.limit is None
            and not self.props
        )


def parse_where(text: str) -> dict[str, str]:
    """``speed=0.5&mode=auto`` → ``{"speed": "0.5", "mode": "auto"}``; paths are checked."""
    if not text.strip():
        return {}
    try:
        pairs = urllib.parse.parse_qsl(text.strip(), keep_blank_values=True, strict_parsing=True)
    except ValueError:
        raise InvalidArgument(
            f"expected property=value pairs joined by & like speed=0.5&mode=auto, got {text[:60]!r}"
        ) from None
    props: dict[str, str] = {}
    for path, value in pairs:
        props[validate_path(path)] = value
    return props


def _parse_types(text: str) -> frozenset[str]:
    stripped = text.strip()
    items = parse_list(stripped) if stripped.startswith("(") else [stripped]
    if not items or not all(isinstance(i, str) and i for i in items):
        raise InvalidArgument(
            f"expected a type or a list of types like (mobile_robot sensor), got {text[:40]!r}"
        )
    return frozenset(str(i) for i in items)


def values_equal(expected: str, actual: Value) -> bool:
    """Whether a property's ``actual`` text equals the ``expected`` one: by value for numbers and vectors.

    A binary value never equals a text.
    """
    if isinstance(actual, bytes):
        return False
    a, b = expected.strip(), actual.strip()
    if a == b:
        return True
    try:
        return parse_number(a) == parse_number(b)
    except ValueFormatError:
        pass
    if a.startswith("(") and b.startswith("("):
        try:
            va, vb = parse_vector(a), parse_vector(b)
        except ValueFormatError:
            return False
        return va.shape == vb.shape and bool(np.allclose(va, vb, rtol=1e-9, atol=1e-12))
    return False


class ServiceIndex:
    """Type, state and location of every service, in arrays a query filters at once.

    Slots of removed services are reused; the natural name order of all
    slots is recomputed only after names change, not on every query.
    """

    def __init__(self, capacity: int = 64) -> None:
        self._names: list[str | None] = [None] * capacity
        self._slots: dict[str, int] = {}
        self._free: list[int] = list(range(capacity - 1, -1, -1))
        self._type = np.full(capacity, -1, dtype=np.int32)
        self._type_codes: dict[str, int] = {}
        self._up = np.zeros(capacity, dtype=bool)
        self._loc = np.full((capacity, 3), np.nan)
        self._order: npt.NDArray[np.intp] | None = None

    def __len__(self) -> int:
        return len(self._slots)

    def __contains__(self, name: object) -> bool:
        return name in self._slots

    def put(self, name: str, type: str, up: bool = True, location: Iterable[float] | None = None) -> None:
        """Add ``name`` or update all it holds."""
        slot = self._slots.get(name)
        if slot is None:
            if not self._free:
                self._grow()
            slot = self._free.pop()
            self._slots[name] = slot
            self._names[slot] = name
            self._order = None
        self._type[slot] = self._code(type)
        self._up[slot] = up
        self._write_location(slot, location)

    def remove(self, name: str) -> None:
        """Forget ``name``; nothing happens when it is not there."""
        slot = self._slots.pop(name, None)
        if slot is None:
            return
        self._names[slot] = None
        self._type[slot] = -1
        self._up[slot] = False
        self._loc[slot] = np.nan
        self._free.append(slot)
        self._order = None

    def set_type(self, name: str, type: str) -> None:
        """Change the type of ``name`` (ignored when unknown)."""
        slot = self._slots.get(name)
        if slot is not None:
            self._type[slot] = self._code(type)

    def set_up(self, name: str, up: bool) -> None:
        """Change the state of ``name`` (ignored when unknown)."""
        slot = self._slots.get(name)
        if slot is not None:
            self._up[slot] = up

    def set_location(self, name: str, location: Iterable[float] | None) -> None:
        """Change the location of ``name``; None forgets it (ignored when the name is unknown)."""
        slot = self._slots.get(name)
        if slot is not None:
            self._write_location(slot, location)

    def select(self, query: Query) -> list[str]:
        """Names matching type, state and location of ``query``, best first; ``query.props`` is not applied.

        The order is by distance when ``near`` is given, else natural name
        order. ``limit`` is not applied either (property filters come first).
        """
        mask = self._type >= 0
        if query.types is not None:
            codes = [self._type_codes[t] for t in query.types if t in self._type_codes]
            mask &= np.isin(self._type, codes)
        if query.state is not None:
            mask &= self._up if query.state == "up" else ~self._up
        if query.near is not None:
            k = query.near.size
            with np.errstate(invalid="ignore"):
                distance = np.linalg.norm(self._loc[:, :k] - query.near, axis=1)
            reach = math.inf if query.radius is None else query.radius
            mask &= distance <= reach  # NaN (no known location) never matches
            hits = np.flatnonzero(mask)
            hits = hits[np.lexsort((self._rank()[hits], distance[hits]))]
        else:
            order = self._natural_order()
            hits = order[mask[order]]
        names = self._names
        return [names[i] for i in hits]  # type: ignore[misc]

    def slots_of(self, names: Iterable[str]) -> npt.NDArray[np.intp]:
        """The slots of ``names`` (all known), for :meth:`planar_at` and :meth:`up_at`.

        A slot stays the same while its name is known; callers keep them until names change.
        """
        slots = self._slots
        return np.fromiter((slots[n] for n in names), dtype=np.intp)

    def planar_at(self, slots: npt.NDArray[np.intp]) -> npt.NDArray[np.float64]:
        """x y of the services at ``slots`` (rows of NaN where unknown)."""
        return self._loc[slots, :2]

    def up_at(self, slots: npt.NDArray[np.intp]) -> npt.NDArray[np.bool_]:
        """Whether the services at ``slots`` are up."""
        return self._up[slots]

    # -- internals -------------------------------------------------------

    def _code(self, type: str) -> int:
        code = self._type_codes.get(type)
        if code is None:
            code = self._type_codes[type] = len(self._type_codes)
        return code

    def _write_location(self, slot: int, location: Iterable[float] | None) -> None:
        row = self._loc[slot]
        row[:] = np.nan
        if location is not None:
            values = np.asarray(
                list(location) if not isinstance(location, np.ndarray) else location, dtype=float
            )
            n = min(3, values.size)
            row[:n] = values[:n]
            row[n:] = 0.0 if n >= 2 else np.nan

    def _grow(self) -> None:
        old = len(self._names)
        new = old * 2
        self._names.extend([None] * (new - old))
        self._free.extend(range(new - 1, old - 1, -1))
        self._type = np.concatenate([self._type, np.full(new - old, -1, dtype=np.int32)])
        self._up = np.concatenate([self._up, np.zeros(new - old, dtype=bool)])
        self._loc = np.concatenate([self._loc, np.full((new - old, 3), np.nan)])
        self._order = None

    def _natural_order(self) -> npt.NDArray[np.intp]:
        if self._order is None or self._order.size != len(self._names):
            used = sorted(self._slots.items(), key=lambda item: natural_key(item[0]))
            empty = [i for i, n in enumerate(self._names) if n is None]
            self._order = np.array([slot for _, slot in used] + empty, dtype=np.intp)
        return self._order

    def _rank(self) -> npt.NDArray[np.intp]:
        order = self._natural_order()
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        return rank

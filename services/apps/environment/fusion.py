"""Marker fusion, sans-IO: observations in, fused markers out; no clock, no event loop.

Each fused marker is a position estimate with an **isotropic variance** ``P`` (m², the same
on every axis: the covariance is ``P·I``). An observation brings a position ``z`` and its own
variance ``R``. Between observations the estimate grows uncertain as a random walk does:
``P' = P + q·dt`` (``q``, the process noise, in m²/s). Association is gated nearest
neighbour among the markers of the observation's class: the squared Mahalanobis distance
``d² / (P' + R)`` must be at most ``gate²`` and the plain distance at most ``max_distance``;
the nearest such marker (smallest Mahalanobis distance) takes the observation, else it starts
a new marker. The update is the Kalman update of a static state with an isotropic covariance:

    K = P' / (P' + R)        x ← x + K (z − x)        P ← (1 − K) P' = P'·R / (P' + R)

so ``n`` observations of variance ``R`` of a still object leave ``P = R / n``.

A source that names its objects (a camera's marker ``id``, a robot reporting its own pose)
is followed by name: an observation whose (source, id) fed a marker before goes to that
marker when the class agrees, updated within the gate, moved to the observation beyond it.

The markers are indexed by a spatial hash of square cells of ``max_distance`` per side and
class, so an association looks at the 3×3 cells around the observation, never at every
marker. Markers not seen for ``ttl`` seconds expire (:meth:`MarkerFusion.expire`); past
``max_markers`` a new marker evicts the one seen least recently.
"""

from __future__ import annotations

import heapq
import math
import re
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from services.kernel.values import Vector

__all__ = ["FusedMarker", "MarkerFusion", "Observation", "Update"]

#: A marker id is a property path segment (``markers.<id>``).
_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")
#: Names a marker id may not take: they are the class wrapper's own names under ``markers``.
_RESERVED_IDS = frozenset({"properties", "parameters", "gui", "doc", "media_type"})
#: (source, id) pairs remembered per marker: a few cameras and the robot itself.
MAX_ALIASES = 8
#: Smallest variance kept (m²): a perfect observation would freeze a marker for ever.
MIN_VARIANCE = 1e-9


@dataclass(frozen=True, slots=True)
class Observation:
    """One sighting of one object: class, position (x y [z]), variance R (m², per axis), source."""

    cls: str
    position: tuple[float, float, float]
    variance: float
    source: str
    #: The source's own name for the object ("" when it gives none).
    id: str = ""
    #: Further fields of the sighting (colour, confidence): the latest sighting's are kept.
    fields: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def at(
        cls,
        kind: str,
        position: tuple[float, ...] | list[float] | Vector,
        variance: float,
        source: str,
        *,
        id: str = "",
        fields: Mapping[str, str] | None = None,
    ) -> Observation:
        """An observation from 2 or 3 numbers (z is 0 when not given); ValueError for bad ones."""
        numbers = [float(v) for v in position]
        if len(numbers) not in (2, 3) or not all(math.isfinite(v) for v in numbers):
            raise ValueError(f"a position is 2 or 3 finite numbers (x y [z]), got {numbers}")
        if not (math.isfinite(variance) and variance > 0):
            raise ValueError(f"a variance is a positive number of m², got {variance}")
        if not kind:
            raise ValueError("an observation needs a class")
        x, y = numbers[0], numbers[1]
        z = numbers[2] if len(numbers) == 3 else 0.0
        return cls(kind, (x, y, z), float(variance), source, id, dict(fields or {}))


@dataclass(slots=True)
class FusedMarker:
    """The fused estimate of one object."""

    id: str
    cls: str
    position: Vector
    variance: float
    source: str
    first_seen: float
    last_seen: float
    count: int = 1
    fields: dict[str, str] = field(default_factory=dict)
    #: source → that source's id of this object (at most MAX_ALIASES).
    aliases: dict[str, str] = field(default_factory=dict)
    #: The spatial hash cell it is filed under.
    cell: tuple[str, int, int] = ("", 0, 0)


@dataclass(frozen=True, slots=True)
class Update:
    """What one observation did: the marker it went to, whether it made it, who was evicted for it."""

    marker: FusedMarker
    created: bool
    evicted: tuple[FusedMarker, ...] = ()


class MarkerFusion:
    """The fused markers of the environment: associate, update, expire, find."""

    def __init__(
        self,
        *,
        gate: float = 4.0,
        max_distance: float = 1.0,
        ttl: float = 30.0,
        max_markers: int = 10_000,
        process_noise: float = 0.01,
    ) -> None:
        if not (math.isfinite(gate) and gate > 0):
            raise ValueError(f"gate must be a positive number of standard deviations, got {gate}")
        if not (math.isfinite(max_distance) and max_distance > 0):
            raise ValueError(f"max_distance must be a positive number of metres, got {max_distance}")
        if not (math.isfinite(ttl) and ttl > 0):
            raise ValueError(f"ttl must be a positive number of seconds, got {ttl}")
        if not 1 <= max_markers <= 1_000_000:
            raise ValueError(f"max_markers must be from 1 to 1000000, got {max_markers}")
        if not (math.isfinite(process_noise) and process_noise >= 0):
            raise ValueError(f"process_noise must be a number of m²/s, at least 0, got {process_noise}")
        self.gate = float(gate)
        self.max_distance = float(max_distance)
        self.ttl = float(ttl)
        self.max_markers = int(max_markers)
        self.process_noise = float(process_noise)
        # id → marker, least recently seen first (expiry and eviction pop from the front).
        self._markers: OrderedDict[str, FusedMarker] = OrderedDict()
        self._cells: dict[tuple[str, int, int], dict[str, FusedMarker]] = {}
        self._aliases: dict[tuple[str, str], str] = {}
        self._serial = 0

    # -- reading ---------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._markers)

    def __iter__(self) -> Iterator[FusedMarker]:
        return iter(list(self._markers.values()))

    def __contains__(self, marker_id: object) -> bool:
        return marker_id in self._markers

    def get(self, marker_id: str) -> FusedMarker | None:
        return self._markers.get(marker_id)

    def ids(self) -> list[str]:
        """Every marker's id, least recently seen first."""
        return list(self._markers)

    def find(
        self,
        cls: str = "",
        near: tuple[float, float] | None = None,
        area: tuple[float, float, float, float] | None = None,
        count: int = 10,
        fields: Mapping[str, str] | None = None,
    ) -> list[FusedMarker]:
        """Up to ``count`` markers of class ``cls`` ("" for any) inside ``area`` (x0 y0 x1 y1) whose
        ``fields`` (``source`` among them) have the given values, nearest to ``near`` first (without
        ``near``: most recently seen first)."""
        if count < 1:
            return []
        chosen: list[FusedMarker] = []
        for m in self._markers.values():
            if cls and m.cls != cls:
                continue
            if fields and any(
                (m.source if name == "source" else m.fields.get(name)) != value
                for name, value in fields.items()
            ):
                continue
            if area is not None:
                x0, y0, x1, y1 = area
                x, y = float(m.position[0]), float(m.position[1])
                if not (min(x0, x1) <= x <= max(x0, x1) and min(y0, y1) <= y <= max(y0, y1)):
                    continue
            chosen.append(m)
        if near is None:
            return list(reversed(chosen))[:count]
        nx, ny = near
        return heapq.nsmallest(
            count, chosen, key=lambda m: (float(m.position[0]) - nx) ** 2 + (float(m.position[1]) - ny) ** 2
        )

    # -- writing ---------------------------------------------------------------------

    def observe(self, obs: Observation, now: float) -> Update:
        """Fuse one observation made at time ``now`` (seconds, any clock that only moves on)."""
        z = np.asarray(obs.position, dtype=np.float64)
        named = self._named(obs)
        if named is not None:
            predicted = self._predicted(named, now)
            if self._within_gate(named, z, predicted, obs.variance) is not None:
                self._update(named, obs, z, predicted, now)
            else:  # the source says it is the same object: it moved farther than the model allowed
                self._move(named, z, obs.variance, obs, now)
            return Update(named, created=False)
        best: FusedMarker | None = None
        best_m2 = math.inf
        best_predicted = 0.0
        cls, cx, cy = self._cell_of(obs.cls, z)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                bucket = self._cells.get((cls, cx + dx, cy + dy))
                if not bucket:
                    continue
                for candidate in bucket.values():
                    predicted = self._predicted(candidate, now)
                    m2 = self._within_gate(candidate, z, predicted, obs.variance)
                    if m2 is not None and m2 < best_m2:
                        best, best_m2, best_predicted = candidate, m2, predicted
        if best is not None:
            self._update(best, obs, z, best_predicted, now)
            return Update(best, created=False)
        evicted: list[FusedMarker] = []
        while len(self._markers) >= self.max_markers:
            evicted.append(self._remove(next(iter(self._markers))))
        marker = FusedMarker(
            id=self._new_id(obs),
            cls=obs.cls,
            position=z,
            variance=max(obs.variance, MIN_VARIANCE),
            source=obs.source,
            first_seen=now,
            last_seen=now,
            fields=dict(obs.fields),
        )
        self._markers[marker.id] = marker
        self._file(marker)
        self._alias(marker, obs)
        return Update(marker, created=True, evicted=tuple(evicted))

    def expire(self, now: float) -> list[FusedMarker]:
        """Remove and return every marker not seen for more than ``ttl`` seconds before ``now``."""
        gone: list[FusedMarker] = []
        oldest = now - self.ttl
        while self._markers:
            first = next(iter(self._markers.values()))
            if first.last_seen >= oldest:
                break
            gone.append(self._remove(first.id))
        return gone

    def touch(self, marker_id: str, now: float) -> bool:
        """Count ``marker_id`` as seen at ``now`` without a new estimate (a source that would tell
        of any change has told of none); False when there is no such marker."""
        marker = self._markers.get(marker_id)
        if marker is None:
            return False
        marker.last_seen = max(marker.last_seen, now)
        self._markers.move_to_end(marker_id)
        return True

    def remove(self, marker_id: str) -> FusedMarker | None:
        """Forget one marker; None when there is none of that id."""
        return self._remove(marker_id) if marker_id in self._markers else None

    def clear(self) -> list[FusedMarker]:
        """Forget every marker; returns them."""
        gone = list(self._markers.values())
        self._markers.clear()
        self._cells.clear()
        self._aliases.clear()
        return gone

    # -- inside ----------------------------------------------------------------------

    def _predicted(self, marker: FusedMarker, now: float) -> float:
        return marker.variance + self.process_noise * max(0.0, now - marker.last_seen)

    def _within_gate(self, marker: FusedMarker, z: Vector, predicted: float, variance: float) -> float | None:
        """The squared Mahalanobis distance when ``z`` passes the gate of ``marker``, else None."""
        d2 = float(np.dot(z - marker.position, z - marker.position))
        if d2 > self.max_distance * self.max_distance:
            return None
        m2 = d2 / (predicted + variance)
        return m2 if m2 <= self.gate * self.gate else None

    def _update(self, marker: FusedMarker, obs: Observation, z: Vector, predicted: float, now: float) -> None:
        gain = predicted / (predicted + obs.variance)
        marker.position = marker.position + gain * (z - marker.position)
        marker.variance = max(predicted * obs.variance / (predicted + obs.variance), MIN_VARIANCE)
        self._seen(marker, obs, now)

    def _move(self, marker: FusedMarker, z: Vector, variance: float, obs: Observation, now: float) -> None:
        marker.position = z
        marker.variance = max(variance, MIN_VARIANCE)
        self._seen(marker, obs, now)

    def _seen(self, marker: FusedMarker, obs: Observation, now: float) -> None:
        marker.count += 1
        marker.last_seen = max(marker.last_seen, now)
        marker.source = obs.source
        marker.fields.update(obs.fields)
        self._markers.move_to_end(marker.id)
        cell = self._cell_of(marker.cls, marker.position)
        if cell != marker.cell:
            self._unfile(marker)
            self._file(marker)
        self._alias(marker, obs)

    def _named(self, obs: Observation) -> FusedMarker | None:
        if not obs.id:
            return None
        marker_id = self._aliases.get((obs.source, obs.id))
        marker = self._markers.get(marker_id) if marker_id is not None else None
        return marker if marker is not None and marker.cls == obs.cls else None

    def _alias(self, marker: FusedMarker, obs: Observation) -> None:
        if not obs.id or marker.aliases.get(obs.source) == obs.id:
            return
        old = marker.aliases.pop(obs.source, None)
        if old is not None:
            self._aliases.pop((obs.source, old), None)
        if len(marker.aliases) >= MAX_ALIASES:
            source, name = next(iter(marker.aliases.items()))
            del marker.aliases[source]
            self._aliases.pop((source, name), None)
        previous = self._aliases.get((obs.source, obs.id))
        if previous is not None and previous != marker.id:
            other = self._markers.get(previous)
            if other is not None:
                other.aliases.pop(obs.source, None)
        marker.aliases[obs.source] = obs.id
        self._aliases[(obs.source, obs.id)] = marker.id

    def _cell_of(self, cls: str, position: Vector) -> tuple[str, int, int]:
        size = self.max_distance
        return cls, math.floor(float(position[0]) / size), math.floor(float(position[1]) / size)

    def _file(self, marker: FusedMarker) -> None:
        marker.cell = self._cell_of(marker.cls, marker.position)
        self._cells.setdefault(marker.cell, {})[marker.id] = marker

    def _unfile(self, marker: FusedMarker) -> None:
        bucket = self._cells.get(marker.cell)
        if bucket is not None:
            bucket.pop(marker.id, None)
            if not bucket:
                del self._cells[marker.cell]

    def _remove(self, marker_id: str) -> FusedMarker:
        marker = self._markers.pop(marker_id)
        self._unfile(marker)
        for source, name in marker.aliases.items():
            if self._aliases.get((source, name)) == marker_id:
                del self._aliases[(source, name)]
        return marker

    def _new_id(self, obs: Observation) -> str:
        if obs.id and _ID.fullmatch(obs.id) and obs.id not in self._markers and obs.id not in _RESERVED_IDS:
            return obs.id
        stem = re.sub(r"[^A-Za-z0-9_-]", "_", obs.cls)[:40] or "marker"
        while True:
            self._serial += 1
            candidate = f"{stem}-{self._serial}"
            if candidate not in self._markers:
                return candidate

"""Listen in the engine's own types: what a Listen asks for, and what its stream hands the front.

Every front end turns its own form of a Listen into a :class:`ListenRequest` (the gRPC front from
a ``ListenRequest`` message, the HTTP front from ``sel=`` query keys or an image stream's URL);
the listen hub checks it against the limits (:func:`gateway.engine.listen.requests.check_listen`) and
opens a stream. What the stream has ready, the front's writer takes (``ListenStream.take``):

* a :data:`Batch`: events in order, with the stream's sequence number before the first;
* or a :class:`Mark`: the ``sync`` marker (the current values were sent), or a heartbeat.

A batch holds each event as the stream queued it: a :class:`~services.kernel.conflation.Slot` (what this
stream alone has of it: how many values it replaced, ``gap``, ``removed``) around a
:class:`SharedEvent` (what every stream the change reaches has alike: service, path, value,
time). :func:`events` turns a batch into plain :class:`Event` values, which is all most fronts
need. A front that sends the same change to many streams encodes the shared part once, on the
first stream's turn, and keeps it in :attr:`SharedEvent.encoded` for the others: the gRPC front
does (:mod:`gateway.fronts.grpc_v1.listen_encoding`), so a change reaching N streams is
serialized once, not N times.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar, overload

from services.kernel.conflation import Slot
from services.kernel.paths import WILDCARD
from services.kernel.values import Value

__all__ = [
    "Batch",
    "Event",
    "ListenRequest",
    "Mark",
    "Ready",
    "Selector",
    "SharedEvent",
    "StreamOptions",
    "Taken",
    "events",
]

#: Bytes an event takes in a message besides its service, path and value (the tags and lengths,
#: the time, the sequence number, the count and the flags), rounded up.
EVENT_OVERHEAD_BYTES = 40


@dataclass(frozen=True, slots=True)
class Selector:
    """What a Listen asks for: a service (or ``*``), a path (``*`` segments allowed), parameters."""

    service: str
    path: str
    params: tuple[tuple[str, str], ...] = ()

    def matches_service(self, name: str) -> bool:
        return self.service in (WILDCARD, name)


@dataclass(frozen=True, slots=True)
class StreamOptions:
    """A Listen's options once checked against the limits; intervals in seconds, 0 = off."""

    updates_only: bool = False
    min_interval: float = 0.0
    sample_interval: float = 0.0
    heartbeat_interval: float = 0.0
    max_batch: int = 256


@dataclass(frozen=True, slots=True)
class ListenRequest:
    """A Listen as a front end hands it to the hub, before the limits are checked.

    ``min_interval``: at most one event a property per that many seconds (throttle);
    ``sample_interval``: every property's latest value each that many seconds, changed or not;
    ``heartbeat_interval``: a heartbeat after that many quiet seconds; 0 = off for each.
    ``updates_only``: no current values first, changes only. ``max_batch``: the most events a
    response carries (0: as many as ``limits.max_batch`` allows). A slow reader gets the latest
    value of each property, never a backlog, whatever the options.
    """

    selectors: Sequence[Selector]
    updates_only: bool = False
    min_interval: float = 0.0
    sample_interval: float = 0.0
    heartbeat_interval: float = 0.0
    max_batch: int = 0


class Mark(enum.Enum):
    """What a stream hands its writer that carries no events: the ``sync`` marker, or a heartbeat."""

    SYNC = "sync"
    HEARTBEAT = "heartbeat"


class SharedEvent:
    """What every stream's event for one change of one property has alike.

    Made once per change, by the first stream the change reaches (kept on the topic for the
    others, ``Topic.event``); a stream's own view of it (its sequence number, how many values it
    replaced, ``gap``, ``removed``) stays in its queue's slot.
    """

    __slots__ = ("encoded", "path", "service", "size", "stamp", "value")

    def __init__(self, service: str, path: str, value: Value, stamp: int) -> None:
        self.service = service
        self.path = path
        #: Text, or bytes for a binary property: the very object every stream's slot holds.
        self.value = value
        #: When the gateway heard it, in nanoseconds since the epoch.
        self.stamp = stamp
        n = len(value) if isinstance(value, bytes) or value.isascii() else len(value.encode())
        #: About the bytes the event takes in a message (exact for the value, which is what can be
        #: big): what batches are bounded by.
        self.size = n + len(service) + len(path) + EVENT_OVERHEAD_BYTES
        #: What a front made of it to send it to every stream: the gRPC front's serialized fields
        #: (never read by the engine); None until the first stream sends it.
        self.encoded: Any = None


#: One event ready for a writer: the stream's topic it is about (the hub's own: a front never reads
#: it, so the engine's types need not know the hub), and the stream's slot for it.
Ready = tuple[Any, Slot[SharedEvent]]
#: Events ready, and the stream's sequence number before the first of them.
Batch = tuple[list[Ready], int]
#: What a writer takes at a time.
Taken = Batch | Mark


@dataclass(frozen=True, slots=True)
class Event:
    """One event of a Listen, as a front end sends it."""

    service: str
    path: str
    #: Text, or bytes for a binary property (empty when ``removed``).
    value: Value
    #: The stream's number for it: 1, 2, 3 … in the order the stream sends its events.
    sequence: int
    #: When the gateway heard the value, in nanoseconds since the epoch.
    time_ns: int
    #: Values of the property this one replaced while the reader was behind.
    conflated: int = 0
    #: Values may have been lost before this one (its service could not be reached a while).
    gap: bool = False
    #: The property no longer exists.
    removed: bool = False


_Made = TypeVar("_Made")
#: What makes an event of its fields, in :class:`Event`'s order (``Event`` itself, or a type of the
#: same shape: the follow's :class:`~services.kernel.follow.FollowedEvent`).
MakeEvent = Callable[[str, str, Value, int, int, int, bool, bool], _Made]


@overload
def events(batch: Batch) -> list[Event]: ...
@overload
def events(batch: Batch, make: MakeEvent[_Made]) -> list[_Made]: ...
def events(batch: Batch, make: MakeEvent[Any] = Event) -> list[Any]:
    """The events of ``batch`` as plain values, numbered; each made by ``make`` (an in-process
    follower takes its own type straight from the batch, with no :class:`Event` in between)."""
    ready, sequence = batch
    out = []
    for _, slot in ready:
        sequence += 1
        shared = slot.value
        out.append(
            make(
                shared.service,
                shared.path,
                shared.value,
                sequence,
                shared.stamp,
                slot.conflated,
                slot.gap,
                slot.removed,
            )
        )
    return out

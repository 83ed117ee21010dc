"""What a Listen yields (:class:`Event` values and :class:`Mark` stream markers), what a Get with
its time answers (:class:`Reading`), and what a History call answers (:class:`History`)."""

from __future__ import annotations

import enum
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.values import Value

__all__ = [
    "HEARTBEAT",
    "SYNC",
    "Event",
    "History",
    "Mark",
    "Reading",
    "history_of",
    "listen_items",
    "reading_of",
]


@dataclass(frozen=True, slots=True)
class Event:
    """One value of one property, as delivered by a Listen."""

    service: str
    property: str
    #: Text, or ``bytes`` for a binary property.
    value: Value
    #: Per-stream sequence number, from 1, without holes.
    sequence: int
    #: When the gateway saw the change (timezone-aware, UTC).
    time: datetime
    #: How many earlier values were replaced by this one (slow reader or throttle).
    conflated: int = 0
    #: Values may have been lost before this one; ``value`` is the current value.
    gap: bool = False
    #: The property no longer exists; ``value`` is empty.
    removed: bool = False


@dataclass(frozen=True, slots=True)
class Reading:
    """A value and its source time: when it became true (the service's own time when it gives
    one, else when the gateway heard the change, or when the answer arrived for a value read
    fresh)."""

    #: Text, or ``bytes`` for a binary property.
    value: Value
    #: Timezone-aware, UTC.
    time: datetime


@dataclass(frozen=True, slots=True)
class History:
    """The kept values of the properties a History call matched, oldest first; iterate over it
    for the events.

    ``truncated``: more values lay in the range than the limit allowed; the newest were left out
    (ask again with ``since`` just after the last event's time).
    """

    events: list[Event]
    truncated: bool = False

    def __iter__(self) -> Iterator[Event]:
        return iter(self.events)

    def __len__(self) -> int:
        return len(self.events)


class Mark(enum.Enum):
    """Stream markers a Listen yields when asked with ``marks=True``."""

    #: The current values have all been sent; what follows are changes.
    SYNC = "sync"
    #: Keep-alive: nothing changed for the heartbeat interval.
    HEARTBEAT = "heartbeat"


SYNC = Mark.SYNC
HEARTBEAT = Mark.HEARTBEAT


def _event(ev: pb.Event) -> Event:
    return Event(
        ev.service,
        ev.property,
        ev.data if ev.HasField("data") else ev.value,
        ev.sequence,
        ev.time.ToDatetime(tzinfo=UTC),
        ev.conflated,
        ev.gap,
        ev.removed,
    )


def reading_of(resp: pb.GetResponse) -> Reading:
    """The value of a GetResponse and its source time."""
    return Reading(resp.data if resp.HasField("data") else resp.value, resp.time.ToDatetime(tzinfo=UTC))


def history_of(resp: pb.HistoryResponse) -> History:
    """The events of a HistoryResponse."""
    return History([_event(ev) for ev in resp.events], resp.truncated)


def listen_items(resp: pb.ListenResponse, marks: bool) -> list[Event | Mark]:
    """The events of one ListenResponse, then its markers when ``marks`` asks for them."""
    items: list[Event | Mark] = [_event(ev) for ev in resp.events]
    if marks:
        if resp.sync:
            items.append(SYNC)
        if resp.heartbeat:
            items.append(HEARTBEAT)
    return items

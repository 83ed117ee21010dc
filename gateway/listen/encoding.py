"""Events into ``ListenResponse`` messages: sizes, batches by bytes, and encoding in place."""

from __future__ import annotations

from collections.abc import Iterable

from gateway.listen.topics import Topic
from gateway.sizes import BATCH_BYTES
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.conflation import Slot
from services.values import Value

#: One event ready to go: the topic it is about and what waits for it.
Ready = tuple[Topic, Slot[Value]]


def event_size(topic: Topic, entry: Slot[Value]) -> int:
    """About the bytes ``entry`` takes as an Event (exact for the value, which is what can be big).

    A binary value counts its bytes (it travels in ``data``).
    """
    value = entry.value  # inlined value_size: this runs for every event
    n = len(value) if isinstance(value, bytes) or value.isascii() else len(value.encode())
    return n + len(topic.service) + len(topic.path) + 40


def within(items: Iterable[Ready]) -> tuple[list[Ready], int]:
    """The first of ``items`` that add up to at most BATCH_BYTES (always at least one), and their size."""
    ready: list[Ready] = []
    size = 0
    for item in items:
        n = event_size(*item)
        if ready and size + n > BATCH_BYTES:
            break
        size += n
        ready.append(item)
    return ready, size


def encode_events(ready: list[Ready], sequence: int) -> pb.ListenResponse:
    """One response carrying ``ready``, numbered from ``sequence + 1``."""
    # Events are added in place: built apart, each would be copied into the response.
    response = pb.ListenResponse()
    add = response.events.add
    seq = sequence
    for topic, entry in ready:
        seq += 1
        value = entry.value
        if isinstance(value, str):
            ev = add(
                service=topic.service,
                property=topic.path,
                value=value,
                sequence=seq,
                conflated=entry.conflated,
                gap=entry.gap,
                removed=entry.removed,
            )
        else:
            ev = add(
                service=topic.service,
                property=topic.path,
                data=value,
                sequence=seq,
                conflated=entry.conflated,
                gap=entry.gap,
                removed=entry.removed,
            )
        ev.time.seconds, ev.time.nanos = divmod(entry.stamp, 1_000_000_000)
    return response

"""Events into ``ListenResponse`` messages: sizes, batches by bytes, and encoding in place.

Two encodings of the same response: :func:`encode_events` builds the message (for the HTTP
front end, which turns it into JSON), :func:`encode_wire` its serialized bytes (what the gRPC
Listen handler sends, and a Session inside its replies: :func:`listen_reply_wire`). The wire
form encodes the fields of an event that every stream sends alike once per change
(:func:`shared_wire`) and adds each stream's own sequence number, count and flags; protobuf
readers take the fields of a message in any order.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable

from gateway.listen.topics import Topic
from gateway.sizes import BATCH_BYTES
from gateway.wire_values import put
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


class Mark(enum.Enum):
    """A response that carries no events: the ``sync`` marker, or a heartbeat."""

    SYNC = "sync"
    HEARTBEAT = "heartbeat"

    @property
    def wire(self) -> bytes:
        """The marker's response, serialized."""
        return _MARK_WIRE[self]


_MARK_WIRE = {
    Mark.SYNC: pb.ListenResponse(sync=True).SerializeToString(),
    Mark.HEARTBEAT: pb.ListenResponse(heartbeat=True).SerializeToString(),
}


def marker_response(mark: Mark) -> pb.ListenResponse:
    """The marker's response, a new message (its receiver may change it)."""
    return pb.ListenResponse(sync=True) if mark is Mark.SYNC else pb.ListenResponse(heartbeat=True)


# Wire tags (field number << 3 | wire type) of what a stream adds to an event's shared fields:
# Event.sequence = 4, conflated = 6, gap = 7, removed = 8 (varints); ListenResponse.events = 1
# (length-delimited). The numbers are the contract's; tests/unit/test_listen_encoding.py
# compares this encoding with protobuf's own.
_SEQUENCE = b"\x20"
_CONFLATED = b"\x30"
_GAP = b"\x38\x01"
_REMOVED = b"\x40\x01"
_EVENTS = b"\x0a"
# SessionResponse.replies = 1 (length-delimited); Reply.id = 1 (varint), Reply.listen = 5
# (length-delimited).
_REPLIES = b"\x0a"
_REPLY_ID = b"\x08"
_REPLY_LISTEN = b"\x2a"
_ONE_BYTE = [bytes((n,)) for n in range(0x80)]


def _varint(n: int) -> bytes:
    if n < 0x80:
        return _ONE_BYTE[n]
    if n < 0x4000:
        return bytes(((n & 0x7F) | 0x80, n >> 7))
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def shared_wire(topic: Topic, entry: Slot[Value]) -> bytes:
    """The fields of ``entry``'s event every stream sends alike (service, property, value, time),
    serialized; kept on the topic, so that a change is encoded once for all its streams."""
    cached = topic.wire
    if cached is not None and cached[0] == entry.stamp and cached[1] is entry.value:
        return cached[2]
    event = pb.Event(service=topic.service, property=topic.path)
    put(event, entry.value)
    event.time.seconds, event.time.nanos = divmod(entry.stamp, 1_000_000_000)
    wire = event.SerializeToString()
    topic.wire = (entry.stamp, entry.value, wire)
    return wire


def encode_wire(ready: list[Ready], sequence: int) -> bytes:
    """:func:`encode_events`, serialized: the same response as bytes."""
    if len(ready) == 1:
        event = _event_wire(*ready[0], sequence + 1)
        return _EVENTS + _varint(len(event)) + event
    parts: list[bytes] = []
    seq = sequence
    for topic, entry in ready:
        seq += 1
        event = _event_wire(topic, entry, seq)
        parts += (_EVENTS, _varint(len(event)), event)
    return b"".join(parts)


def _event_wire(topic: Topic, entry: Slot[Value], sequence: int) -> bytes:
    event = shared_wire(topic, entry) + _SEQUENCE + _varint(sequence)
    if entry.conflated:
        event += _CONFLATED + _varint(entry.conflated)
    if entry.gap:
        event += _GAP
    if entry.removed:
        event += _REMOVED
    return event


def reply_wire(reply: pb.Reply) -> bytes:
    """``reply`` as one entry of a serialized SessionResponse's replies."""
    body = reply.SerializeToString()
    return _REPLIES + _varint(len(body)) + body


def listen_reply_wire(rid: int, response: bytes) -> bytes:
    """The reply to Listen request ``rid`` carrying ``response`` (a serialized ListenResponse),
    as one entry of a serialized SessionResponse's replies."""
    body = _REPLY_ID + _varint(rid) + _REPLY_LISTEN + _varint(len(response)) + response
    return _REPLIES + _varint(len(body)) + body

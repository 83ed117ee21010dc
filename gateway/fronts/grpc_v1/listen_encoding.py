"""Events into ``ListenResponse`` messages: sizes, batches by bytes, and encoding in place.

Two encodings of the same response: :func:`encode_events` builds the message (for the HTTP
front end, which turns it into JSON), :func:`encode_wire` its serialized bytes (what the gRPC
Listen handler sends, and a Session inside its replies: :func:`listen_reply_wire`). The wire
form encodes the fields of an event that every stream sends alike once per change
(:func:`shared_event`, kept on the topic) and adds each stream's own sequence number, count
and flags; protobuf readers take the fields of a message in any order.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable

from gateway.listen.topics import SharedEvent, Topic
from gateway.sizes import BATCH_BYTES
from gateway.wire_values import put
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.conflation import Slot
from services.values import Value

#: One event ready to go: the topic it is about and what waits for it.
Ready = tuple[Topic, Slot[Value]]


def event_size(topic: Topic, entry: Slot[Value]) -> int:
    """About the bytes ``entry`` takes as an Event (exact for the value, which is what can be big).

    A binary value counts its bytes (it travels in ``data``). Counted once per change for
    every stream (:func:`shared_event`).
    """
    return shared_event(topic, entry).size


def shared_event(topic: Topic, entry: Slot[Value]) -> SharedEvent:
    """What every stream's event for ``entry``'s change has alike, kept on the topic: the
    streams a change reaches find it there (the entry with the same stamp and value object)."""
    cached = topic.wire
    if cached is not None and cached.stamp == entry.stamp and cached.value is entry.value:
        return cached
    value = entry.value
    n = len(value) if isinstance(value, bytes) or value.isascii() else len(value.encode())
    shared = SharedEvent(entry.stamp, value, n + len(topic.service) + len(topic.path) + 40)
    topic.wire = shared
    return shared


def within(items: Iterable[Ready]) -> tuple[list[Ready], int]:
    """The first of ``items`` that add up to at most BATCH_BYTES (always at least one), and their size."""
    ready: list[Ready] = []
    size = 0
    for item in items:
        topic, entry = item
        # shared_event's lookup written out: this runs for every event of every stream.
        shared = topic.wire
        if shared is None or shared.stamp != entry.stamp or shared.value is not entry.value:
            shared = shared_event(topic, entry)
        n = shared.size
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
#: A sequence number below 128 as its tag and one byte: every stream's first 127 events; and
#: the tag and the first byte of a longer one (the low seven bits, continued).
_SEQUENCE_TAILS = [_SEQUENCE + one for one in _ONE_BYTE]
_SEQUENCE_LOW = [_SEQUENCE + bytes((n | 0x80,)) for n in range(0x80)]
#: The most bytes of a value's event copied into each of its leads (one per length of what
#: streams add, usually one or two); a bigger one is joined in from the one copy.
LEAD_BODY_BYTES = 4096


def _varint(n: int) -> bytes:
    if n < 0x80:
        return _ONE_BYTE[n]
    if n < 0x4000:
        return bytes(((n & 0x7F) | 0x80, n >> 7))
    if n < 0x200000:
        return bytes(((n & 0x7F) | 0x80, ((n >> 7) & 0x7F) | 0x80, n >> 14))
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def encode_wire(ready: list[Ready], sequence: int) -> bytes:
    """:func:`encode_events`, serialized: the same response as bytes.

    Each event is its lead (its tag, its length and the fields every stream sends alike, kept on
    the change's :class:`SharedEvent` for every stream whose additions take as many bytes) and
    what this stream adds, joined once for the whole response.
    """
    parts: list[bytes] = []
    append = parts.append
    seq = sequence
    for topic, entry in ready:
        seq += 1
        # shared_event's lookup written out: this runs for every event of every stream.
        shared = topic.wire
        if shared is None or shared.stamp != entry.stamp or shared.value is not entry.value:
            shared = shared_event(topic, entry)
        if seq < 0x80:
            tail = _SEQUENCE_TAILS[seq]
        elif seq < 0x4000:
            tail = _SEQUENCE_LOW[seq & 0x7F] + _ONE_BYTE[seq >> 7]
        else:
            tail = _SEQUENCE + _varint(seq)
        if entry.conflated or entry.gap or entry.removed:
            tail += _flags(entry)
        lead = shared.leads.get(len(tail))
        if lead is None:
            lead = _lead(topic, entry, shared, len(tail))
        append(lead)
        if shared.rest:
            append(shared.rest)
        append(tail)
    return b"".join(parts)


def _lead(topic: Topic, entry: Slot[Value], shared: SharedEvent, added: int) -> bytes:
    """The lead of ``shared``'s event for a stream that adds ``added`` bytes; kept for the others."""
    body = shared.body
    if body is None:
        body = shared.body = _shared_body(topic, entry)
        # A big value is not copied into each lead: it follows the lead as a piece of its own.
        shared.rest = body if len(body) > LEAD_BODY_BYTES else b""
    lead = _EVENTS + _varint(len(body) + added)
    if not shared.rest:
        lead += body
    shared.leads[added] = lead
    return lead


def _shared_body(topic: Topic, entry: Slot[Value]) -> bytes:
    """The fields of ``entry``'s event every stream sends alike (service, property, value, time)."""
    event = pb.Event(service=topic.service, property=topic.path)
    put(event, entry.value)
    event.time.seconds, event.time.nanos = divmod(entry.stamp, 1_000_000_000)
    return event.SerializeToString()


def _flags(entry: Slot[Value]) -> bytes:
    flags = _CONFLATED + _varint(entry.conflated) if entry.conflated else b""
    if entry.gap:
        flags += _GAP
    if entry.removed:
        flags += _REMOVED
    return flags


def reply_wire(reply: pb.Reply) -> bytes:
    """``reply`` as one entry of a serialized SessionResponse's replies."""
    body = reply.SerializeToString()
    return _REPLIES + _varint(len(body)) + body


def listen_reply_wire(rid: int, response: bytes) -> bytes:
    """The reply to Listen request ``rid`` carrying ``response`` (a serialized ListenResponse),
    as one entry of a serialized SessionResponse's replies."""
    body = _REPLY_ID + _varint(rid) + _REPLY_LISTEN + _varint(len(response)) + response
    return _REPLIES + _varint(len(body)) + body

"""The Listen side of contract v1: a ``ListenRequest`` read into the engine's request, and what a
stream takes written as ``ListenResponse`` messages, serialized in place.

Two encodings of the same response: :func:`listen_response` builds the message (a Session's
Listens flushed as it ends), :func:`listen_wire` its serialized bytes (what the gRPC Listen
handler sends, and a Session inside its replies: :func:`listen_reply_wire`). The wire form
encodes the fields of an event that every stream sends alike once per change (kept on the
change's :class:`~gateway.engine.events.SharedEvent`, in ``encoded``) and adds each stream's own
sequence number, count and flags; protobuf readers take the fields of a message in any order.
Only this module knows the contract's field numbers for a Listen.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import overload

from google.protobuf.duration_pb2 import Duration

from gateway.engine.events import ListenRequest, Mark, Ready, Selector, SharedEvent, Taken
from gateway.engine.listen.stream import ListenStream
from gateway.wire_values import put
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.errors import InvalidArgument

# -- requests ------------------------------------------------------------------


class _Selectors(Sequence[Selector]):
    """The selectors of a ``ListenRequest``, read from the message as they are asked for: the hub
    counts them against ``limits.max_selectors`` before it reads one (a message may hold a
    hundred thousand). An empty service in ``more`` is the request's own."""

    __slots__ = ("_request",)

    def __init__(self, request: pb.ListenRequest) -> None:
        self._request = request

    def __len__(self) -> int:
        return 1 + len(self._request.more)

    @overload
    def __getitem__(self, index: int) -> Selector: ...

    @overload
    def __getitem__(self, index: slice) -> Sequence[Selector]: ...

    def __getitem__(self, index: int | slice) -> Selector | Sequence[Selector]:
        if isinstance(index, slice):
            return [self[i] for i in range(len(self))[index]]
        request = self._request
        if index in (0, -len(self)):
            return Selector(request.service, request.property, _params(request.parameters))
        ref = request.more[index - 1 if index > 0 else index]
        return Selector(ref.service or request.service, ref.property, _params(ref.parameters))

    def __iter__(self) -> Iterator[Selector]:
        request = self._request
        yield Selector(request.service, request.property, _params(request.parameters))
        for ref in request.more:
            yield Selector(ref.service or request.service, ref.property, _params(ref.parameters))


def _params(parameters: Mapping[str, str]) -> tuple[tuple[str, str], ...]:
    return tuple(sorted(parameters.items())) if parameters else ()


def _seconds(d: Duration, name: str) -> float:
    if (d.seconds < 0 < d.nanos) or (d.nanos < 0 < d.seconds):
        raise InvalidArgument(f"options.{name} is not a Duration: its seconds and nanos differ in sign")
    return d.seconds + d.nanos / 1e9


def listen_request(request: pb.ListenRequest) -> ListenRequest:
    """``request`` in the engine's terms; the hub checks it against the limits."""
    opts = request.options
    return ListenRequest(
        _Selectors(request),
        updates_only=opts.updates_only,
        min_interval=_seconds(opts.min_interval, "min_interval"),
        sample_interval=_seconds(opts.sample_interval, "sample_interval"),
        heartbeat_interval=_seconds(opts.heartbeat_interval, "heartbeat_interval"),
        max_batch=opts.max_batch,
    )


# -- responses, as messages ------------------------------------------------------


def encode_events(ready: Sequence[Ready], sequence: int) -> pb.ListenResponse:
    """One response carrying ``ready``, numbered from ``sequence + 1``."""
    # Events are added in place: built apart, each would be copied into the response.
    response = pb.ListenResponse()
    add = response.events.add
    seq = sequence
    for _, slot in ready:
        seq += 1
        shared = slot.value
        ev = add(
            service=shared.service,
            property=shared.path,
            sequence=seq,
            conflated=slot.conflated,
            gap=slot.gap,
            removed=slot.removed,
        )
        put(ev, shared.value)
        ev.time.seconds, ev.time.nanos = divmod(shared.stamp, 1_000_000_000)
    return response


def marker_response(mark: Mark) -> pb.ListenResponse:
    """The marker's response, a new message (its receiver may change it)."""
    return pb.ListenResponse(sync=True) if mark is Mark.SYNC else pb.ListenResponse(heartbeat=True)


def listen_response(taken: Taken) -> pb.ListenResponse:
    """What a stream took (:meth:`ListenStream.take`) as one response."""
    if isinstance(taken, Mark):
        return marker_response(taken)
    return encode_events(*taken)


# -- responses, serialized ---------------------------------------------------------

#: Each marker's response, serialized.
MARK_WIRE = {
    Mark.SYNC: pb.ListenResponse(sync=True).SerializeToString(),
    Mark.HEARTBEAT: pb.ListenResponse(heartbeat=True).SerializeToString(),
}

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


class EncodedEvent:
    """A change's shared fields serialized (service, property, value, time), made by the first
    stream that sends the change and kept in its :attr:`SharedEvent.encoded` for the others."""

    __slots__ = ("body", "leads", "rest")

    def __init__(self, body: bytes) -> None:
        self.body = body
        #: The event's tag and length followed by ``body``, per number of bytes a stream adds
        #: (its sequence number, count and flags): a few distinct numbers at most.
        self.leads: dict[int, bytes] = {}
        #: ``body`` when it is too big to copy into each lead (it follows the lead then), else b"".
        self.rest = body if len(body) > LEAD_BODY_BYTES else b""


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


def encode_wire(ready: Sequence[Ready], sequence: int) -> bytes:
    """:func:`encode_events`, serialized: the same response as bytes.

    Each event is its lead (its tag, its length and the fields every stream sends alike, kept on
    the change's :class:`EncodedEvent` for every stream whose additions take as many bytes) and
    what this stream adds, joined once for the whole response.
    """
    parts: list[bytes] = []
    append = parts.append
    seq = sequence
    for _, slot in ready:
        seq += 1
        if seq < 0x80:
            tail = _SEQUENCE_TAILS[seq]
        elif seq < 0x4000:
            tail = _SEQUENCE_LOW[seq & 0x7F] + _ONE_BYTE[seq >> 7]
        else:
            tail = _SEQUENCE + _varint(seq)
        if slot.conflated or slot.gap or slot.removed:
            tail += _flags(slot.conflated, slot.gap, slot.removed)
        shared = slot.value
        encoded = shared.encoded
        if encoded is None:
            encoded = shared.encoded = EncodedEvent(_shared_body(shared))
        lead = encoded.leads.get(len(tail))
        if lead is None:
            lead = _lead(encoded, len(tail))
        append(lead)
        if encoded.rest:
            append(encoded.rest)
        append(tail)
    return b"".join(parts)


def listen_wire(taken: Taken) -> bytes:
    """What a stream took (:meth:`ListenStream.take`) as one response, serialized."""
    if isinstance(taken, Mark):
        return MARK_WIRE[taken]
    return encode_wire(*taken)


def take_wire(stream: ListenStream) -> bytes | None:
    """What ``stream`` has ready as one serialized response; None when nothing is."""
    taken = stream.take()
    return None if taken is None else listen_wire(taken)


def _lead(encoded: EncodedEvent, added: int) -> bytes:
    """The lead of ``encoded``'s event for a stream that adds ``added`` bytes; kept for the others."""
    body = encoded.body
    lead = _EVENTS + _varint(len(body) + added)
    if not encoded.rest:  # a big value is not copied into each lead: it follows as a piece of its own
        lead += body
    encoded.leads[added] = lead
    return lead


def _shared_body(shared: SharedEvent) -> bytes:
    """The fields of ``shared``'s event every stream sends alike (service, property, value, time)."""
    event = pb.Event(service=shared.service, property=shared.path)
    put(event, shared.value)
    event.time.seconds, event.time.nanos = divmod(shared.stamp, 1_000_000_000)
    return event.SerializeToString()


def _flags(conflated: int, gap: bool, removed: bool) -> bytes:
    flags = _CONFLATED + _varint(conflated) if conflated else b""
    if gap:
        flags += _GAP
    if removed:
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

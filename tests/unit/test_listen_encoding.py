"""The serialized Listen response (what the gRPC Listen handler sends) reads back as the message,
and a Listen request reads into the engine's own request."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.fake_backend import DictBackend

from gateway.config import Limits
from gateway.engine.events import ListenRequest, Mark, Selector, SharedEvent
from gateway.engine.listen.requests import check_listen
from gateway.engine.listen.topics import Topic
from gateway.fronts.grpc_v1.listen_encoding import (
    LEAD_BODY_BYTES,
    MARK_WIRE,
    encode_events,
    encode_wire,
    listen_reply_wire,
    listen_request,
    marker_response,
    reply_wire,
)
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.conflation import ConflatingQueue, Slot
from services.kernel.errors import InvalidArgument, ResourceExhausted
from services.kernel.values import Value

values = st.one_of(st.text(max_size=300), st.binary(max_size=300))
paths = st.sampled_from(["a", "robots.scout1.location", "ü.x"])


def _queued(event: SharedEvent, gap: bool = False, removed: bool = False) -> Slot[SharedEvent]:
    """What a Listen stream's queue holds for ``event``."""
    queue: ConflatingQueue[int, SharedEvent] = ConflatingQueue()
    queue.put(0, event, event.stamp, gap, removed)
    slot = queue.get(0)
    assert slot is not None
    return slot


def _slot(value: Value, stamp: int, conflated: int, gap: bool, removed: bool) -> Slot[SharedEvent]:
    slot = _queued(SharedEvent("svc", "a", value, stamp), gap, removed)
    slot.conflated = conflated
    return slot


def _on(path: str, slot: Slot[SharedEvent]) -> Slot[SharedEvent]:
    """``slot``'s change as an event of property ``path`` of ``svc``."""
    event = slot.value
    moved = _queued(SharedEvent("svc", path, event.value, event.stamp), slot.gap, slot.removed)
    moved.conflated = slot.conflated
    return moved


slots = st.builds(
    _slot,
    values,
    st.integers(min_value=0, max_value=2**62),
    st.integers(min_value=0, max_value=2**32 - 1),
    st.booleans(),
    st.booleans(),
)


def _topic(service: str, path: str) -> Topic:
    return Topic((service, path, ()), DictBackend({}))


# No deadline: on a loaded machine one example may take longer than hypothesis's 200 ms.
@settings(deadline=None)
@given(st.lists(st.tuples(paths, slots), min_size=1, max_size=8), st.integers(min_value=0, max_value=2**40))
def test_the_wire_form_parses_to_the_message_built_in_place(
    events: list[tuple[str, Slot[SharedEvent]]], sequence: int
) -> None:
    topics = {path: _topic("svc", path) for path, _ in events}
    ready = [(topics[path], _on(path, slot)) for path, slot in events]
    wire = encode_wire(ready, sequence)
    assert pb.ListenResponse.FromString(wire) == encode_events(ready, sequence)


def test_two_streams_share_the_encoded_change_and_keep_their_own_numbers() -> None:
    topic = _topic("scout1", "location")
    event = SharedEvent("scout1", "location", "(1 2 3)", 1_700_000_000_123_456_789)
    change = _queued(event)
    first = pb.ListenResponse.FromString(encode_wire([(topic, change)], 0))
    cached = event.encoded
    behind = _queued(event, gap=True)
    behind.conflated = 4
    second = pb.ListenResponse.FromString(encode_wire([(topic, behind)], 20_000))
    assert cached is not None and event.encoded is cached  # encoded once
    assert (first.events[0].sequence, first.events[0].conflated, first.events[0].gap) == (1, 0, False)
    assert (second.events[0].sequence, second.events[0].conflated, second.events[0].gap) == (20_001, 4, True)
    assert second.events[0].value == "(1 2 3)"
    assert second.events[0].time.ToNanoseconds() == event.stamp
    newer = _queued(SharedEvent("scout1", "location", "(4 5 6)", event.stamp + 1))
    assert pb.ListenResponse.FromString(encode_wire([(topic, newer)], 1)).events[0].value == "(4 5 6)"


def test_markers_serialized_are_the_marker_messages() -> None:
    for mark in Mark:
        assert pb.ListenResponse.FromString(MARK_WIRE[mark]) == marker_response(mark)
    assert marker_response(Mark.SYNC).sync
    assert marker_response(Mark.HEARTBEAT).heartbeat


@settings(deadline=None)
@given(st.integers(min_value=0, max_value=2**64 - 1), slots)
def test_listen_replies_serialized_join_the_other_replies_of_a_session_response(
    rid: int, slot: Slot[SharedEvent]
) -> None:
    topic = _topic("svc", "a")
    answer = pb.Reply(id=3, get=pb.GetResponse(value="x"))
    head = pb.SessionResponse(replies=[answer]).SerializeToString()
    wire = head + listen_reply_wire(rid, encode_wire([(topic, slot)], 41)) + reply_wire(pb.Reply(id=rid))
    expected = pb.SessionResponse(
        replies=[answer, pb.Reply(id=rid, listen=encode_events([(topic, slot)], 41)), pb.Reply(id=rid)]
    )
    assert pb.SessionResponse.FromString(wire) == expected


#: Sequence numbers on each side of each varint width the encoding treats apart (one byte, two,
#: three, more).
EDGES = [1, 127, 128, 16_383, 16_384, 2**21 - 1, 2**21, 2**28, 2**40]


@settings(deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(["a", "b"]), slots), min_size=1, max_size=4),
    st.lists(st.sampled_from(EDGES), min_size=2, max_size=4),
    st.one_of(values, st.binary(min_size=LEAD_BODY_BYTES, max_size=LEAD_BODY_BYTES + 50)),
)
def test_streams_at_any_sequence_share_one_change_and_each_reads_its_own_message(
    events: list[tuple[str, Slot[SharedEvent]]], sequences: list[int], big: Value
) -> None:
    topics = {path: _topic("svc", path) for path in ("a", "b")}
    events = [*events, ("a", _slot(big, 7, 0, False, False))]
    ready = [(topics[path], _on(path, slot)) for path, slot in events]
    for sequence in sequences:  # one stream each, all sending the same changes
        wire = encode_wire(ready, sequence)
        expected = encode_events(ready, sequence)
        assert wire == _canonical(expected)
        assert pb.ListenResponse.FromString(wire) == expected


def _canonical(response: pb.ListenResponse) -> bytes:
    """``response`` serialized with each event's fields in the order encode_wire writes them:
    the shared ones (protobuf's own bytes of an Event holding only those), then the stream's."""
    out = b""
    for event in response.events:
        shared = pb.Event(service=event.service, property=event.property, value=event.value, time=event.time)
        if event.HasField("data"):
            shared.data = event.data
        own = pb.Event(
            sequence=event.sequence, conflated=event.conflated, gap=event.gap, removed=event.removed
        )
        body = shared.SerializeToString() + own.SerializeToString()
        out += pb.ListenResponse(events=[pb.Event()]).SerializeToString()[:1] + _varint(len(body)) + body
    return out


def _varint(n: int) -> bytes:
    out = b""
    while n > 0x7F:
        out += bytes(((n & 0x7F) | 0x80,))
        n >>= 7
    return out + bytes((n,))


def test_a_change_is_led_once_per_length_and_a_big_value_is_not_copied_into_its_leads() -> None:
    topic = _topic("cam", "frame")
    small = _queued(SharedEvent("cam", "frame", "x", 1))
    encode_wire([(topic, small)], 0)
    encode_wire([(topic, small)], 5)  # a second stream whose sequence number is as long
    shared = small.value.encoded
    assert shared is not None and list(shared.leads) == [2] and shared.rest == b""
    encode_wire([(topic, small)], 200)  # a third, with a longer one: a second lead
    assert sorted(shared.leads) == [2, 3]
    frame = _queued(SharedEvent("cam", "frame", bytes(LEAD_BODY_BYTES + 1), 2))
    first = encode_wire([(topic, frame)], 0)
    shared = frame.value.encoded
    assert shared is not None and shared.rest is shared.body
    assert all(len(lead) < 8 for lead in shared.leads.values())
    assert pb.ListenResponse.FromString(first).events[0].data == frame.value.value


def test_a_listen_request_reads_into_the_engines_request_with_the_requests_own_service() -> None:
    request = pb.ListenRequest(
        service="s",
        property="a",
        parameters={"frame": "robot"},
        more=[pb.PropertyRef(property="b"), pb.PropertyRef(service="t", property="c")],
    )
    request.options.min_interval.FromMilliseconds(5)
    request.options.max_batch = 100_000
    listen = listen_request(request)
    assert list(listen.selectors) == [
        Selector("s", "a", (("frame", "robot"),)),
        Selector("s", "b"),
        Selector("t", "c"),
    ]
    assert listen.selectors[-1] == Selector("t", "c") and len(listen.selectors) == 3
    selectors, options = check_listen(listen, Limits())
    assert len(selectors) == 3
    assert (options.min_interval, options.max_batch) == (0.005, Limits().max_batch)


def test_a_duration_whose_seconds_and_nanos_differ_in_sign_is_refused() -> None:
    request = pb.ListenRequest(service="s", property="a")
    request.options.heartbeat_interval.seconds = 1
    request.options.heartbeat_interval.nanos = -5
    with pytest.raises(InvalidArgument, match="heartbeat_interval"):
        listen_request(request)


def test_a_listen_of_more_selectors_than_the_limit_or_none_is_refused() -> None:
    request = pb.ListenRequest(service="s", property="a", more=[pb.PropertyRef(property="b")] * 100)
    with pytest.raises(ResourceExhausted, match="at most 2 selectors, this one has 101"):
        check_listen(listen_request(request), Limits(max_selectors=2))
    with pytest.raises(InvalidArgument, match="at least one selector"):
        check_listen(ListenRequest([]), Limits())

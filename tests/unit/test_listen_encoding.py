"""The serialized Listen response (what the gRPC Listen handler sends) reads back as the message."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st
from support.fake_backend import DictBackend

from gateway.listen.encoding import (
    LEAD_BODY_BYTES,
    Mark,
    encode_events,
    encode_wire,
    listen_reply_wire,
    marker_response,
    reply_wire,
)
from gateway.listen.topics import Topic
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.conflation import ConflatingQueue, Slot
from services.values import Value

values = st.one_of(st.text(max_size=300), st.binary(max_size=300))
paths = st.sampled_from(["a", "robots.scout1.location", "ü.x"])


def _slot(value: Value, stamp: int, conflated: int, gap: bool, removed: bool) -> Slot[Value]:
    queue: ConflatingQueue[int, Value] = ConflatingQueue()
    queue.put(0, value, stamp, gap, removed)
    slot = queue.get(0)
    assert slot is not None
    slot.conflated = conflated
    return slot


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
    events: list[tuple[str, Slot[Value]]], sequence: int
) -> None:
    topics = {path: _topic("svc", path) for path, _ in events}
    ready = [(topics[path], slot) for path, slot in events]
    wire = encode_wire(ready, sequence)
    assert pb.ListenResponse.FromString(wire) == encode_events(ready, sequence)


def test_two_streams_share_the_encoded_change_and_keep_their_own_numbers() -> None:
    topic = _topic("scout1", "location")
    change = _slot("(1 2 3)", 1_700_000_000_123_456_789, 0, False, False)
    first = pb.ListenResponse.FromString(encode_wire([(topic, change)], 0))
    cached = topic.wire
    behind = _slot("(1 2 3)", change.stamp, 4, True, False)
    behind.value = change.value
    second = pb.ListenResponse.FromString(encode_wire([(topic, behind)], 20_000))
    assert topic.wire is cached  # encoded once
    assert (first.events[0].sequence, first.events[0].conflated, first.events[0].gap) == (1, 0, False)
    assert (second.events[0].sequence, second.events[0].conflated, second.events[0].gap) == (20_001, 4, True)
    assert second.events[0].value == "(1 2 3)"
    assert second.events[0].time.ToNanoseconds() == change.stamp
    newer = _slot("(4 5 6)", change.stamp + 1, 0, False, False)
    assert pb.ListenResponse.FromString(encode_wire([(topic, newer)], 1)).events[0].value == "(4 5 6)"


def test_markers_serialized_are_the_marker_messages() -> None:
    for mark in Mark:
        assert pb.ListenResponse.FromString(mark.wire) == marker_response(mark)
    assert marker_response(Mark.SYNC).sync
    assert marker_response(Mark.HEARTBEAT).heartbeat


@settings(deadline=None)
@given(st.integers(min_value=0, max_value=2**64 - 1), slots)
def test_listen_replies_serialized_join_the_other_replies_of_a_session_response(
    rid: int, slot: Slot[Value]
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
    events: list[tuple[str, Slot[Value]]], sequences: list[int], big: Value
) -> None:
    topics = {path: _topic("svc", path) for path in ("a", "b")}
    events = [*events, ("a", _slot(big, 7, 0, False, False))]
    ready = [(topics[path], slot) for path, slot in events]
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
    small = _slot("x", 1, 0, False, False)
    encode_wire([(topic, small)], 0)
    encode_wire([(topic, small)], 5)  # a second stream whose sequence number is as long
    shared = topic.wire
    assert shared is not None and list(shared.leads) == [2] and shared.rest == b""
    encode_wire([(topic, small)], 200)  # a third, with a longer one: a second lead
    assert sorted(shared.leads) == [2, 3]
    frame = _slot(bytes(LEAD_BODY_BYTES + 1), 2, 0, False, False)
    first = encode_wire([(topic, frame)], 0)
    shared = topic.wire
    assert shared is not None and shared.body is not None and shared.rest is shared.body
    assert all(len(lead) < 8 for lead in shared.leads.values())
    assert pb.ListenResponse.FromString(first).events[0].data == frame.value

"""The line-protocol codec: round trips, hostile bytes, resynchronisation, limits."""

from __future__ import annotations

import re
from pathlib import Path
from typing import get_args

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.kernel.errors import Code
from services.kernel.line_protocol import (
    MAX_LINE,
    BadLine,
    ErrorReply,
    Event,
    Frame,
    Get,
    Gone,
    Hello,
    HelloRequest,
    LineProtocolError,
    LineReceiver,
    Listen,
    Ok,
    Ping,
    Pong,
    Set,
    Unlisten,
    crc8,
    decode_line,
    encode,
)

ROOT = Path(__file__).resolve().parents[2]

tags = st.none() | st.from_regex(r"\A[A-Za-z0-9_-]{1,8}\Z")
paths = st.from_regex(r"\A[A-Za-z0-9_-]{1,12}(\.[A-Za-z0-9_-]{1,12}){0,3}\Z")
names = st.from_regex(r"\A[A-Za-z0-9_.-]{1,12}\Z")
texts = st.text(max_size=60)
#: Values of SET, OK and EVENT: text, or bytes (the ``\=`` base64 form of protocol 1.2).
values = texts | st.binary(max_size=60)
#: PING and PONG data travel as sent (no escapes), so they hold no control characters.
ping_data = st.text(st.characters(exclude_categories=("Cc", "Cs")), max_size=60)
params = st.dictionaries(names, texts, max_size=3)
hello_extra = st.dictionaries(
    names.filter(lambda k: k not in {"name", "type", "push", "maxline", "inflight", "rxbuf"}),
    texts,
    max_size=2,
)

frames: st.SearchStrategy[Frame] = st.one_of(
    st.builds(Get, paths, params, tags),
    st.builds(Set, paths, values, params, tags),
    st.builds(Listen, paths, params, tags),
    st.builds(Unlisten, paths, params, tags),
    st.builds(Ping, ping_data, tags),
    st.builds(Pong, ping_data, tags),
    st.builds(HelloRequest, tags),
    st.builds(
        Hello,
        name=texts,
        type=texts,
        push=st.booleans(),
        max_line=st.integers(64, 100_000),
        version=st.integers(0, 9999),
        extra=hello_extra,
        tag=tags,
        inflight=st.none() | st.integers(1, 4096),
        rxbuf=st.none() | st.integers(16, 65536),
    ),
    st.builds(Ok, values, tags),
    st.builds(ErrorReply, st.integers(0, 999), texts, tags),
    st.builds(Event, paths, values),
    st.builds(Gone, paths),
)


@given(frames, st.booleans())
def test_every_frame_round_trips(frame: Frame, checksum: bool) -> None:
    line = encode(frame, checksum=checksum)
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    assert decode_line(line[:-1]) == frame
    assert LineReceiver().receive_data(line) == [frame]


@given(st.binary(max_size=300))
def test_arbitrary_line_raises_only_the_protocol_error(data: bytes) -> None:
    try:
        decode_line(data)
    except LineProtocolError as exc:
        assert isinstance(exc.code, Code)
        assert exc.message


@given(st.lists(st.binary(max_size=400), max_size=8))
def test_receiver_never_raises_and_stays_bounded(chunks: list[bytes]) -> None:
    receiver = LineReceiver(max_line=128)
    for chunk in chunks:
        for item in receiver.receive_data(chunk):
            assert isinstance(item, (BadLine, *get_args(Frame)))
        assert receiver.pending < 128


@given(st.binary(max_size=3000), frames)
def test_garbage_then_newline_then_a_valid_line_yields_that_line(garbage: bytes, frame: Frame) -> None:
    out = LineReceiver().receive_data(garbage + b"\n" + encode(frame))
    assert out[-1] == frame


@settings(max_examples=60)
@given(st.lists(frames | st.binary(max_size=1500), min_size=1, max_size=8), st.data())
def test_splitting_the_stream_anywhere_gives_the_same_frames(
    parts: list[Frame | bytes], data: st.DataObject
) -> None:
    stream = b"".join(p if isinstance(p, bytes) else encode(p) for p in parts)
    whole = LineReceiver().receive_data(stream)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    receiver = LineReceiver()
    pieces = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        pieces.extend(receiver.receive_data(stream[a:b]))
    assert pieces == whole


def test_crc8_check_value() -> None:
    assert crc8(b"123456789") == 0xF4


def test_escapes_in_values_and_parameters() -> None:
    frame = Set("note", "two\nlines \\ and\r", {"frame": "a b=c"}, tag="x")
    line = encode(frame)
    assert line == b"#x SET frame=a\\sb=c note two\\nlines \\\\ and\\r\n"
    assert decode_line(line[:-1]) == frame


def test_bad_escape_is_a_clear_error_with_the_tag() -> None:
    with pytest.raises(LineProtocolError, match="bad escape") as info:
        decode_line(b"#5 SET note a\\qb")
    assert info.value.code == Code.INVALID_ARGUMENT
    assert info.value.tag == "5"


def test_hand_typed_lines_are_accepted() -> None:
    out = LineReceiver().receive_data(b"get location\r\n\r\n  \nset   velocity (1 0 0)\nping\n")
    assert out == [Get("location"), Set("velocity", "(1 0 0)"), Ping()]


def test_unknown_word_is_unimplemented() -> None:
    (bad,) = LineReceiver().receive_data(b"#t1 FROB x\n")
    assert bad == BadLine(Code.UNIMPLEMENTED, "unknown word 'FROB'", "t1")


def test_over_long_line_is_reported_once_with_its_tag_then_the_next_line_is_read() -> None:
    receiver = LineReceiver()
    long_line = b"#42 SET x " + b"y" * 5000
    out = []
    for i in range(0, len(long_line), 700):
        out += receiver.receive_data(long_line[i : i + 700])
    assert len(out) == 1
    assert out[0].code == Code.RESOURCE_EXHAUSTED and out[0].tag == "42"
    assert "line too long" in out[0].message
    assert receiver.receive_data(b"yyy\n#43 GET x\n") == [Get("x", tag="43")]


def test_line_of_exactly_the_limit_is_accepted() -> None:
    line = b"OK " + b"v" * (MAX_LINE - 4) + b"\n"
    assert len(line) == MAX_LINE
    assert LineReceiver().receive_data(line) == [Ok("v" * (MAX_LINE - 4))]
    (bad,) = LineReceiver().receive_data(b"OK v" + line)
    assert bad.code == Code.RESOURCE_EXHAUSTED


def test_encoding_an_over_long_frame_raises_resource_exhausted() -> None:
    with pytest.raises(LineProtocolError) as info:
        encode(Ok("v" * 200, tag="3"), max_line=128)
    assert info.value.code == Code.RESOURCE_EXHAUSTED and info.value.tag == "3"


def test_checksum_mismatch_is_data_loss_without_a_tag() -> None:
    good = encode(Get("data", tag="2"), checksum=True)
    damaged = good.replace(b"data", b"dat?")
    (bad,) = LineReceiver().receive_data(damaged)
    assert bad.code == Code.DATA_LOSS and bad.tag is None
    (bad,) = LineReceiver().receive_data(b"$#2 GET data\n")
    assert bad.code == Code.DATA_LOSS


def test_unencodable_fields_are_refused() -> None:
    for frame in (Get("a b"), Get("x", tag="toolongtag"), Get("x", {"a b": "c"}), Event("x=y", "v")):
        with pytest.raises(LineProtocolError):
            encode(frame)


def test_error_reply_maps_codes_one_to_one() -> None:
    assert ErrorReply(5, "no such").to_exception().code == Code.NOT_FOUND
    assert ErrorReply(77, "odd").to_exception().code == Code.UNKNOWN
    assert decode_line(b"ERR 9 read-only") == ErrorReply(9, "read-only")


def test_every_session_line_in_the_specification_decodes() -> None:
    spec = (ROOT / "docs" / "line-protocol.md").read_text()
    lines = re.findall(r"^[<>] (.*)$", spec, re.MULTILINE)
    assert len(lines) > 20
    for line in lines:
        raw = line.encode()
        if b"dat?" in raw:
            with pytest.raises(LineProtocolError):
                decode_line(raw)
        elif not raw.startswith(b"FROB"):
            decode_line(raw)


# -- protocol 1.1 -------------------------------------------------------------


def test_a_greeting_states_flow_control_and_a_1_0_greeting_states_none() -> None:
    hello = decode_line(b"HELLO 1 name=avr type=sensor push=1 maxline=64 inflight=1 rxbuf=32")
    assert isinstance(hello, Hello)
    assert (hello.max_line, hello.inflight, hello.rxbuf, dict(hello.extra)) == (64, 1, 32, {})
    old = decode_line(b"HELLO 1 name=avr type=sensor push=1 maxline=64")
    assert isinstance(old, Hello) and (old.inflight, old.rxbuf) == (None, None)
    assert encode(hello) == b"HELLO 1 name=avr type=sensor push=1 maxline=64 inflight=1 rxbuf=32\n"


@pytest.mark.parametrize(
    ("line", "says"),
    [
        (b"HELLO 1 maxline=32", "maxline=32 is outside 64.."),
        (b"HELLO 1 inflight=0", "inflight=0 is outside 1..4096"),
        (b"HELLO 1 rxbuf=8", "rxbuf=8 is outside 16..65536"),
        (b"HELLO 1 rxbuf=lots", "rxbuf='lots' is not a number"),
        (b"HELLO 1 push=2", "push='2'"),
        (b"HELLO 1 name=a name=b", "field 'name' given twice"),
    ],
)
def test_a_greeting_that_cannot_be_accepted_is_a_bad_greeting_not_noise(line: bytes, says: str) -> None:
    (bad,) = LineReceiver().receive_data(line + b"\n")
    assert isinstance(bad, BadLine) and bad.greeting and bad.code == Code.INVALID_ARGUMENT
    assert bad.message.startswith("bad greeting: ") and says in bad.message


def test_leading_spaces_are_skipped_before_a_tag_and_a_checksum_too() -> None:
    assert decode_line(b"   #7 GET x") == Get("x", {}, "7")
    body = b"#8 GET x"
    assert decode_line(b"  $" + body + b"*%02X" % crc8(body)) == Get("x", {}, "8")
    assert decode_line(b"HELLO  ") == HelloRequest()
    with pytest.raises(LineProtocolError) as info:
        decode_line(b"HELLO x")
    assert info.value.code == Code.INVALID_ARGUMENT


def test_a_space_after_the_dollar_makes_a_checked_line_bad_untagged_even_when_its_checksum_is_right() -> None:
    for body in (b" #4 PING", b" GET x"):
        line = b"$" + body + b"*%02X" % crc8(body)
        with pytest.raises(LineProtocolError) as info:
            decode_line(line)
        assert info.value.code == Code.INVALID_ARGUMENT and info.value.tag is None
        assert "space after '$'" in info.value.message
        (bad,) = LineReceiver().receive_data(line + b"\n")
        assert isinstance(bad, BadLine) and bad.checksummed and bad.tag is None


def test_the_receiver_says_which_lines_were_checksummed_and_a_plain_hello_ends_checksum_mode() -> None:
    receiver = LineReceiver()
    good = b"$GET x*%02X\n" % crc8(b"GET x")
    frames = receiver.receive_data(b"GET a\n" + good + b"$GET y*00\n")
    assert [type(f) for f in frames] == [Get, Get, BadLine]
    assert receiver.last_checked == [False, True, True]
    assert isinstance(frames[2], BadLine) and frames[2].checksummed and frames[2].code == Code.DATA_LOSS
    assert receiver.saw_checksum
    receiver.receive_data(b"HELLO\n")
    assert not receiver.saw_checksum
    receiver.receive_data(b"$HELLO*%02X\n" % crc8(b"HELLO"))
    assert receiver.saw_checksum


def test_ping_data_is_echoed_byte_for_byte() -> None:
    # PING data is opaque (docs/device-spec.md §3.6): no escape is decoded, so none is refused.
    for raw in (b"PING a\\qb\n", b"#1 PING a\\sb  \n"):
        (ping,) = LineReceiver().receive_data(raw)
        assert isinstance(ping, Ping)
        echoed = encode(Pong(ping.data, ping.tag)).rstrip(b"\n")
        assert echoed.endswith(raw.rstrip(b"\n").split(b"PING", 1)[1])

"""Binary values on the line (protocol 1.2): ``\\=`` and standard base64, exact both ways.

The codec is fed bytes and must give back the same bytes; every bad form is
a clear INVALID_ARGUMENT that names what is wrong, tagged when the line was;
the line limit counts the encoded line.
"""

from __future__ import annotations

import base64

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.kernel.errors import Code
from services.kernel.line_protocol import (
    MAX_LINE,
    BadLine,
    ErrorReply,
    Event,
    Get,
    LineProtocolError,
    LineReceiver,
    Ok,
    Set,
    decode_line,
    decode_value,
    encode,
    encode_value,
)


def test_the_example_of_the_specification_is_a_jpeg_header() -> None:
    frame = decode_line(b"#4 OK \\=/9j/4AAQSkZJRg==")
    assert frame == Ok(b"\xff\xd8\xff\xe0\x00\x10JFIF", "4")
    assert encode(frame) == b"#4 OK \\=/9j/4AAQSkZJRg==\n"


@given(st.binary(max_size=2000))
def test_any_bytes_go_through_set_ok_and_event_byte_for_byte(data: bytes) -> None:
    for frame in (Set("frame", data, tag="1"), Ok(data, "1"), Event("frame", data)):
        line = encode(frame, max_line=4096)
        # The value is standard base64 with padding, no line break: what any library writes.
        assert line.endswith(b"\\=" + base64.b64encode(data) + b"\n")
        decoded = decode_line(line[:-1], max_line=4096)
        assert decoded == frame and type(getattr(decoded, "value", None)) is bytes


@given(st.binary(max_size=300), st.booleans())
def test_bytes_survive_a_checksum_and_a_stream_cut_anywhere(data: bytes, checksum: bool) -> None:
    stream = encode(Ok(data, "7"), checksum=checksum) + encode(Event("image", data))
    receiver = LineReceiver()
    out = [frame for i in range(len(stream)) for frame in receiver.receive_data(stream[i : i + 1])]
    assert out == [Ok(data, "7"), Event("image", data)]


def test_empty_bytes_are_still_binary_and_empty_text_is_still_text() -> None:
    assert encode(Ok(b"")) == b"OK \\=\n"
    assert decode_line(b"OK \\=") == Ok(b"")
    assert decode_line(b"OK") == Ok("") and decode_line(b"OK ") == Ok("")
    assert decode_line(b"SET x \\=") == Set("x", b"")


def test_text_that_begins_with_a_backslash_and_an_equals_sign_stays_text() -> None:
    line = encode(Set("note", "\\=not base64"))
    assert line == b"SET note \\\\=not base64\n"
    assert decode_line(line[:-1]) == Set("note", "\\=not base64")
    assert encode_value("\\=") == "\\\\=" and decode_value("\\\\=") == "\\="


@pytest.mark.parametrize(
    ("line", "says"),
    [
        (b"#9 SET frame \\=AB$=", "'$' at position 2 is not in the base64 alphabet"),
        (b"#9 SET frame \\=QUJD RA==", "' ' at position 4 is not in the base64 alphabet"),
        (b"#9 SET frame \\=QUJDRA", "6 characters; base64 comes in groups of 4"),
        (b"#9 SET frame \\=QQ==QQ==", "'=' is padding and may only end the value"),
        (b"#9 SET frame \\=QR==", "padding bits of the last quantum are not zero"),
        (b"#9 SET frame \\=QUJD\\n", "'\\\\' at position 4 is not in the base64 alphabet"),
        (b"#9 SET frame \\=QUJ-", "'-' at position 3"),  # base64url is not standard base64
        (b"#9 SET frame x\\=QUJD", "'\\=' (a binary value) may only open a SET, OK or EVENT value"),
        (b"#9 SET p=\\=QUJD frame x", "'\\=' (a binary value) may only open"),
        (b"#9 OK  \\=QUJD", "'\\=' (a binary value) may only open"),  # two spaces: the value is " \=..."
    ],
)
def test_a_bad_binary_form_is_invalid_argument_naming_the_fault(line: bytes, says: str) -> None:
    (bad,) = LineReceiver().receive_data(line + b"\n")
    assert isinstance(bad, BadLine)
    assert (bad.code, bad.tag) == (Code.INVALID_ARGUMENT, "9")
    assert says in bad.message, bad.message


def test_an_error_message_is_text_never_a_binary_value() -> None:
    with pytest.raises(LineProtocolError, match="may only open"):
        decode_line(b"ERR 3 \\=QUJD")
    assert decode_line(b"ERR 3 bad escape '\\\\='") == ErrorReply(3, "bad escape '\\='")


def test_the_line_limit_counts_the_encoded_line() -> None:
    # "#1 OK \=" is 8 bytes, the LF 1: 1015 bytes of base64 do not fit 1024, 1012 do (759 bytes of data).
    fits = bytes(759)
    assert len(encode(Ok(fits, "1"))) == 8 + 1012 + 1 <= MAX_LINE
    with pytest.raises(LineProtocolError) as info:
        encode(Ok(bytes(760), "1"))
    assert (
        info.value.code == Code.RESOURCE_EXHAUSTED and "1025 bytes, the limit is 1024" in info.value.message
    )
    (bad,) = LineReceiver().receive_data(b"#2 OK \\=" + b"A" * 1016 + b"\n")
    assert isinstance(bad, BadLine) and (bad.code, bad.tag) == (Code.RESOURCE_EXHAUSTED, "2")
    # A receiver with a larger limit takes the larger line.
    big = bytes(range(256)) * 40
    assert LineReceiver(max_line=16384).receive_data(encode(Ok(big), max_line=16384)) == [Ok(big)]


def test_a_1_1_peer_that_does_not_know_the_form_refuses_it_as_a_bad_escape() -> None:
    # What a 1.1 codec did with "\=": an unknown escape, ERR 3 "bad escape" (docs/device-spec.md §2.5).
    (bad,) = LineReceiver().receive_data(b"#3 SET notes x\\=y\n")
    assert isinstance(bad, BadLine) and bad.code == Code.INVALID_ARGUMENT
    assert bad.message.startswith("bad escape")
    assert decode_line(b"GET frame") == Get("frame")

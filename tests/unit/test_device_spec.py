"""docs/device-spec.md: short enough to read in one sitting, its clauses the ones the kit checks,
its test vectors what the codec reads."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from gateway.conformance import CLAUSES
from services.kernel.errors import Code
from services.kernel.line_protocol import (
    ErrorReply,
    Event,
    Hello,
    LineProtocolError,
    Ok,
    Pong,
    crc8,
    decode_line,
)

SPEC = Path(__file__).resolve().parents[2] / "docs" / "device-spec.md"
#: The size a firmware author reads alone (Firmata's protocol document is 14.7 KB).
MOST_BYTES = 15_000


def spec_text() -> str:
    return SPEC.read_text(encoding="utf-8")


def vectors() -> list[tuple[str, str]]:
    """The (direction, line) pairs of the test-vector block (§10)."""
    section = spec_text().split("## 10. Test vectors", 1)[1].split("## 11.", 1)[0]
    block = section.split("```", 2)[1]
    return [(line[0], line[2:]) for line in block.splitlines() if line[:2] in ("> ", "< ")]


def test_the_specification_is_under_15_kilobytes() -> None:
    assert len(SPEC.read_bytes()) < MOST_BYTES


def test_every_clause_the_kit_checks_is_a_clause_of_the_specification() -> None:
    text = spec_text()
    numbered = set(re.findall(r"^\*\*(\d+\.\d+)\b", text, re.M)) | set(
        re.findall(r"^## (\d+)\. ", text, re.M)
    )
    reported = {clause.number for clause in CLAUSES} | {"4.1", "4.2"}
    assert reported <= numbered, reported - numbered


def test_the_specification_settles_twelve_points() -> None:
    points = spec_text().split("## 11. Points settled in 1.3", 1)[1]
    assert re.findall(r"^(\d+)\. ", points, re.M) == [str(n) for n in range(1, 13)]


#: Vector lines that are bad on purpose, and the code a device answers them with.
BAD_ON_PURPOSE = {
    "#123456789 PING": Code.INVALID_ARGUMENT,
    "HELLO foo": Code.INVALID_ARGUMENT,
    "#9 FROB x": Code.UNIMPLEMENTED,
    "$#2 PING b*00": Code.DATA_LOSS,
    "$ #4 PING*D3": Code.INVALID_ARGUMENT,
}


def test_every_test_vector_is_read_by_the_codec_as_the_specification_says() -> None:
    pairs = vectors()
    assert len(pairs) > 30
    for direction, line in pairs:
        raw = line.encode()
        if line in BAD_ON_PURPOSE:
            with pytest.raises(LineProtocolError) as info:
                decode_line(raw)
            assert info.value.code == BAD_ON_PURPOSE[line], line
            continue
        frame = decode_line(raw)  # a checksummed line whose CRC were wrong would raise here
        if direction == "<":
            assert isinstance(frame, Ok | ErrorReply | Pong | Hello | Event), line
    checked = [line for _, line in pairs if line.startswith("$") and line not in BAD_ON_PURPOSE]
    assert checked and all(int(line[-2:], 16) == crc8(line[1:-3].encode()) for line in checked)

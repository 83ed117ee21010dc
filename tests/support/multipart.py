"""A reader of the live image route's ``multipart/x-mixed-replace`` body, for tests: one part at a
time, each by its ``Content-Length``, every read with a deadline.

    async with session.get(stream_url) as response:
        parts = PartReader(response.content, boundary_of(response.headers["Content-Type"]))
        part = await parts.next()   # Part(headers, body); None once the closing boundary came
"""

from __future__ import annotations

import asyncio
import re
from dataclasses import dataclass
from typing import Protocol

from support.waiting import WAIT


class LineStream(Protocol):
    async def readline(self) -> bytes: ...

    async def readexactly(self, n: int) -> bytes: ...


@dataclass(frozen=True)
class Part:
    headers: dict[str, str]
    body: bytes

    @property
    def sequence(self) -> int:
        return int(self.headers["x-sequence"])

    @property
    def conflated(self) -> int:
        return int(self.headers["x-conflated"])


def boundary_of(content_type: str) -> str:
    match = re.search(r"boundary=\"?([^\";]+)", content_type)
    assert match, f"no boundary in {content_type!r}"
    return match.group(1)


class PartReader:
    def __init__(self, stream: LineStream, boundary: str) -> None:
        self.stream = stream
        self.dash = f"--{boundary}".encode()

    async def next(self, within: float = WAIT) -> Part | None:
        """The next part; None after the closing boundary; AssertionError for anything else."""
        async with asyncio.timeout(within):
            line = await self.stream.readline()
            while line in (b"\r\n", b"\n"):
                line = await self.stream.readline()
            line = line.rstrip(b"\r\n")
            if line == self.dash + b"--":
                return None
            assert line == self.dash, f"expected a boundary, got {line[:100]!r}"
            headers = {}
            while (header := (await self.stream.readline()).rstrip(b"\r\n")) != b"":
                name, _, value = header.decode("latin-1").partition(":")
                headers[name.strip().lower()] = value.strip()
            body = await self.stream.readexactly(int(headers["content-length"]))
            assert await self.stream.readexactly(2) == b"\r\n", "a part ends with CRLF"
            return Part(headers, body)

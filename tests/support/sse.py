"""A Server-Sent-Events reader for tests: messages of an ``aiohttp`` response, one at a time, bounded.

Each :class:`Message` is one event (``event``, ``id``, ``data`` parsed as JSON) or one comment
(``event == "comment"``, its text in ``comment``), as an EventSource would split the stream::

    async with session.get(url) as response:
        events = SseReader(response)
        first = await events.next()
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass
from typing import Any

import aiohttp

from support.waiting import WAIT


@dataclass(frozen=True)
class Message:
    event: str
    id: str | None = None
    data: Any = None
    comment: str = ""


class SseReader:
    """Reads one SSE response; every read has a deadline."""

    def __init__(self, response: aiohttp.ClientResponse) -> None:
        self.response = response

    async def next(self, within: float = WAIT) -> Message:
        """The next event or comment; TimeoutError after ``within`` s, AssertionError when the stream ends."""
        async with asyncio.timeout(within):
            return await self._read()

    async def _read(self) -> Message:
        event, ident, data = "message", None, []
        while True:
            raw = await self.response.content.readline()
            if not raw:
                raise AssertionError("the event stream ended")
            line = raw.decode().rstrip("\n").rstrip("\r")
            if line.startswith(":"):
                comment = line[1:].strip()
                # A comment followed by its blank line: an EventSource ignores it; tests see it.
                await self.response.content.readline()
                return Message("comment", comment=comment)
            if not line:
                if data:
                    return Message(event, ident, json.loads("\n".join(data)))
                continue
            field, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if field == "event":
                event = value
            elif field == "id":
                ident = value
            elif field == "data":
                data.append(value)

    async def until(self, event: str, within: float = WAIT) -> Message:
        """Skip messages up to the next ``event`` (comments included in what is skipped)."""
        async with asyncio.timeout(within):
            while True:
                message = await self._read()
                if message.event == event:
                    return message

    async def values_until_sync(self, within: float = WAIT) -> list[Message]:
        """The snapshot: every ``value`` event before ``sync`` (nothing else may come before it)."""
        values = []
        async with asyncio.timeout(within):
            while True:
                message = await self._read()
                if message.event == "sync":
                    return values
                assert message.event == "value", message
                values.append(message)

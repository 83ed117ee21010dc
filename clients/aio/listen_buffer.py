"""What a Session listen holds for its reader: the latest event per property, never a backlog."""

from __future__ import annotations

import asyncio
import dataclasses

from clients.aio.events import Event, Mark, listen_items
from clients.errors import PropertyServiceError
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.conflation import ConflatingQueue

__all__ = ["ListenBuffer"]


class ListenBuffer:
    """Events of one Session listen not yet taken by its reader, conflated per property (bounded).

    A slow reader gets the latest value of each property, with ``conflated``
    counting every value it missed (those the gateway already conflated
    included) and ``gap`` kept once set.
    """

    __slots__ = ("_marks", "_queue", "_wake", "done", "error")

    def __init__(self, marks: bool) -> None:
        self._marks = marks
        self._queue: ConflatingQueue[tuple[str, str] | Mark, Event | Mark] = ConflatingQueue()
        self._wake = asyncio.Event()
        #: The stream has ended (the reader still takes what waits).
        self.done = False
        #: Why it ended, when it failed.
        self.error: PropertyServiceError | None = None

    def add(self, resp: pb.ListenResponse) -> None:
        """Queue the events (and markers, if asked for) of one ListenResponse."""
        queue = self._queue
        for item in listen_items(resp, self._marks):
            if isinstance(item, Mark):
                queue.put(item, item)
                continue
            key = (item.service, item.property)
            waiting = queue.get(key)
            if waiting is not None and isinstance(waiting.value, Event):
                # The gateway's count for the replaced event carries over; the queue counts the replacement.
                item = dataclasses.replace(item, conflated=item.conflated + waiting.value.conflated)  # noqa: PLW2901
            queue.put(key, item, gap=item.gap)
        self._wake.set()

    def finish(self, error: PropertyServiceError | None) -> None:
        """The stream has ended, with ``error`` when it failed."""
        self.done = True
        self.error = error
        self._wake.set()

    async def next(self) -> Event | Mark | None:
        """The oldest waiting item, once there is one; None when the stream has ended and all is taken."""
        while not self._queue and not self.done:
            self._wake.clear()
            await self._wake.wait()
        taken = self._queue.take(1)
        if not taken:
            return None
        slot = taken[0][1]
        item = slot.value
        if isinstance(item, Event) and (slot.conflated or slot.gap != item.gap):
            item = dataclasses.replace(item, conflated=item.conflated + slot.conflated, gap=slot.gap)
        return item

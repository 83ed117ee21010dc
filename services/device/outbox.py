"""What one device-side connection still has to write."""

from __future__ import annotations

import asyncio
from collections import deque

from services.kernel.conflation import ConflatingQueue
from services.kernel.line_protocol import Event, Gone

__all__ = ["Outbox"]


class Outbox:
    """Replies in order, events conflated per path: a slow reader costs one slot per listened path.

    ``wake`` is set while something waits to be written; ``room`` is set by
    :meth:`take` (the writer took the replies), so that a reader held back by
    too many queued replies may go on.
    """

    def __init__(self) -> None:
        self.replies: deque[bytes] = deque()
        #: Bytes of the replies waiting: a binary value makes one reply line as long as 8 MiB.
        self.reply_bytes = 0
        self.events: ConflatingQueue[str, Event | Gone] = ConflatingQueue()
        self.wake = asyncio.Event()
        self.room = asyncio.Event()

    def reply(self, line: bytes) -> None:
        """Queue an encoded reply line; replies are never conflated."""
        self.replies.append(line)
        self.reply_bytes += len(line)
        self.wake.set()

    def event(self, frame: Event | Gone) -> None:
        """Queue an event for its path, replacing one that still waits there."""
        self.events.put(frame.path, frame, removed=isinstance(frame, Gone))
        self.wake.set()

    def take(self) -> tuple[list[bytes], list[Event | Gone]]:
        """Everything waiting: the replies, then one event per path (paths in the order they first waited)."""
        replies = list(self.replies)
        self.replies.clear()
        self.reply_bytes = 0
        events = [slot.value for _, slot in self.events.take()]
        self.wake.clear()
        self.room.set()
        return replies, events

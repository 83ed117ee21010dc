"""Reads a Listen stream of the listen hub without gRPC, as a front end's writer would."""

from __future__ import annotations

import asyncio

from gateway.engine.events import Mark, events
from gateway.engine.listen import ListenHub, ListenStream, Selector, StreamOptions
from support.waiting import wait_until

#: (service, property, value, gap) of one event.
Seen = tuple[str, str, str, bool]


class Reader:
    """Opens a stream on the hub and collects what it sends, as a front end's writer would."""

    def __init__(self, hub: ListenHub, *selectors: Selector, options: StreamOptions | None = None) -> None:
        self.events: list[Seen] = []
        #: (service, property) of each event that says a property is gone.
        self.removed: list[tuple[str, str]] = []
        self.synced = False
        self.stream: ListenStream = hub.open(list(selectors), options or StreamOptions(), self._ready)

    def _ready(self) -> None:
        asyncio.get_running_loop().call_soon(self._drain)

    def _drain(self) -> None:
        while (taken := self.stream.take()) is not None:
            if isinstance(taken, Mark):
                self.synced = self.synced or taken is Mark.SYNC
                continue
            heard = events(taken)
            self.events += [(e.service, e.path, e.value, e.gap) for e in heard]
            self.removed += [(e.service, e.path) for e in heard if e.removed]

    async def start(self) -> None:
        await self.stream.start()
        await wait_until(lambda: self.synced, what="the stream's sync marker")

    async def until(self, event: Seen) -> None:
        await wait_until(lambda: event in self.events, what=f"event {event}")

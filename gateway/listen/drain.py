"""How a front end writes one Listen stream: wait until it is ready, take what it has, repeat.

Every front end's Listen drains its :class:`~gateway.listen.stream.ListenStream` through
:func:`taken`: the gRPC Listen handler (encoding each batch, :mod:`gateway.fronts.grpc_v1.listen_encoding`),
the HTTP front end's event and image streams. (A Listen inside a gRPC Session is the exception:
the Session's writer takes from all its Listens at once, when each says it is ready.) A writer
that waits on its client (a slow reader) is simply not taking: the stream's conflating queue
holds the latest value per property meanwhile, so memory stays bounded by the properties it
matches.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncGenerator

from gateway.engine.events import Taken
from gateway.listen.stream import ListenStream


class Wake:
    """A one-waiter asyncio.Event without the waiter deque: idle Listen streams stay small.

    Hand :meth:`set` to :meth:`gateway.listen.ListenHub.open` as ``on_ready``.
    """

    __slots__ = ("_future", "_set")

    def __init__(self) -> None:
        self._set = False
        self._future: asyncio.Future[None] | None = None

    def set(self) -> None:
        future = self._future
        if future is None or future.done():  # no waiter (or one cancelled): the next wait returns at once
            self._set = True
            self._future = None
        else:  # the waiter wakes, and its wake is spent
            self._future = None
            future.set_result(None)

    def waiter(self) -> asyncio.Future[None] | None:
        """What to await before the next round: a future :meth:`set` completes, or None when it
        was set already (and is cleared now).

        :meth:`wait` without a coroutine of its own, for a writer woken once a message.
        """
        if self._set:
            self._set = False
            return None
        future = self._future = asyncio.get_running_loop().create_future()
        return future

    async def wait(self) -> None:
        future = self.waiter()
        if future is not None:
            await future


async def taken(stream: ListenStream, wake: Wake) -> AsyncGenerator[Taken, None]:
    """Start ``stream`` and yield what it has ready (:meth:`ListenStream.take`), as it
    becomes ready.

    ``wake`` is the one the stream was opened with. Raises the stream's error (a
    ``PropertyError``: the start failed, a limit was passed, the gateway is shutting down);
    returns when the stream is ended or closed. The caller closes the stream. The events carry
    the values every stream shares: a writer that waits on its client holds a reference to one,
    never a copy.
    """
    await stream.start()
    while True:
        waiter = wake.waiter()  # awaited here, not in Wake.wait: a coroutine less a message
        if waiter is not None:
            await waiter
        while (item := stream.take()) is not None:
            yield item
        if stream.error is not None:
            raise stream.error
        if stream.ended or stream.closed:
            return

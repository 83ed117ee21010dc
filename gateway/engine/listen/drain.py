"""How a front end writes one Listen stream: wait until it is ready, take what it has, repeat.

Every front end's Listen drains its :class:`~gateway.engine.listen.stream.ListenStream` by one loop,
:func:`steps`: the gRPC Listen handler (encoding each batch,
:mod:`gateway.fronts.grpc_v1.listen_encoding`) runs it itself, the HTTP front end's event and
image streams through :func:`taken`. (A Listen inside a gRPC Session is the exception: the
Session's writer takes from all its Listens at once, when each says it is ready.) A writer
that waits on its client (a slow reader) is simply not taking: the stream's conflating queue
holds the latest value per property meanwhile, so memory stays bounded by the properties it
matches.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncGenerator, Iterator

from gateway.engine.events import Event, Mark, Taken, events
from gateway.engine.listen.stream import ListenStream


class Wake:
    """A one-waiter asyncio.Event without the waiter deque: idle Listen streams stay small.

    Hand :meth:`set` to :meth:`gateway.engine.listen.ListenHub.open` as ``on_ready``.
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


def steps(stream: ListenStream, wake: Wake) -> Iterator[Taken | asyncio.Future[None]]:
    """The writer's loop over a started ``stream``: what it has ready (:meth:`ListenStream.take`)
    as it becomes ready, and in between the future to await until it is (then ask for the next
    step).

    ``wake`` is the one the stream was opened with. Raises the stream's error (a
    ``PropertyError``: a limit was passed, the gateway is shutting down); ends when the stream is
    ended or closed. The caller closes the stream. The events carry the values every stream
    shares: a writer that waits on its client holds a reference to one, never a copy.

    A plain generator, which the writer's own coroutine steps and whose futures it awaits
    itself: an async generator in between would cost every message a step of its own. What it
    yields it does not keep (``yield from``: no local holds it while the writer writes), so a
    writer that waits on its client holds only what it keeps itself.
    """
    while True:
        ready: Iterator[Taken] = iter(stream.take, None)
        yield from ready
        if stream.error is not None:
            raise stream.error
        if stream.ended or stream.closed:
            return
        waiter = wake.waiter()
        if waiter is not None:
            yield waiter


async def taken(stream: ListenStream, wake: Wake) -> AsyncGenerator[list[Event] | Mark, None]:
    """Start ``stream`` and yield what it has ready as plain events, or a marker, as it becomes
    ready (:func:`steps`). An event holds the value every stream shares, not a copy."""
    await stream.start()
    for step in steps(stream, wake):
        if isinstance(step, asyncio.Future):
            await step
            continue
        item = step if isinstance(step, Mark) else events(step)
        del step  # the batch and its shared events: only the plain events are held while written
        yield item

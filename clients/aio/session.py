"""The multiplexed :class:`Session`: many Get, Set and Listen calls over one bidirectional stream."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from collections.abc import AsyncGenerator, Iterable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol, Self

import grpc
from grpc.aio import EOF  # type: ignore[attr-defined]  # missing from grpc-stubs

from clients.aio.events import Event, Mark
from clients.aio.listen import ListenCalls
from clients.aio.listen_buffer import ListenBuffer
from clients.aio.requests import (
    Selector,
    format_params,
    get_many_request,
    get_many_values,
    matching_values,
    set_request,
    value_of,
)
from clients.errors import (
    Cancelled,
    PropertyServiceError,
    Unavailable,
    Unknown,
    error_for_code,
    error_from_rpc,
)
from clients.values import Value
from protos.propertyservice.v1 import property_service_pb2 as pb

__all__ = ["DEFAULT_SESSION_QUEUE", "MAX_SESSION_BATCH", "Session"]

#: Requests a Session holds before callers wait (back-pressure instead of unbounded memory).
DEFAULT_SESSION_QUEUE = 1024
#: Most requests put into one SessionRequest.
MAX_SESSION_BATCH = 256
#: Seconds a Session writer that could not send waits for the reader to report why the call ended.
_READER_GRACE = 1.0


class Channel(Protocol):
    """What a Session needs of its client (an :class:`~clients.aio.AsyncClient`)."""

    target: str
    timeout: float | None
    metadata: tuple[tuple[str, str], ...] | None

    def stub(self) -> Any: ...

    def gateway_failed(self, target: str, why: str, *, say: bool = True) -> None: ...


@dataclass(slots=True)
class _Pending:
    future: asyncio.Future[pb.Reply]
    service: str
    property: str
    timer: asyncio.TimerHandle | None = None


def _again(error: PropertyServiceError, service: str = "", prop: str = "") -> PropertyServiceError:
    """A fresh error of the same class (GatewayUnreachable stays GatewayUnreachable) for another call."""
    return type(error)(error.code, error.message, service, prop)


class Session(ListenCalls[AsyncGenerator[Event, None], AsyncGenerator[Event | Mark, None]]):
    """Many Get, Set and Listen calls multiplexed over one bidirectional ``Session`` stream.

    Requests issued in the same event-loop iteration travel in one
    SessionRequest; each carries a client-chosen id and its reply resolves
    the matching future. A failed request raises its own error; the session
    lives on. At most ``max_pending`` requests wait to be written (callers
    then wait), and every Get/Set is bounded by the client's timeout. A slow
    Listen reader gets the latest value per property with ``conflated``
    counting the values it missed.
    """

    def __init__(
        self,
        client: Channel,
        *,
        max_pending: int = DEFAULT_SESSION_QUEUE,
        carries_resumed_listens: bool = False,
    ) -> None:
        """``carries_resumed_listens``: the Session a client's listens share, whose listens each
        log their own move to the next gateway (so the Session's end logs none)."""
        self._client = client
        self._carries_resumed_listens = carries_resumed_listens
        self._timeout = client.timeout
        self._queue: asyncio.Queue[pb.Request] = asyncio.Queue(max_pending)
        self._ids = itertools.count(1)
        self._pending: dict[int, _Pending] = {}
        self._listens: dict[int, ListenBuffer] = {}
        self._call: Any = None
        self._tasks: list[asyncio.Task[None]] = []
        self._closed: PropertyServiceError | None = None
        #: The gateway address the stream went to (the client may move on to another later).
        self.target = client.target

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()

    async def open(self) -> None:
        """Open the stream (done by ``async with``)."""
        if self._call is not None:
            return
        self.target = self._client.target
        self._call = self._client.stub().Session(metadata=self._client.metadata)
        self._tasks = [asyncio.create_task(self._read()), asyncio.create_task(self._write())]

    async def aclose(self) -> None:
        """End the stream; pending calls raise :class:`Cancelled`. Idempotent."""
        self._shutdown(Cancelled(None, "the session is closed"))
        if self._call is not None:
            self._call.cancel()
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    @property
    def closed(self) -> bool:
        """True once the stream has ended (closed or failed)."""
        return self._closed is not None

    def _shutdown(self, error: PropertyServiceError) -> None:
        if self._closed is not None:
            return
        self._closed = error
        for p in self._pending.values():
            if not p.future.done():
                p.future.set_exception(_again(error, p.service, p.property))
        for buffer in self._listens.values():
            buffer.finish(error)
        # Wake callers blocked on a full queue; their futures have failed above.
        while not self._queue.empty():
            self._queue.get_nowait()

    async def _read(self) -> None:
        error: PropertyServiceError = Cancelled(None, "the session is closed")
        try:
            while True:
                resp = await self._call.read()
                if resp is EOF:
                    error = Unavailable(None, "the gateway ended the session")
                    break
                for reply in resp.replies:
                    self._dispatch(reply)
        except grpc.RpcError as e:
            error = error_from_rpc(e, target=self.target)
        except asyncio.CancelledError:
            pass
        finally:
            if isinstance(error, Unavailable):
                # The stream's gateway went away (or shut down): the client's next stream or
                # call goes to its next gateway, when it has several.
                self._client.gateway_failed(self.target, error.message, say=not self._carries_resumed_listens)
            self._shutdown(error)

    def _dispatch(self, reply: pb.Reply) -> None:
        buffer = self._listens.get(reply.id)
        if buffer is not None:
            if reply.HasField("listen"):
                buffer.add(reply.listen)
            if reply.status.code:
                buffer.finish(error_for_code(reply.status.code, reply.status.message))
            elif not reply.HasField("listen"):
                buffer.finish(None)
            return
        p = self._pending.get(reply.id)
        if p is not None and not p.future.done():
            p.future.set_result(reply)

    async def _write(self) -> None:
        queue = self._queue
        try:
            while True:
                batch = [await queue.get()]
                while not queue.empty() and len(batch) < MAX_SESSION_BATCH:
                    batch.append(queue.get_nowait())
                await self._call.write(pb.SessionRequest(requests=batch))
        except grpc.RpcError as e:
            self._shutdown(error_from_rpc(e, target=self.target))
        except asyncio.CancelledError:
            pass
        except Exception as e:
            # The call finished under us (e.g. no connection): the reader reports the reason,
            # which says more than this writer can; wait for it (bounded), then fall back.
            reader = [t for t in self._tasks if t is not asyncio.current_task()]
            if reader:
                await asyncio.wait(reader, timeout=_READER_GRACE)
            self._shutdown(Unknown(None, f"the session could not send: {e}"))

    def _check_open(self) -> None:
        if self._closed is not None:
            raise _again(self._closed)
        if self._call is None:
            raise Cancelled(None, "the session is not open: use 'async with client.session() as s'")

    async def _enqueue(self, request: pb.Request, done: asyncio.Future[Any] | None) -> None:
        try:
            self._queue.put_nowait(request)
            return
        except asyncio.QueueFull:
            pass
        put = asyncio.ensure_future(self._queue.put(request))
        if done is None:
            await put
            return
        await asyncio.wait((put, done), return_when=asyncio.FIRST_COMPLETED)
        if not put.done():
            put.cancel()

    async def _call_one(self, request: pb.Request, service: str, prop: str) -> pb.Reply:
        self._check_open()
        rid = request.id = next(self._ids)
        loop = asyncio.get_running_loop()
        future: asyncio.Future[pb.Reply] = loop.create_future()
        pending = _Pending(future, service, prop)
        if self._timeout is not None:
            pending.timer = loop.call_later(self._timeout, self._expire, rid)
        self._pending[rid] = pending
        try:
            await self._enqueue(request, future)
            reply = await future
        finally:
            del self._pending[rid]
            if pending.timer is not None:
                pending.timer.cancel()
        if reply.status.code:
            raise error_for_code(reply.status.code, reply.status.message, service, prop)
        return reply

    def _expire(self, rid: int) -> None:
        p = self._pending.get(rid)
        if p is not None and not p.future.done():
            p.future.set_exception(
                error_for_code(
                    grpc.StatusCode.DEADLINE_EXCEEDED,
                    f"no reply within {self._timeout} s",
                    p.service,
                    p.property,
                )
            )

    async def get(self, service: str, prop: str, /, **params: Any) -> Value:
        """Like :meth:`AsyncClient.get`, over the session."""
        request = pb.Request(
            get=pb.GetRequest(service=service, property=prop, parameters=format_params(params))
        )
        reply = await self._call_one(request, service, prop)
        return value_of(reply.get)

    async def get_matching(self, service: str, pattern: str, /, **params: Any) -> dict[str, Value]:
        """Like :meth:`AsyncClient.get_matching`, over the session."""
        request = pb.GetRequest(service=service, property=pattern, parameters=format_params(params))
        reply = await self._call_one(pb.Request(get=request), service, pattern)
        return matching_values(reply.get)

    async def get_many(self, refs: Iterable[Selector]) -> list[Value]:
        """Like :meth:`AsyncClient.get_many`, over the session."""
        refs = list(refs)
        if not refs:
            return []
        reply = await self._call_one(pb.Request(get=get_many_request(refs)), "", "")
        return get_many_values(reply.get, len(refs))

    async def set(self, service: str, prop: str, value: Any, /, **params: Any) -> Value:
        """Like :meth:`AsyncClient.set`, over the session."""
        request = pb.Request(set=set_request(service, prop, value, params))
        reply = await self._call_one(request, service, prop)
        return value_of(reply.set)

    async def start_listen(
        self, request: pb.ListenRequest, marks: bool, resume: bool = False
    ) -> AsyncGenerator[Event | Mark, None]:
        """The Listen for ``request`` over the session; closing the iterator sends a Cancel."""
        if resume:
            # A session ends with its gateway; resuming is opening a new session, the caller's choice.
            raise ValueError("resume=True is for a client's listen; a session's listens end with the session")
        self._check_open()
        rid = next(self._ids)
        buffer = ListenBuffer(marks)
        self._listens[rid] = buffer
        try:
            await self._enqueue(pb.Request(id=rid, listen=request), None)
            while (item := await buffer.next()) is not None:
                yield item
            if buffer.error is not None:
                raise _again(buffer.error, request.service, request.property)
        finally:
            del self._listens[rid]
            if not buffer.done and self._closed is None:
                cancel = pb.Request(id=next(self._ids), cancel=pb.Cancel(id=rid))
                # Best effort when the queue is full: replies to an unknown id are dropped anyway.
                with contextlib.suppress(asyncio.QueueFull):
                    self._queue.put_nowait(cancel)

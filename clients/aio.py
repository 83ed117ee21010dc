"""The asyncio client: :class:`AsyncClient` and its multiplexed :class:`Session`.

Unary calls (Get, Set) and server-streamed Listen go over ``grpc.aio``; a
:class:`Session` multiplexes many calls over the bidirectional ``Session`` RPC,
which is the fast path for programs making many small calls.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import enum
import itertools
from collections.abc import AsyncGenerator, Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from types import TracebackType
from typing import Any, Literal, Self, overload

import grpc
import grpc.aio
from google.protobuf.duration_pb2 import Duration
from grpc.aio import EOF  # type: ignore[attr-defined]  # missing from grpc-stubs

from clients.errors import (
    Cancelled,
    DeadlineExceeded,
    PropertyServiceError,
    Unavailable,
    Unknown,
    error_for_code,
    error_from_rpc,
)
from clients.values import (
    Marker,
    ValueFormatError,
    Vector,
    format_value,
    parse_marker,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

__all__ = [
    "DEFAULT_MAX_IN_FLIGHT",
    "DEFAULT_TARGET",
    "DEFAULT_TIMEOUT",
    "HEARTBEAT",
    "SYNC",
    "AsyncClient",
    "Event",
    "Mark",
    "Selector",
    "Session",
]

DEFAULT_TARGET = "127.0.0.1:50051"
#: Seconds a unary call (or a request inside a Session) may take.
DEFAULT_TIMEOUT = 10.0
#: Unary calls (Get, Set) one AsyncClient has in flight at once; more callers wait their turn.
#: grpc.aio answers part of a burst of more than about a thousand simultaneous unary calls on one
#: channel with CANCELLED, so the client never starts that many.
DEFAULT_MAX_IN_FLIGHT = 256
#: Requests a Session holds before callers wait (back-pressure instead of unbounded memory).
DEFAULT_SESSION_QUEUE = 1024
#: Most requests put into one SessionRequest.
MAX_SESSION_BATCH = 256
#: Seconds a Session writer that could not send waits for the reader to report why the call ended.
_READER_GRACE = 1.0

#: A Listen selector: ``(service, property)`` or ``(service, property, parameters)``.
Selector = tuple[str, str] | tuple[str, str, Mapping[str, Any]]


@dataclass(frozen=True, slots=True)
class Event:
    """One value of one property, as delivered by a Listen."""

    service: str
    property: str
    value: str
    #: Per-stream sequence number, from 1, without holes.
    sequence: int
    #: When the gateway saw the change (timezone-aware, UTC).
    time: datetime
    #: How many earlier values were replaced by this one (slow reader or throttle).
    conflated: int = 0
    #: Values may have been lost before this one; ``value`` is the current value.
    gap: bool = False
    #: The property no longer exists; ``value`` is empty.
    removed: bool = False


class Mark(enum.Enum):
    """Stream markers a Listen yields when asked with ``marks=True``."""

    #: The current values have all been sent; what follows are changes.
    SYNC = "sync"
    #: Keep-alive: nothing changed for the heartbeat interval.
    HEARTBEAT = "heartbeat"


SYNC = Mark.SYNC
HEARTBEAT = Mark.HEARTBEAT


def _params(params: Mapping[str, Any]) -> dict[str, str]:
    return {name: format_value(value) for name, value in params.items()}


def _duration(seconds: float | None, what: str) -> Duration | None:
    if seconds is None:
        return None
    if seconds < 0:
        raise ValueError(f"{what} must not be negative, got {seconds}")
    d = Duration()
    d.FromNanoseconds(round(seconds * 1e9))
    return d


def _ref(selector: Selector) -> pb.PropertyRef:
    if len(selector) == 3:
        service, prop, params = selector
        return pb.PropertyRef(service=service, property=prop, parameters=_params(params))
    service, prop = selector[0], selector[1]
    return pb.PropertyRef(service=service, property=prop)


def _listen_request(
    service: str,
    prop: str,
    more: Sequence[Selector],
    *,
    params: Mapping[str, Any] | None,
    updates_only: bool,
    min_interval: float | None,
    sample_interval: float | None,
    heartbeat: float | None,
    max_batch: int,
) -> pb.ListenRequest:
    options = pb.ListenOptions(
        updates_only=updates_only,
        min_interval=_duration(min_interval, "min_interval"),
        sample_interval=_duration(sample_interval, "sample_interval"),
        heartbeat_interval=_duration(heartbeat, "heartbeat"),
        max_batch=max_batch,
    )
    return pb.ListenRequest(
        service=service,
        property=prop,
        parameters=_params(params or {}),
        more=[_ref(s) for s in more],
        options=options,
    )


def _event(ev: pb.Event) -> Event:
    return Event(
        ev.service,
        ev.property,
        ev.value,
        ev.sequence,
        ev.time.ToDatetime(tzinfo=UTC),
        ev.conflated,
        ev.gap,
        ev.removed,
    )


def _items(resp: pb.ListenResponse, marks: bool) -> list[Event | Mark]:
    items: list[Event | Mark] = [_event(ev) for ev in resp.events]
    if marks:
        if resp.sync:
            items.append(SYNC)
        if resp.heartbeat:
            items.append(HEARTBEAT)
    return items


def _decode(parse: Any, text: str, service: str, prop: str) -> Any:
    try:
        return parse(text)
    except ValueFormatError as e:
        raise ValueFormatError(f"{service} {prop}: {e}") from None


def _get_many_request(refs: Sequence[Selector]) -> pb.GetRequest:
    first = _ref(refs[0])
    more = [_ref(r) for r in refs[1:]]
    return pb.GetRequest(
        service=first.service, property=first.property, parameters=first.parameters, more=more
    )


def _get_many_values(resp: pb.GetResponse, n: int) -> list[str]:
    if len(resp.more) != n - 1:
        raise Unknown(None, f"the gateway answered {len(resp.more) + 1} values for {n} paths")
    return [resp.value, *(v.value for v in resp.more)]


class AsyncClient:
    """Asyncio client of a Property Service gateway.

    Use as ``async with AsyncClient("127.0.0.1:50051") as c: await c.get("scout1", "location")``.
    Every unary call is bounded by ``timeout`` seconds (None: no limit);
    ``metadata`` (e.g. ``[("authorization", "Bearer ...")]``) goes with every call.
    At most ``max_in_flight`` unary calls run at once; further callers queue
    in the client, first come first served, and their waiting counts towards
    their ``timeout``. For many calls, :meth:`session` is the faster path.
    Failures raise :class:`clients.errors.PropertyServiceError` subclasses.
    """

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        metadata: Iterable[tuple[str, str]] | None = None,
        options: Sequence[tuple[str, Any]] | None = None,
        max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
    ) -> None:
        if isinstance(max_in_flight, bool) or not isinstance(max_in_flight, int) or max_in_flight < 1:
            raise ValueError(f"max_in_flight must be a whole number of at least 1, got {max_in_flight!r}")
        self.target = target
        self.timeout = timeout
        self.metadata: tuple[tuple[str, str], ...] | None = tuple(metadata) if metadata else None
        self.max_in_flight = max_in_flight
        self._options = list(options or [])
        self._channel: grpc.aio.Channel | None = None
        self._stub: Any = None
        self._slots = asyncio.Semaphore(max_in_flight)

    # The channel (and the call slots) are made on first use, so that they bind to the running loop.
    def _get_stub(self) -> Any:
        if self._stub is None:
            self._channel = grpc.aio.insecure_channel(self.target, options=self._options)
            self._stub = pb_grpc.PropertyServiceStub(self._channel)
            self._slots = asyncio.Semaphore(self.max_in_flight)
        return self._stub

    async def __aenter__(self) -> Self:
        self._get_stub()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Close the channel; ongoing calls are cancelled. Idempotent."""
        channel, self._channel, self._stub = self._channel, None, None
        if channel is not None:
            await channel.close(None)

    def _error(self, err: grpc.RpcError, service: str = "", prop: str = "") -> PropertyServiceError:
        return error_from_rpc(err, service, prop, self.target)

    async def _unary(self, method: str, request: Any, service: str = "", prop: str = "") -> Any:
        """One Get or Set, in a call slot; the wait for the slot counts towards the timeout."""
        stub = self._get_stub()
        slots = self._slots
        timeout = self.timeout
        if slots.locked():
            timeout = await self._wait_for_slot(slots, service, prop)
        else:
            await slots.acquire()  # a free slot: taken at once, no timer needed
        try:
            return await getattr(stub, method)(request, timeout=timeout, metadata=self.metadata)
        except grpc.RpcError as e:
            raise self._error(e, service, prop) from None
        finally:
            slots.release()

    async def _wait_for_slot(self, slots: asyncio.Semaphore, service: str, prop: str) -> float | None:
        """Wait for a call slot within the timeout; return the time left for the call itself."""
        loop = asyncio.get_running_loop()
        start = loop.time()
        try:
            async with asyncio.timeout(self.timeout):
                await slots.acquire()
        except TimeoutError:
            raise DeadlineExceeded(
                None,
                f"no call slot free within {self.timeout} s: {self.max_in_flight} calls of this client "
                "are in flight (raise max_in_flight, or use client.session() for many calls)",
                service,
                prop,
            ) from None
        return None if self.timeout is None else max(self.timeout - (loop.time() - start), 1e-3)

    async def get(self, service: str, prop: str, /, **params: Any) -> str:
        """The value of ``prop`` of ``service`` as text; keyword arguments are request parameters."""
        request = pb.GetRequest(service=service, property=prop, parameters=_params(params))
        resp = await self._unary("Get", request, service, prop)
        value: str = resp.value
        return value

    async def get_many(self, refs: Iterable[Selector]) -> list[str]:
        """Values of several ``(service, property[, params])`` in one call, in order; all or nothing."""
        refs = list(refs)
        if not refs:
            return []
        resp = await self._unary("Get", _get_many_request(refs))
        return _get_many_values(resp, len(refs))

    async def set(self, service: str, prop: str, value: Any, /, **params: Any) -> str:
        """Write ``value`` (text, number, bool, vector, list, :class:`Marker`); return the answer."""
        request = pb.SetRequest(
            service=service, property=prop, value=format_value(value), parameters=_params(params)
        )
        resp = await self._unary("Set", request, service, prop)
        answer: str = resp.value
        return answer

    async def get_number(self, service: str, prop: str, /, **params: Any) -> float:
        """The value as a float."""
        result: float = _decode(parse_number, await self.get(service, prop, **params), service, prop)
        return result

    async def get_vector(self, service: str, prop: str, /, **params: Any) -> Vector:
        """The value ``(1 2 3)`` as a 1-D numpy array."""
        result: Vector = _decode(parse_vector, await self.get(service, prop, **params), service, prop)
        return result

    async def get_vectors(self, service: str, prop: str, /, **params: Any) -> list[Vector]:
        """The value ``((1 2) (3 4))`` as a list of 1-D numpy arrays."""
        result: list[Vector] = _decode(parse_vectors, await self.get(service, prop, **params), service, prop)
        return result

    async def get_names(self, service: str, prop: str, /, **params: Any) -> list[str]:
        """The value ``(a b c)`` as a list of names."""
        result: list[str] = _decode(parse_names, await self.get(service, prop, **params), service, prop)
        return result

    async def get_marker(self, service: str, prop: str, /, **params: Any) -> Marker:
        """The value as a :class:`Marker`."""
        result: Marker = _decode(parse_marker, await self.get(service, prop, **params), service, prop)
        return result

    async def services(self) -> list[str]:
        """Names of the services the gateway's registry knows."""
        return await self.get_names("registry", "services")

    async def properties(self, service: str) -> list[str]:
        """The properties ``service`` offers right now."""
        return await self.get_names(service, "properties")

    @overload
    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        params: Mapping[str, Any] | None = ...,
        updates_only: bool = ...,
        min_interval: float | None = ...,
        sample_interval: float | None = ...,
        heartbeat: float | None = ...,
        max_batch: int = ...,
        marks: Literal[False] = ...,
    ) -> AsyncGenerator[Event, None]: ...

    @overload
    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        params: Mapping[str, Any] | None = ...,
        updates_only: bool = ...,
        min_interval: float | None = ...,
        sample_interval: float | None = ...,
        heartbeat: float | None = ...,
        max_batch: int = ...,
        marks: Literal[True],
    ) -> AsyncGenerator[Event | Mark, None]: ...

    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        params: Mapping[str, Any] | None = None,
        updates_only: bool = False,
        min_interval: float | None = None,
        sample_interval: float | None = None,
        heartbeat: float | None = None,
        max_batch: int = 0,
        marks: bool = False,
    ) -> AsyncGenerator[Event, None] | AsyncGenerator[Event | Mark, None]:
        """Stream events of ``(service, prop)`` and of the further ``(service, property)`` selectors.

        ``*`` in a selector matches one path segment (or every service).
        The current values come first (unless ``updates_only``), then changes.
        ``min_interval`` throttles each property (seconds; values in between
        are conflated), ``sample_interval`` sends every value periodically,
        ``heartbeat`` asks for keep-alives. With ``marks=True`` the iterator
        also yields :data:`SYNC` after the current values and :data:`HEARTBEAT`
        for each keep-alive. Close the iterator (``aclose()`` or leaving
        ``async for``) to end the stream.
        """
        request = _listen_request(
            service,
            prop,
            more,
            params=params,
            updates_only=updates_only,
            min_interval=min_interval,
            sample_interval=sample_interval,
            heartbeat=heartbeat,
            max_batch=max_batch,
        )
        return self._listen(request, marks)

    async def _listen(self, request: pb.ListenRequest, marks: bool) -> AsyncGenerator[Any, None]:
        call = self._get_stub().Listen(request, metadata=self.metadata)
        try:
            async for resp in call:
                for item in _items(resp, marks):
                    yield item
        except grpc.RpcError as e:
            raise self._error(e, request.service, request.property) from None
        finally:
            call.cancel()

    def session(self, *, max_pending: int = DEFAULT_SESSION_QUEUE) -> Session:
        """A :class:`Session` over this client's channel: ``async with client.session() as s: ...``."""
        return Session(self, max_pending=max_pending)


@dataclass(slots=True)
class _Pending:
    future: asyncio.Future[pb.Reply]
    service: str
    property: str
    timer: asyncio.TimerHandle | None = None


class _ListenState:
    """Events of one Session listen not yet taken by its reader, conflated per property (bounded)."""

    __slots__ = ("done", "error", "items", "marks", "wake")

    def __init__(self, marks: bool) -> None:
        self.items: dict[tuple[str, str] | Mark, Event | Mark] = {}
        self.marks = marks
        self.wake = asyncio.Event()
        self.done = False
        self.error: PropertyServiceError | None = None

    def add(self, resp: pb.ListenResponse) -> None:
        for new in _items(resp, self.marks):
            key: tuple[str, str] | Mark = new if isinstance(new, Mark) else (new.service, new.property)
            old = self.items.pop(key, None)
            if isinstance(old, Event) and isinstance(new, Event):
                new = dataclasses.replace(  # noqa: PLW2901 - the conflated event replaces the new one
                    new, conflated=new.conflated + old.conflated + 1, gap=new.gap or old.gap
                )
            self.items[key] = new
        self.wake.set()

    def finish(self, error: PropertyServiceError | None) -> None:
        self.done = True
        self.error = error
        self.wake.set()


def _again(error: PropertyServiceError, service: str = "", prop: str = "") -> PropertyServiceError:
    """A fresh error of the same class (GatewayUnreachable stays GatewayUnreachable) for another call."""
    return type(error)(error.code, error.message, service, prop)


class Session:
    """Many Get, Set and Listen calls multiplexed over one bidirectional ``Session`` stream.

    Requests issued in the same event-loop iteration travel in one
    SessionRequest; each carries a client-chosen id and its reply resolves
    the matching future. A failed request raises its own error; the session
    lives on. At most ``max_pending`` requests wait to be written (callers
    then wait), and every Get/Set is bounded by the client's timeout. A slow
    Listen reader gets the latest value per property with ``conflated``
    counting the values it missed.
    """

    def __init__(self, client: AsyncClient, *, max_pending: int = DEFAULT_SESSION_QUEUE) -> None:
        self._client = client
        self._timeout = client.timeout
        self._queue: asyncio.Queue[pb.Request] = asyncio.Queue(max_pending)
        self._ids = itertools.count(1)
        self._pending: dict[int, _Pending] = {}
        self._listens: dict[int, _ListenState] = {}
        self._call: Any = None
        self._tasks: list[asyncio.Task[None]] = []
        self._closed: PropertyServiceError | None = None

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
        self._call = self._client._get_stub().Session(metadata=self._client.metadata)
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
        for state in self._listens.values():
            state.finish(error)
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
            error = error_from_rpc(e, target=self._client.target)
        except asyncio.CancelledError:
            pass
        finally:
            self._shutdown(error)

    def _dispatch(self, reply: pb.Reply) -> None:
        state = self._listens.get(reply.id)
        if state is not None:
            if reply.HasField("listen"):
                state.add(reply.listen)
            if reply.status.code:
                state.finish(error_for_code(reply.status.code, reply.status.message))
            elif not reply.HasField("listen"):
                state.finish(None)
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
            self._shutdown(error_from_rpc(e, target=self._client.target))
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

    async def get(self, service: str, prop: str, /, **params: Any) -> str:
        """Like :meth:`AsyncClient.get`, over the session."""
        request = pb.Request(get=pb.GetRequest(service=service, property=prop, parameters=_params(params)))
        reply = await self._call_one(request, service, prop)
        value: str = reply.get.value
        return value

    async def get_many(self, refs: Iterable[Selector]) -> list[str]:
        """Like :meth:`AsyncClient.get_many`, over the session."""
        refs = list(refs)
        if not refs:
            return []
        reply = await self._call_one(pb.Request(get=_get_many_request(refs)), "", "")
        return _get_many_values(reply.get, len(refs))

    async def set(self, service: str, prop: str, value: Any, /, **params: Any) -> str:
        """Like :meth:`AsyncClient.set`, over the session."""
        request = pb.Request(
            set=pb.SetRequest(
                service=service, property=prop, value=format_value(value), parameters=_params(params)
            )
        )
        reply = await self._call_one(request, service, prop)
        answer: str = reply.set.value
        return answer

    @overload
    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        params: Mapping[str, Any] | None = ...,
        updates_only: bool = ...,
        min_interval: float | None = ...,
        sample_interval: float | None = ...,
        heartbeat: float | None = ...,
        max_batch: int = ...,
        marks: Literal[False] = ...,
    ) -> AsyncGenerator[Event, None]: ...

    @overload
    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        params: Mapping[str, Any] | None = ...,
        updates_only: bool = ...,
        min_interval: float | None = ...,
        sample_interval: float | None = ...,
        heartbeat: float | None = ...,
        max_batch: int = ...,
        marks: Literal[True],
    ) -> AsyncGenerator[Event | Mark, None]: ...

    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        params: Mapping[str, Any] | None = None,
        updates_only: bool = False,
        min_interval: float | None = None,
        sample_interval: float | None = None,
        heartbeat: float | None = None,
        max_batch: int = 0,
        marks: bool = False,
    ) -> AsyncGenerator[Event, None] | AsyncGenerator[Event | Mark, None]:
        """Like :meth:`AsyncClient.listen`, over the session; closing the iterator sends a Cancel."""
        request = _listen_request(
            service,
            prop,
            more,
            params=params,
            updates_only=updates_only,
            min_interval=min_interval,
            sample_interval=sample_interval,
            heartbeat=heartbeat,
            max_batch=max_batch,
        )
        return self._listen(request, marks)

    async def _listen(self, request: pb.ListenRequest, marks: bool) -> AsyncGenerator[Any, None]:
        self._check_open()
        rid = next(self._ids)
        state = _ListenState(marks)
        self._listens[rid] = state
        try:
            await self._enqueue(pb.Request(id=rid, listen=request), None)
            while True:
                while not state.items and not state.done:
                    state.wake.clear()
                    await state.wake.wait()
                if state.items:
                    key = next(iter(state.items))
                    yield state.items.pop(key)
                    continue
                if state.error is not None:
                    raise _again(state.error, request.service, request.property)
                return
        finally:
            del self._listens[rid]
            if not state.done and self._closed is None:
                cancel = pb.Request(id=next(self._ids), cancel=pb.Cancel(id=rid))
                # Best effort when the queue is full: replies to an unknown id are dropped anyway.
                with contextlib.suppress(asyncio.QueueFull):
                    self._queue.put_nowait(cancel)

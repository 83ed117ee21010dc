"""The asyncio client: unary Get and Set, server-streamed Listen, and the door to a :class:`Session`."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import AsyncGenerator, Callable, Iterable, Sequence
from contextlib import aclosing
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

import grpc
import grpc.aio

from clients.aio.events import Event, History, Mark, Reading, history_of, listen_items, reading_of
from clients.aio.gateways import (
    DEFAULT_FAILOVER_LIMIT,
    DEFAULT_KEEPALIVE,
    GatewayList,
    answered_by_gateway,
    channel_options,
    no_gateway_answered,
)
from clients.aio.listen import ListenCalls
from clients.aio.requests import (
    Selector,
    TimeArg,
    binary,
    decode,
    format_params,
    get_many_request,
    get_many_values,
    history_request,
    matching_values,
    set_request,
    value_of,
)
from clients.aio.session import DEFAULT_SESSION_QUEUE, Session
from clients.credentials import ClientCredentials
from clients.errors import (
    DeadlineExceeded,
    GatewayUnreachable,
    PropertyServiceError,
    ResourceExhausted,
    Unavailable,
    error_from_rpc,
)
from clients.values import (
    Marker,
    Value,
    ValueFormatError,
    parse_marker,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.model import ServiceModel
from services.kernel.model_codec import model_from_proto

if TYPE_CHECKING:
    from clients.values import Vector

__all__ = [
    "DEFAULT_FAILOVER_LIMIT",
    "DEFAULT_KEEPALIVE",
    "DEFAULT_MAX_IN_FLIGHT",
    "DEFAULT_TARGET",
    "DEFAULT_TIMEOUT",
    "AsyncClient",
]

DEFAULT_TARGET = "127.0.0.1:50051"
#: Seconds a unary call (or a request inside a Session) may take.
DEFAULT_TIMEOUT = 10.0
#: Unary calls (Get, Set) one AsyncClient has in flight at once; more callers wait their turn.
#: grpc.aio answers part of a burst of more than about a thousand simultaneous unary calls on one
#: channel with CANCELLED, so the client never starts that many.
DEFAULT_MAX_IN_FLIGHT = 256
#: Names asked of the registry a page (``services()`` past one value, ``service_pages``): 1,000
#: names of the longest a name may be (64 characters) fit in one value.
SERVICES_PAGE = 1000
#: Seconds before a resumed Listen (``resume=True``) is opened again, doubling up to the most:
#: a gateway that restarts is back within seconds; one that stays away is asked every 5 s.
RESUME_FIRST_PAUSE = 0.1
RESUME_MAX_PAUSE = 5.0
#: Unary calls that only read: one that failed on the way to a gateway is asked again of the next.
#: A Set is asked again only when it never reached a gateway (it may have been applied otherwise).
_READS = frozenset({"Get", "Describe", "History"})

log = logging.getLogger(__name__)


class AsyncClient(ListenCalls[AsyncGenerator[Event, None], AsyncGenerator[Event | Mark, None]]):
    """Asyncio client of a Property Service gateway.

    Use as ``async with AsyncClient("127.0.0.1:50051") as c: await c.get("scout1", "location")``.
    ``target`` may name several gateways that offer the same services (the gateways of a
    cluster): a list, or one string ``"gw1:50051,gw2:50051"``; a gRPC name such as
    ``dns:///gateways.local:50051`` may stand for several addresses itself. The client uses one
    at a time and moves to the next when it stops answering (see :mod:`clients.aio.gateways`):
    a Get whose gateway could not be reached is asked of the next within the same ``timeout``;
    a resumed listen opens again on the next, its first event marked ``gap``; when no address
    answers, :class:`~clients.errors.GatewayUnreachable` names each one tried. Keep-alive
    pings every ``keepalive`` seconds (None: grpc's defaults) find a frozen gateway.
    Every unary call is bounded by ``timeout`` seconds (None: no limit);
    ``metadata`` goes with every call; ``credentials`` (a CA, a client certificate and key, a
    token: :class:`clients.credentials.ClientCredentials`) make the channel TLS and add
    ``authorization: Bearer TOKEN`` to that metadata.
    At most ``max_in_flight`` unary calls run at once; further callers queue
    in the client, first come first served, and their waiting counts towards
    their ``timeout``. For many calls, :meth:`session` is the faster path.
    Every :meth:`listen` of the client travels inside one Session stream, opened by
    the first and again after it ended (about 2 KiB of the gateway's memory a listen,
    against about 23 KiB for a Listen stream of its own); ``separate_listens=True``
    gives each listen a Listen stream of its own instead.
    Failures raise :class:`clients.errors.PropertyServiceError` subclasses.
    """

    def __init__(
        self,
        target: str | Sequence[str] = DEFAULT_TARGET,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        metadata: Iterable[tuple[str, str]] | None = None,
        options: Sequence[tuple[str, Any]] | None = None,
        max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
        credentials: ClientCredentials | None = None,
        separate_listens: bool = False,
        keepalive: float | None = DEFAULT_KEEPALIVE,
        failover_limit: float | None = DEFAULT_FAILOVER_LIMIT,
    ) -> None:
        """``failover_limit``: seconds a resumed listen may go without reaching any gateway before
        it raises (None: it keeps trying)."""
        if isinstance(max_in_flight, bool) or not isinstance(max_in_flight, int) or max_in_flight < 1:
            raise ValueError(f"max_in_flight must be a whole number of at least 1, got {max_in_flight!r}")
        self.gateways = GatewayList(target)
        #: The gateway address in use now.
        self.target = self.gateways.current
        self.timeout = timeout
        self.failover_limit = failover_limit
        self.credentials = credentials or ClientCredentials()
        sent = (*(metadata or ()), *self.credentials.metadata())
        self.metadata: tuple[tuple[str, str], ...] | None = sent or None
        self.max_in_flight = max_in_flight
        # The caller's options win over the keep-alive defaults (grpc takes the last of a key).
        self._options = [*channel_options(keepalive), *(options or [])]
        #: Each ``listen`` on a Listen stream of its own, rather than inside the shared Session.
        self.separate_listens = separate_listens
        self._channel: grpc.aio.Channel | None = None
        self._stub: Any = None
        self._slots = asyncio.Semaphore(max_in_flight)
        #: The Session the listens share (made by the first listen, again after it ended).
        self._listen_session: Session | None = None
        #: One channel per gateway address used so far; the one in use is ``_channel``. A channel
        #: left behind is kept, not closed: calls still on it end on their own (closing it would
        #: turn their UNAVAILABLE into CANCELLED), and going back to its gateway reuses it.
        self._channels: dict[str, grpc.aio.Channel] = {}

    def stub(self) -> Any:
        """The generated ``PropertyServiceStub`` over this client's channel, made on first use.

        The channel (and the call slots) are made on first use, so that they bind to the running loop.
        """
        if self._stub is None:
            self._open_channel()
            self._slots = asyncio.Semaphore(self.max_in_flight)
        return self._stub

    def _open_channel(self) -> None:
        channel = self._channels.get(self.target)
        if channel is None:
            if self.credentials.secure:
                channel = grpc.aio.secure_channel(
                    self.target, self.credentials.channel_credentials(), options=self._options
                )
            else:
                channel = grpc.aio.insecure_channel(self.target, options=self._options)
            self._channels[self.target] = channel
        self._channel = channel
        self._stub = pb_grpc.PropertyServiceStub(channel)

    def gateway_failed(self, target: str, why: str, *, say: bool = True) -> None:
        """A call or stream through ``target`` found it gone (``why``): when that is the gateway in
        use and the client has several, later calls and streams go to the next. ``say``: log the
        move (False where what resumes logs it, one line a move)."""
        if self._move_on(target) and say:
            self._log_move(target, why)

    def _move_on(self, failed: str) -> bool:
        """Use the next gateway when ``failed`` (the address a call used) is the one in use; True
        when it moved. The caller logs the move, unless it gives up instead."""
        if not self.gateways.move_on(failed):
            return False
        self.target = self.gateways.current
        if self._stub is not None:
            self._open_channel()
        return True

    def _log_move(self, failed: str, why: str) -> None:
        log.warning("gateway %s failed (%s); moving to %s", failed, why, self.target)

    async def __aenter__(self) -> Self:
        self.stub()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Close the channel; ongoing calls are cancelled (listens raise Cancelled). Idempotent."""
        session, self._listen_session = self._listen_session, None
        if session is not None:
            await session.aclose()
        channels, self._channels = list(self._channels.values()), {}
        self._channel = self._stub = None
        for channel in channels:
            await channel.close(None)

    def _error(
        self, err: grpc.RpcError, service: str = "", prop: str = "", target: str | None = None
    ) -> PropertyServiceError:
        return error_from_rpc(err, service, prop, self.target if target is None else target)

    async def _unary(self, method: str, request: Any, service: str = "", prop: str = "") -> Any:
        """One Get or Set, in a call slot; the wait for the slot counts towards the timeout.

        With several gateways, a call that did not reach its gateway is made again on the next,
        each address once, all within the one timeout.
        """
        self.stub()
        slots = self._slots
        timeout = self.timeout
        if slots.locked():
            timeout = await self._wait_for_slot(slots, service, prop)
        else:
            await slots.acquire()  # a free slot: taken at once, no timer needed
        loop = asyncio.get_running_loop()
        deadline = None if timeout is None else loop.time() + timeout
        tried: dict[str, str] = {}
        try:
            while True:
                target, stub = self.target, self.stub()
                left = None if deadline is None else max(deadline - loop.time(), 1e-3)
                try:
                    return await getattr(stub, method)(request, timeout=left, metadata=self.metadata)
                except grpc.RpcError as e:
                    error = self._error(e, service, prop, target)
                    if not isinstance(error, Unavailable) or answered_by_gateway(e):
                        raise error from None
                    moved = self._move_on(target)
                    tried[target] = error.message
                    again = isinstance(error, GatewayUnreachable) or method in _READS
                    if len(self.gateways) == 1:
                        raise error from None
                    if not again:
                        raise Unavailable(
                            error.code,
                            f"{error.message} (at {target}; the call may have been applied there; "
                            f"the next call goes to {self.target})",
                            service,
                            prop,
                        ) from None
                    if self.target in tried or (deadline is not None and loop.time() >= deadline):
                        raise no_gateway_answered(tried, None, service, prop) from None
                    if moved:
                        self._log_move(target, error.message)
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

    async def get(self, service: str, prop: str, /, **params: Any) -> Value:
        """The value of ``prop`` of ``service``: text, or ``bytes`` for a binary property (type
        ``bytes``); keyword arguments are request parameters."""
        request = pb.GetRequest(service=service, property=prop, parameters=format_params(params))
        return value_of(await self._unary("Get", request, service, prop))

    async def get_with_time(self, service: str, prop: str, /, **params: Any) -> Reading:
        """The value of ``prop`` of ``service`` and its source time (:class:`Reading`): when the
        value became true, as far as the gateway knows."""
        request = pb.GetRequest(service=service, property=prop, parameters=format_params(params))
        return reading_of(await self._unary("Get", request, service, prop))

    async def history(
        self,
        service: str,
        prop: str,
        /,
        *,
        since: TimeArg = None,
        until: TimeArg = None,
        limit: int = 0,
    ) -> History:
        """The values the gateway kept of ``prop`` of ``service`` (``*`` for the service or a path
        segment: every match) with ``since <= time < until``, oldest first.

        ``since`` and ``until``: a ``datetime`` (naive is UTC), a ``timedelta`` before now, or
        seconds since the epoch; None is open. ``limit``: the most events (0: the gateway's
        default); with more in the range, :attr:`History.truncated` is set. FAILED_PRECONDITION
        when the gateway keeps no history; NOT_FOUND when it keeps none of these properties.
        """
        request = history_request(service, prop, since, until, limit)
        return history_of(await self._unary("History", request, service, prop))

    async def get_bytes(self, service: str, prop: str, /, **params: Any) -> bytes:
        """The value of a binary property; ValueFormatError when it is text."""
        return binary(await self.get(service, prop, **params), service, prop)

    async def get_many(self, refs: Iterable[Selector]) -> list[Value]:
        """Values of several ``(service, property[, params])`` in one call, in order; all or nothing."""
        refs = list(refs)
        if not refs:
            return []
        resp = await self._unary("Get", get_many_request(refs))
        return get_many_values(resp, len(refs))

    async def get_matching(self, service: str, pattern: str, /, **params: Any) -> dict[str, Value]:
        """Path → value of every readable property of ``service`` that ``pattern`` matches, in one Get.

        ``*`` in ``pattern`` stands for one segment (``robots.*.location``); no match is NOT_FOUND.
        """
        request = pb.GetRequest(service=service, property=pattern, parameters=format_params(params))
        return matching_values(await self._unary("Get", request, service, pattern))

    async def set(self, service: str, prop: str, value: Any, /, **params: Any) -> Value:
        """Write ``value`` (text, number, bool, vector, list, :class:`Marker`, or ``bytes`` for a
        binary property); return the answer (``bytes`` when the answer is binary)."""
        request = set_request(service, prop, value, params)
        return value_of(await self._unary("Set", request, service, prop))

    async def get_number(self, service: str, prop: str, /, **params: Any) -> float:
        """The value as a float."""
        return decode(parse_number, await self.get(service, prop, **params), service, prop)

    async def get_vector(self, service: str, prop: str, /, **params: Any) -> Vector:
        """The value ``(1 2 3)`` as a 1-D numpy array."""
        return decode(parse_vector, await self.get(service, prop, **params), service, prop)

    async def get_vectors(self, service: str, prop: str, /, **params: Any) -> list[Vector]:
        """The value ``((1 2) (3 4))`` as a list of 1-D numpy arrays."""
        return decode(parse_vectors, await self.get(service, prop, **params), service, prop)

    async def get_names(self, service: str, prop: str, /, **params: Any) -> list[str]:
        """The value ``(a b c)`` as a list of names."""
        return decode(parse_names, await self.get(service, prop, **params), service, prop)

    async def get_marker(self, service: str, prop: str, /, **params: Any) -> Marker:
        """The value as a :class:`Marker`."""
        return decode(parse_marker, await self.get(service, prop, **params), service, prop)

    async def services(self) -> list[str]:
        """Names of the services the gateway's registry knows, in the order they joined.

        The registry's ``services`` is one value: past about 6,000 names it passes the 64 KiB a
        value may hold. Then the names are read a page at a time (:meth:`service_pages`), in name
        order."""
        try:
            return await self.get_names("registry", "services")
        except (ValueFormatError, ResourceExhausted):
            return [name async for page in self.service_pages() for name in page]

    async def service_pages(self, page: int = SERVICES_PAGE) -> AsyncGenerator[list[str], None]:
        """The names of the registry's services in name order, ``page`` at most at a time (fewer
        when that many would pass one value's 64 KiB): the registry's ``service_names``, each page asked
        after the last name of the one before, until an empty one. A service that joins or leaves
        meanwhile may be in the pages or not; one registered throughout is in them exactly once."""
        after = ""
        while True:
            names = await self.get_names("registry", "service_names", after=after, limit=str(page))
            if not names:
                return
            yield names
            after = names[-1]

    async def describe(self, service: str) -> ServiceModel:
        """The typed model of every property of ``service`` in one call (the ``Describe`` RPC)."""
        resp = await self._unary("Describe", pb.DescribeRequest(service=service), service)
        return model_from_proto(resp)

    async def properties(self, service: str) -> list[str]:
        """The properties ``service`` offers right now."""
        return await self.get_names(service, "properties")

    def start_listen(
        self, request: pb.ListenRequest, marks: bool, resume: bool = False
    ) -> AsyncGenerator[Event | Mark, None]:
        """The Listen for ``request``, inside the client's shared Session (on a Listen stream of its
        own with ``separate_listens``); see :meth:`listen`."""
        items = self._stream_items if self.separate_listens else self._session_items
        return self._resumed(lambda: items(request, marks), request, resume)

    async def _resumed(
        self,
        attempt: Callable[[], AsyncGenerator[Event | Mark, None]],
        request: pb.ListenRequest,
        resume: bool,
    ) -> AsyncGenerator[Event | Mark, None]:
        """The items of ``attempt()``; with ``resume``, of a new attempt after each UNAVAILABLE,
        on the next gateway when there are several, until ``failover_limit`` passes with no
        gateway reached."""
        loop = asyncio.get_running_loop()
        pause = RESUME_FIRST_PAUSE
        resumed = False
        #: Since the stream broke, without an item since: each address tried, with why it failed.
        tried: dict[str, str] = {}
        broken_at = 0.0
        while True:
            target = self.target
            try:
                async with aclosing(attempt()) as items:
                    async for item in items:
                        pause = RESUME_FIRST_PAUSE
                        tried.clear()
                        if resumed and isinstance(item, Event):
                            resumed = False
                            yield dataclasses.replace(item, gap=True)  # values may have been missed
                        else:
                            yield item
                return
            except Unavailable as e:  # GatewayUnreachable too
                if not resume:
                    raise
                if not tried:
                    broken_at = loop.time()
                tried[target] = e.message
                self._move_on(target)  # logged below with the resume, one line a move
                limit = self.failover_limit
                if limit is not None and loop.time() - broken_at >= limit:
                    raise no_gateway_answered(tried, limit, request.service, request.property) from None
                # The next address at once when it has not failed yet; a full round, a pause.
                wait = pause if self.target in tried else 0.0
                log.warning(
                    "listen %s %s: %s at %s; resuming at %s in %.1f s",
                    request.service,
                    request.property,
                    e.message,
                    target,
                    self.target,
                    wait,
                )
            if wait:
                await asyncio.sleep(wait)
                pause = min(2 * pause, RESUME_MAX_PAUSE)
            resumed = True

    async def _stream_items(
        self, request: pb.ListenRequest, marks: bool
    ) -> AsyncGenerator[Event | Mark, None]:
        """The items of a server-streamed Listen call of its own."""
        target = self.target
        call = self.stub().Listen(request, metadata=self.metadata)
        try:
            async for resp in call:
                for item in listen_items(resp, marks):
                    yield item
        except grpc.RpcError as e:
            raise self._error(e, request.service, request.property, target) from None
        finally:
            call.cancel()

    async def _session_items(
        self, request: pb.ListenRequest, marks: bool
    ) -> AsyncGenerator[Event | Mark, None]:
        """The items of a Listen inside the Session the client's listens share."""
        session = self._listen_session
        if session is None or session.closed:
            if session is not None:
                await session.aclose()  # its tasks: the reader ended with the stream, the writer waits
            # Kept before opening: open() never waits, so no other listen can find it unopened.
            session = self._listen_session = Session(self, carries_resumed_listens=True)
            await session.open()
        async with aclosing(session.start_listen(request, marks)) as items:
            async for item in items:
                yield item

    def session(self, *, max_pending: int = DEFAULT_SESSION_QUEUE) -> Session:
        """A :class:`Session` over this client's channel: ``async with client.session() as s: ...``."""
        return Session(self, max_pending=max_pending)

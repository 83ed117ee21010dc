"""The ``propertyservice.v1.PropertyService`` servicer: Get, Set, Listen, Session and Describe.

Get, Set and Describe are translated at the door into the engine's own types
(:mod:`gateway.fronts.grpc_v1.messages`) and served by one unary wrapper
(:meth:`PropertyServicer._unary`: the request id, ``[limits] max_calls``, the
call timeout or the client's deadline when that is shorter, the status of a
failure, the counts) through the call layer (:class:`gateway.engine.calls.Calls`).
Listen streams come from the listen hub. Session lives in :mod:`gateway.fronts.grpc_v1.session`.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from time import perf_counter
from typing import Any, Generic, TypeVar

import grpc
from google.protobuf.message import Message
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection, reflection_pb2_grpc
from grpc_reflection.v1alpha._async import ReflectionServicer

from gateway.config import Config
from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.history import HistoryKeeper, HistoryQuery, HistoryReply, kept_history
from gateway.engine.identity import ANONYMOUS
from gateway.engine.listen import ListenHub
from gateway.engine.listen.budget import COUNTED_BYTES, GRPC_COPIES
from gateway.engine.listen.drain import Wake, steps
from gateway.engine.router import Router
from gateway.engine.rules import Subject
from gateway.engine.status import to_property_error
from gateway.engine.types import DescribeCall
from gateway.federation import VIA_KEY, enter, new_gateway_id
from gateway.fronts.grpc_v1.listen_encoding import listen_request, listen_wire
from gateway.fronts.grpc_v1.messages import (
    Undecodable,
    get_call,
    get_response,
    history_query,
    history_response,
    lenient,
    set_call,
    set_response,
)
from gateway.fronts.grpc_v1.session import Session
from gateway.fronts.grpc_v1.status import abort
from gateway.logs import REQUEST_ID_HEADER, RequestContext, current_request, request_id_from
from gateway.metrics.counts import GrpcCounts, MethodCounts
from gateway.peer_protocol import PROTOCOLS_KEY, check_caller
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.errors import Code, ResourceExhausted
from services.kernel.model_codec import model_to_proto

Context = grpc.aio.ServicerContext[Any, Any]

#: The contract's service, by its full name (``propertyservice.v1.PropertyService``).
SERVICE_NAME: str = pb.DESCRIPTOR.services_by_name["PropertyService"].full_name


def arrival(context: Context) -> tuple[str, str | bytes | None]:
    """The call's request id (the client's ``x-request-id`` metadata when usable, else a new one)
    and its ``ps-via`` chain (None: it came straight from a client). A call from a gateway that
    shares no cluster protocol version with this one (its ``ps-protocols`` metadata) is refused:
    :class:`~gateway.peer_protocol.ProtocolMismatch`.

    One pass over the metadata for both: grpc builds the metadata tuple anew on every read.
    """
    chosen: str | bytes | None = None
    via: str | bytes | None = None
    for key, value in context.invocation_metadata() or ():
        if key == REQUEST_ID_HEADER:
            if chosen is None:
                chosen = value
        elif key == VIA_KEY and via is None:
            via = value
        elif key == PROTOCOLS_KEY:
            check_caller(value)
    return request_id_from(chosen), via


def _subject_name(subject: Subject) -> str | None:
    return subject.name if subject is not ANONYMOUS else None


def _begin_unary(context: Context, service: str, path: str) -> tuple[RequestContext, str | bytes | None]:
    """Give the call its request id (in the log context, and back to the client as a trailer);
    return that context and the call's ``ps-via`` chain (see :func:`arrival`)."""
    request_id, via = arrival(context)
    context.set_trailing_metadata(((REQUEST_ID_HEADER, request_id),))
    request = RequestContext(request_id, service or None, path or None)
    current_request.set(request)
    return request, via


def _serialized(response: bytes) -> bytes:
    return response


def add_to_server(servicer: PropertyServicer, server: grpc.aio.Server) -> None:
    """Serve ``servicer`` on ``server``: the generated registration, but a request that does not
    parse is INVALID_ARGUMENT (a Session ends with it after answering what it read before)."""
    handlers = {
        "Get": grpc.unary_unary_rpc_method_handler(
            servicer.Get,
            request_deserializer=lenient(pb.GetRequest),
            response_serializer=pb.GetResponse.SerializeToString,
        ),
        "Set": grpc.unary_unary_rpc_method_handler(
            servicer.Set,
            request_deserializer=lenient(pb.SetRequest),
            response_serializer=pb.SetResponse.SerializeToString,
        ),
        "Listen": grpc.unary_stream_rpc_method_handler(
            servicer.Listen,
            request_deserializer=lenient(pb.ListenRequest),
            response_serializer=_serialized,  # Listen yields its responses serialized already
        ),
        "Session": grpc.stream_stream_rpc_method_handler(
            servicer.Session,
            request_deserializer=lenient(pb.SessionRequest),
            response_serializer=_serialized,  # a Session writes its responses serialized already
        ),
        "Describe": grpc.unary_unary_rpc_method_handler(
            servicer.Describe,
            request_deserializer=lenient(pb.DescribeRequest),
            response_serializer=pb.DescribeResponse.SerializeToString,
        ),
        "History": grpc.unary_unary_rpc_method_handler(
            servicer.History,
            request_deserializer=lenient(pb.HistoryRequest),
            response_serializer=pb.HistoryResponse.SerializeToString,
        ),
    }
    # Generic only, never registered: see GenericOnly.
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))


class GenericOnly:
    """A grpc.aio server as a generated ``add_*_to_server`` sees it: the servicer's methods are
    served by generic handlers only, never registered.

    grpc.aio's accept loop waits (``asyncio.wait``) on one pending request per registered method
    plus one for every generic method, so each registered method makes every call of every method
    dearer (callgrind shows it on a unary Get: ``python -m bench.instructions --parts unary``);
    finding a generic method is a dictionary lookup.
    """

    def __init__(self, server: grpc.aio.Server) -> None:
        self._server = server

    def add_generic_rpc_handlers(self, handlers: Sequence[grpc.GenericRpcHandler[Any, Any]]) -> None:
        self._server.add_generic_rpc_handlers(handlers)

    def add_registered_method_handlers(self, service: str, handlers: Mapping[str, Any]) -> None:
        """Not registered: the same methods came as generic handlers just before."""


def add_health_and_reflection(server: grpc.aio.Server, health: Any) -> None:
    """Serve the gRPC health service ``health`` and server reflection listing the contract's
    service, health and reflection, as generic handlers (see :class:`GenericOnly`)."""
    generic = GenericOnly(server)
    health_pb2_grpc.add_HealthServicer_to_server(health, generic)
    listed = (
        SERVICE_NAME,
        health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
        reflection.SERVICE_NAME,
    )
    # What reflection.enable_server_reflection does for a grpc.aio server (it tells one by its
    # type, so it cannot be handed GenericOnly): the asyncio servicer, added by the generated code.
    reflection_pb2_grpc.add_ServerReflectionServicer_to_server(ReflectionServicer(listed), generic)


def _describe_call(request: pb.DescribeRequest) -> DescribeCall:
    return DescribeCall(request.service)


#: The response message of a unary method.
M = TypeVar("M", bound=Message)


@dataclass(frozen=True, slots=True)
class _Unary(Generic[M]):
    """One unary method as :meth:`PropertyServicer._unary` serves it: the request translated
    into the engine's call, the engine's method that serves it, and its answer translated back."""

    name: str
    counts: MethodCounts | None
    to_call: Callable[[Any], Any]
    #: ``serve(call, time_limit, subject)``: a method of :class:`gateway.engine.calls.Calls`.
    serve: Callable[[Any, float, Subject], Awaitable[Any]]
    to_response: Callable[[Any], M]
    #: Who calls (a Set names its caller even when nothing is refused: the audit trail says who).
    identify: Callable[[Context], Subject]
    #: Whether the request names a property (for its log lines).
    has_path: bool = True


class PropertyServicer(pb_grpc.PropertyServiceServicer):  # type: ignore[misc]
    """Serves the v1 contract from a router and a listen hub."""

    def __init__(
        self,
        router: Router,
        hub: ListenHub,
        config: Config,
        guard: Guard | None = None,
        history: HistoryKeeper | None = None,
    ) -> None:
        """``guard`` checks every call (the hub's own: the same rules hold for every front end);
        ``history`` answers History (None: the gateway keeps none)."""
        self.router = router
        self.history = history
        self.guard = guard or hub.guard
        self.calls = Calls(
            router,
            config.gateway.call_timeout,
            config.limits.max_get_paths,
            self.guard,
            heard_at=hub.topics.heard_at,
        )
        self.hub = hub
        self.config = config
        self._timeout = config.gateway.call_timeout
        #: Unary calls (Get, Set, Describe) running now, and how many may (``[limits] max_calls``).
        self.calls_running = 0
        self._max_calls = config.limits.max_calls
        #: Session calls running now (see gateway.fronts.grpc_v1.session).
        self.sessions: set[Session] = set()
        #: This gateway's id in the ``ps-via`` chain of federated calls (gateway.federation).
        self.gateway_id = new_gateway_id()
        #: Calls by method and code, latencies, Session requests; None when ``[metrics]`` is off.
        self.counts = GrpcCounts() if config.metrics.enabled else None
        methods = self.counts.methods if self.counts is not None else {}
        self._get_counts: MethodCounts | None = methods.get("Get")
        self._set_counts: MethodCounts | None = methods.get("Set")
        self._describe_counts: MethodCounts | None = methods.get("Describe")
        self._listen_counts: MethodCounts | None = methods.get("Listen")
        self._session_counts: MethodCounts | None = methods.get("Session")
        self._history_counts: MethodCounts | None = methods.get("History")
        calls = self.calls
        self._get_method = _Unary("Get", self._get_counts, get_call, calls.get, get_response, self._subject)
        # Identified even when nothing is refused: the audit trail names who set what.
        self._set_method = _Unary(
            "Set", self._set_counts, set_call, calls.set, set_response, self.guard.identify_call
        )
        self._describe_method = _Unary(
            "Describe",
            self._describe_counts,
            _describe_call,
            calls.describe,
            model_to_proto,
            self._subject,
            has_path=False,
        )
        self._history_method = _Unary(
            "History", self._history_counts, history_query, self.read_history, history_response, self._subject
        )

    async def read_history(self, query: HistoryQuery, time_limit: float, subject: Subject) -> HistoryReply:
        """A History call, answered from the history keeper (FAILED_PRECONDITION when it keeps none)."""
        return kept_history(self.history, query, subject)

    def end_sessions(self) -> None:
        """Gateway shutdown: every Session flushes, ends its listens and ends with OK."""
        for session in list(self.sessions):
            session.stop()

    def _subject(self, context: Context) -> Subject:
        """Who calls; without rules or tokens nobody is refused and a Get need not ask."""
        return self.guard.identify_call(context) if self.guard.checks else ANONYMOUS

    def _take_call_place(self) -> None:
        """Count one more unary call running; RESOURCE_EXHAUSTED naming the limit when it is reached.

        Without it a burst only meets grpc's queue of calls not yet taken up, whose overflow
        ends calls with a bare CANCELLED (docs/errors.md).
        """
        if self.calls_running >= self._max_calls:
            raise ResourceExhausted(
                f"{self._max_calls} calls are running in this gateway already ([limits] max_calls);"
                " try again, or send them in a Session"
            )
        self.calls_running += 1

    def _deadline(self, context: Context) -> float:
        remaining = context.time_remaining()
        timeout = self._timeout
        return remaining if remaining is not None and remaining < timeout else timeout

    async def _unary(self, request: Any, context: Context, method: _Unary[M]) -> M:
        """Serve a unary call: its request id, its place among ``[limits] max_calls``, its deadline,
        the ``method``'s answer, and its count; a failure ends it with its status."""
        started = perf_counter()
        counts = method.counts
        try:
            if isinstance(request, Undecodable):
                _begin_unary(context, "", "")
                raise request.error
            logged, via = _begin_unary(context, request.service, request.property if method.has_path else "")
            enter(via, self.gateway_id)
            subject = method.identify(context)
            logged.subject = _subject_name(subject)
            self._take_call_place()
            try:
                answer = await method.serve(method.to_call(request), self._deadline(context), subject)
            finally:
                self.calls_running -= 1
            response = method.to_response(answer)
        except Exception as exc:
            await _failed(context, exc, method.name, counts, started)
            raise  # not reached: abort raises
        except asyncio.CancelledError:
            if counts is not None:
                counts.done(Code.CANCELLED, None)
            raise
        if counts is not None:
            counts.done(0, perf_counter() - started)
        return response

    async def Get(self, request: pb.GetRequest, context: Context) -> pb.GetResponse:
        return await self._unary(request, context, self._get_method)

    async def Set(self, request: pb.SetRequest, context: Context) -> pb.SetResponse:
        return await self._unary(request, context, self._set_method)

    async def Describe(self, request: pb.DescribeRequest, context: Context) -> pb.DescribeResponse:
        return await self._unary(request, context, self._describe_method)

    async def History(self, request: pb.HistoryRequest, context: Context) -> pb.HistoryResponse:
        return await self._unary(request, context, self._history_method)

    async def Listen(self, request: pb.ListenRequest, context: Context) -> AsyncIterator[bytes]:
        # Responses are yielded rather than written with context.write: grpc.aio
        # delivers 20-35% more messages per second this way (measured by bench/). They are
        # yielded serialized (listen_wire): a change is encoded once for every stream.
        wake = Wake()
        try:
            request_id, via = arrival(context)
            logged = RequestContext(request_id)
            current_request.set(logged)
            # Sent at once: a Listen may wait long for its first event, and the client logs the id now.
            await context.send_initial_metadata(((REQUEST_ID_HEADER, request_id),))
            if isinstance(request, Undecodable):
                raise request.error
            enter(via, self.gateway_id)
            subject = self._subject(context)
            logged.subject = _subject_name(subject)
            stream = self.hub.listen(listen_request(request), wake.set, subject)
        except Exception as exc:
            await _failed(context, exc, "Listen", self._listen_counts, None)
            return
        counts = self.counts
        if counts is not None:
            counts.listens_open += 1
        code = Code.CANCELLED  # unless it ends otherwise: the client went away
        budget = self.hub.budget
        held = 0
        try:
            await stream.start()
            for item in steps(stream, wake):
                if isinstance(item, asyncio.Future):
                    await item  # until the stream has something ready
                    continue
                response = listen_wire(item)
                del item  # not held while the client takes its message: the message is all it holds
                if len(response) < COUNTED_BYTES:
                    yield response
                    continue
                # A large message (a binary value) to a reader that does not read waits in
                # two copies, this one and grpc's, and grpc may still be writing the one
                # before it to the socket (measured: about 3 copies each for readers that
                # announce a large window and never read): all three count in the budget.
                counted = GRPC_COPIES * len(response)
                if not budget.take(counted):
                    # Not kept by the refusal's traceback (a cycle through this frame, freed
                    # only by the next collection: measured, 300 MB for 60 refused readers).
                    del response
                    raise budget.refusal(counted, "Listen")
                held = counted
                yield response
                budget.give_back(held)
                held = 0
            code = Code.OK
        except Exception as exc:
            err = to_property_error(exc, "Listen")
            code = err.code
            await abort(context, err, "Listen")
        finally:
            budget.give_back(held)  # a message the client never took
            stream.close()
            if counts is not None:
                counts.listens_open -= 1
                counts.methods["Listen"].done(code, None)

    async def Session(self, request_iterator: AsyncIterator[pb.SessionRequest], context: Context) -> None:
        try:
            request_id, via = arrival(context)
            logged = RequestContext(request_id)
            current_request.set(logged)
            await context.send_initial_metadata(((REQUEST_ID_HEADER, request_id),))
            enter(via, self.gateway_id)
            subject = self._subject(context)
            logged.subject = _subject_name(subject)
        except Exception as exc:
            await _failed(context, exc, "Session", self._session_counts, None)
            raise
        requests = self.counts.session_requests if self.counts is not None else None
        session = Session(
            self.calls, self.hub, self.config.limits, context, subject, logged=logged, requests=requests
        )
        self.sessions.add(session)
        code = Code.CANCELLED  # unless it ends otherwise: the client went away
        try:
            await session.run()
            code = Code.OK
        except Exception as exc:
            code = to_property_error(exc, "Session").code if session.error is None else session.error.code
            raise
        finally:
            self.sessions.discard(session)
            if self._session_counts is not None:
                self._session_counts.done(code, None)


async def _failed(
    context: Context, exc: BaseException, what: str, counts: MethodCounts | None, started: float | None
) -> None:
    """Count the call as ended with ``exc``'s code, then end it with that status (never returns)."""
    err = to_property_error(exc, what)
    if counts is not None:
        counts.done(err.code, None if started is None else perf_counter() - started)
    await abort(context, err, what)

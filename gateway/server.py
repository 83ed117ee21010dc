"""The ``propertyservice.v1.PropertyService`` servicer: Get, Set, Listen, Session and Describe.

Get, Set and Describe go through the router to one backend each, under the
call timeout (and the client's deadline when that is shorter). Listen streams
come from the listen hub. Session lives in :mod:`gateway.session`.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import aclosing
from typing import Any

import grpc
from google.protobuf.message import DecodeError, Message

from gateway.calls import Calls, Undecodable
from gateway.config import Config
from gateway.federation import enter, new_gateway_id
from gateway.guard import Guard
from gateway.identity import ANONYMOUS
from gateway.listen import ListenHub, parse_options, parse_selectors
from gateway.listen.drain import Wake, responses
from gateway.logs import REQUEST_ID_HEADER, RequestContext, current_request, request_id_from
from gateway.router import Router
from gateway.rules import Subject
from gateway.session import Session
from gateway.status import abort
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.errors import InvalidArgument
from services.model_codec import model_to_proto

Context = grpc.aio.ServicerContext[Any, Any]


def request_id_of(context: Context) -> str:
    """The call's request id: the client's ``x-request-id`` metadata when usable, else a new one."""
    for key, value in context.invocation_metadata() or ():
        if key == REQUEST_ID_HEADER:
            return request_id_from(value)
    return request_id_from(None)


def _subject_name(subject: Subject) -> str | None:
    return subject.name if subject is not ANONYMOUS else None


def _begin_unary(context: Context, service: str, path: str) -> RequestContext:
    """Give the call its request id (in the log context, and back to the client as a trailer)."""
    request_id = request_id_of(context)
    context.set_trailing_metadata(((REQUEST_ID_HEADER, request_id),))
    request = RequestContext(request_id, service or None, path or None)
    current_request.set(request)
    return request


def _lenient(message: type[Message]) -> Callable[[bytes], Message | Undecodable]:
    # grpc's own handling of a deserializer that raises is UNKNOWN and a logged traceback.
    name = message.DESCRIPTOR.full_name

    def parse(data: bytes) -> Message | Undecodable:
        try:
            return message.FromString(data)
        except DecodeError as exc:
            return Undecodable(InvalidArgument(f"the request is not a valid {name}: {exc}"))

    return parse


def add_to_server(servicer: PropertyServicer, server: grpc.aio.Server) -> None:
    """Serve ``servicer`` on ``server``: the generated registration, but a request that does not
    parse is INVALID_ARGUMENT (a Session ends with it after answering what it read before)."""
    handlers = {
        "Get": grpc.unary_unary_rpc_method_handler(
            servicer.Get,
            request_deserializer=_lenient(pb.GetRequest),
            response_serializer=pb.GetResponse.SerializeToString,
        ),
        "Set": grpc.unary_unary_rpc_method_handler(
            servicer.Set,
            request_deserializer=_lenient(pb.SetRequest),
            response_serializer=pb.SetResponse.SerializeToString,
        ),
        "Listen": grpc.unary_stream_rpc_method_handler(
            servicer.Listen,
            request_deserializer=_lenient(pb.ListenRequest),
            response_serializer=pb.ListenResponse.SerializeToString,
        ),
        "Session": grpc.stream_stream_rpc_method_handler(
            servicer.Session,
            request_deserializer=_lenient(pb.SessionRequest),
            response_serializer=pb.SessionResponse.SerializeToString,
        ),
        "Describe": grpc.unary_unary_rpc_method_handler(
            servicer.Describe,
            request_deserializer=_lenient(pb.DescribeRequest),
            response_serializer=pb.DescribeResponse.SerializeToString,
        ),
    }
    name = pb.DESCRIPTOR.services_by_name["PropertyService"].full_name
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(name, handlers),))
    # As the generated code does: grpc finds registered methods faster than generic ones.
    server.add_registered_method_handlers(name, handlers)  # type: ignore[attr-defined]


class PropertyServicer(pb_grpc.PropertyServiceServicer):  # type: ignore[misc]
    """Serves the v1 contract from a router and a listen hub."""

    def __init__(self, router: Router, hub: ListenHub, config: Config, guard: Guard | None = None) -> None:
        """``guard`` checks every call (the hub's own: the same rules hold for every front end)."""
        self.router = router
        self.guard = guard or hub.guard
        self.calls = Calls(router, config.gateway.call_timeout, config.limits.max_get_paths, self.guard)
        self.hub = hub
        self.config = config
        self._timeout = config.gateway.call_timeout
        #: Session calls running now (see gateway.session).
        self.sessions: set[Session] = set()
        #: This gateway's id in the ``ps-via`` chain of federated calls (gateway.federation).
        self.gateway_id = new_gateway_id()

    def end_sessions(self) -> None:
        """Gateway shutdown: every Session flushes, ends its listens and ends with OK."""
        for session in list(self.sessions):
            session.stop()

    def _subject(self, context: Context) -> Subject:
        """Who calls; without rules or tokens nobody is refused and a Get need not ask."""
        return self.guard.identify_call(context) if self.guard.checks else ANONYMOUS

    def _deadline(self, context: Context) -> float:
        remaining = context.time_remaining()
        timeout = self._timeout
        return remaining if remaining is not None and remaining < timeout else timeout

    async def Get(self, request: pb.GetRequest, context: Context) -> pb.GetResponse:
        try:
            if isinstance(request, Undecodable):
                _begin_unary(context, "", "")
                raise request.error
            logged = _begin_unary(context, request.service, request.property)
            enter(context.invocation_metadata(), self.gateway_id)
            subject = self._subject(context)
            logged.subject = _subject_name(subject)
            return await self.calls.get(request, self._deadline(context), subject)
        except Exception as exc:
            await abort(context, exc, "Get")
            raise  # not reached: abort raises

    async def Set(self, request: pb.SetRequest, context: Context) -> pb.SetResponse:
        try:
            if isinstance(request, Undecodable):
                _begin_unary(context, "", "")
                raise request.error
            logged = _begin_unary(context, request.service, request.property)
            enter(context.invocation_metadata(), self.gateway_id)
            # Identified even when nothing is refused: the audit trail names who set what.
            subject = self.guard.identify_call(context)
            logged.subject = _subject_name(subject)
            return await self.calls.set(request, self._deadline(context), subject)
        except Exception as exc:
            await abort(context, exc, "Set")
            raise

    async def Describe(self, request: pb.DescribeRequest, context: Context) -> pb.DescribeResponse:
        try:
            if isinstance(request, Undecodable):
                _begin_unary(context, "", "")
                raise request.error
            logged = _begin_unary(context, request.service, "")
            enter(context.invocation_metadata(), self.gateway_id)
            subject = self._subject(context)
            logged.subject = _subject_name(subject)
            model = await self.calls.describe(request.service, self._deadline(context), subject)
            return model_to_proto(model)
        except Exception as exc:
            await abort(context, exc, "Describe")
            raise

    async def Listen(self, request: pb.ListenRequest, context: Context) -> AsyncIterator[pb.ListenResponse]:
        # Responses are yielded rather than written with context.write: grpc.aio
        # delivers 20-35% more messages per second this way (measured by bench/).
        limits = self.config.limits
        wake = Wake()
        try:
            logged = RequestContext(request_id_of(context))
            current_request.set(logged)
            # Sent at once: a Listen may wait long for its first event, and the client logs the id now.
            await context.send_initial_metadata(((REQUEST_ID_HEADER, logged.request_id),))
            if isinstance(request, Undecodable):
                raise request.error
            enter(context.invocation_metadata(), self.gateway_id)
            subject = self._subject(context)
            logged.subject = _subject_name(subject)
            stream = self.hub.open(
                parse_selectors(request, limits),
                parse_options(request.options, limits),
                wake.set,
                subject,
            )
        except Exception as exc:
            await abort(context, exc, "Listen")
            return
        try:
            async with aclosing(responses(stream, wake)) as ready:
                async for response in ready:
                    yield response
        except Exception as exc:
            await abort(context, exc, "Listen")
        finally:
            stream.close()

    async def Session(self, request_iterator: AsyncIterator[pb.SessionRequest], context: Context) -> None:
        try:
            logged = RequestContext(request_id_of(context))
            current_request.set(logged)
            await context.send_initial_metadata(((REQUEST_ID_HEADER, logged.request_id),))
            enter(context.invocation_metadata(), self.gateway_id)
            subject = self._subject(context)
            logged.subject = _subject_name(subject)
        except Exception as exc:
            await abort(context, exc, "Session")
            raise
        session = Session(self.calls, self.hub, self.config.limits, context, subject, logged=logged)
        self.sessions.add(session)
        try:
            await session.run()
        finally:
            self.sessions.discard(session)

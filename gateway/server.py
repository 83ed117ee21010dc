"""The ``propertyservice.v1.PropertyService`` servicer: Get, Set, Listen and Session.

Get and Set go through the router to one backend each, under the call
timeout (and the client's deadline when that is shorter). Listen streams
come from the listen hub. Session lives in :mod:`gateway.session`.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import AsyncIterator, Callable, Mapping
from typing import TYPE_CHECKING, Any

import grpc
from google.protobuf.message import DecodeError, Message

from gateway.config import Config
from gateway.listen_hub import MAX_MESSAGE_BYTES, ListenHub, parse_options, parse_selectors
from gateway.router import Router, bounded_call, check_path
from gateway.status import abort, to_property_error
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.backend import NO_PARAMS, Backend
from services.errors import InvalidArgument, PropertyError, ResourceExhausted

if TYPE_CHECKING:
    from gateway.session import Session

Context = grpc.aio.ServicerContext[Any, Any]

#: The largest Get or Set answer sent: a client's limit less room for a Session's envelope.
MAX_ANSWER_BYTES = MAX_MESSAGE_BYTES - 1024
#: An answer carrying one value of at most this many characters fits whatever they are (UTF-8
#: takes at most 4 bytes a character): such an answer need not be measured.
SURELY_FITS_CHARS = (MAX_ANSWER_BYTES - 16) // 4


def check_fits(answer: pb.GetResponse | pb.SetResponse, what: Callable[[], str]) -> None:
    """Raise RESOURCE_EXHAUSTED when ``answer`` is too big for a client to receive.

    Sent anyway, the client would refuse it with a bare "message larger than max" (and, in a
    Session, drop every other request with it).
    """
    size = answer.ByteSize()
    if size > MAX_ANSWER_BYTES:
        raise ResourceExhausted(
            f"{what()}: the answer is {size} bytes, more than one message may carry "
            f"({MAX_ANSWER_BYTES} bytes); read fewer paths per Get"
        )


def _params(params: Mapping[str, str]) -> Mapping[str, str]:
    return dict(params) if params else NO_PARAMS


class Undecodable:
    """A request that did not parse, e.g. a string field holding bytes that are not UTF-8."""

    __slots__ = ("error",)

    def __init__(self, error: InvalidArgument) -> None:
        self.error = error


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
    }
    name = pb.DESCRIPTOR.services_by_name["PropertyService"].full_name
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(name, handlers),))
    # As the generated code does: grpc finds registered methods faster than generic ones.
    server.add_registered_method_handlers(name, handlers)  # type: ignore[attr-defined]


class Calls:
    """Get and Set against the router, shared by the unary calls and Session."""

    def __init__(self, router: Router, config: Config) -> None:
        self.router = router
        self.timeout = config.gateway.call_timeout
        self.max_get_paths = config.limits.max_get_paths

    async def get(self, request: pb.GetRequest, time_limit: float) -> pb.GetResponse:
        """Read the request's path and its ``more`` paths; all or nothing."""
        service = request.service
        if not service:
            raise InvalidArgument("Get needs a service name")
        backend = self.router.backend(service)
        path = check_path(request.property)
        params = request.parameters
        future = backend.start_get(path, params, time_limit)
        if future is not None:
            value = (await future).value
        else:
            value = await bounded_call(
                backend.get(path, dict(params) if params else NO_PARAMS),
                time_limit,
                lambda: f"{service}: get {path}",
            )
        if not request.more:
            response = pb.GetResponse(value=value)
        else:
            response = pb.GetResponse(value=value, more=await self._get_more(request, time_limit))
        check_fits(
            response,
            lambda: f"{service}: get {path}" + (f" and {len(request.more)} more" if request.more else ""),
        )
        return response

    async def _get_more(self, request: pb.GetRequest, time_limit: float) -> list[pb.PropertyValue]:
        if len(request.more) + 1 > self.max_get_paths:
            raise ResourceExhausted(
                f"a Get may read at most {self.max_get_paths} paths, this one reads {len(request.more) + 1}"
            )
        # Resolve every path first so that a bad one fails the call before any backend is asked.
        refs: list[tuple[str, str, Mapping[str, str], Backend]] = []
        for ref in request.more:
            service = ref.service or request.service
            try:
                backend = self.router.backend(service)
                path = check_path(ref.property)
            except PropertyError as exc:
                # Names are clipped: an echo of a huge bad name must not outgrow the status message.
                raise type(exc)(f"{service[:80]}/{ref.property[:256]}: {exc.message}", exc.code) from None
            refs.append((service, path, _params(ref.parameters), backend))
        groups: dict[int, list[int]] = {}
        for i, (_, _, _, backend) in enumerate(refs):
            groups.setdefault(id(backend), []).append(i)
        values: list[str | BaseException] = [""] * len(refs)

        async def read_group(indexes: list[int]) -> None:
            # One backend's paths are read one after another, as a device would answer them.
            for i in indexes:
                service, path, params, backend = refs[i]
                try:
                    values[i] = await bounded_call(
                        backend.get(path, params),
                        time_limit,
                        functools.partial("{}: get {}".format, service, path),
                    )
                except Exception as exc:
                    values[i] = exc
                    return

        if len(groups) == 1:
            await read_group(next(iter(groups.values())))
        else:
            await asyncio.gather(*(read_group(ix) for ix in groups.values()))
        out = []
        for (service, path, _, _), value in zip(refs, values, strict=True):
            if isinstance(value, BaseException):
                err = to_property_error(value, f"{service}: get {path}")
                raise type(err)(f"{service}/{path}: {err.message}", err.code) from None
            out.append(pb.PropertyValue(service=service, property=path, value=value))
        return out

    async def set(self, request: pb.SetRequest, time_limit: float) -> pb.SetResponse:
        """Write the request's value; the response carries the service's answer."""
        service = request.service
        if not service:
            raise InvalidArgument("Set needs a service name")
        backend = self.router.backend(service)
        path = check_path(request.property)
        params = request.parameters
        answer = await bounded_call(
            backend.set(path, request.value, dict(params) if params else NO_PARAMS),
            time_limit,
            lambda: f"{service}: set {path}",
        )
        response = pb.SetResponse(value=answer if answer is not None else "")
        check_fits(response, lambda: f"{service}: set {path}")
        return response


class _Wake:
    """A one-waiter asyncio.Event without the waiter deque: idle Listen streams stay small."""

    __slots__ = ("_future", "_set")

    def __init__(self) -> None:
        self._set = False
        self._future: asyncio.Future[None] | None = None

    def set(self) -> None:
        self._set = True
        future = self._future
        if future is not None and not future.done():
            future.set_result(None)

    async def wait(self) -> None:
        if not self._set:
            self._future = asyncio.get_running_loop().create_future()
            try:
                await self._future
            finally:
                self._future = None
        self._set = False


class PropertyServicer(pb_grpc.PropertyServiceServicer):  # type: ignore[misc]
    """Serves the v1 contract from a router and a listen hub."""

    def __init__(self, router: Router, hub: ListenHub, config: Config) -> None:
        self.calls = Calls(router, config)
        self.hub = hub
        self.config = config
        self._timeout = config.gateway.call_timeout
        #: Session calls running now (see gateway.session).
        self.sessions: set[Session] = set()

    def end_sessions(self) -> None:
        """Gateway shutdown: every Session flushes, ends its listens and ends with OK."""
        for session in list(self.sessions):
            session.stop()

    def _deadline(self, context: Context) -> float:
        remaining = context.time_remaining()
        timeout = self._timeout
        return remaining if remaining is not None and remaining < timeout else timeout

    async def Get(self, request: pb.GetRequest, context: Context) -> pb.GetResponse:
        try:
            if isinstance(request, Undecodable):
                raise request.error
            return await self.calls.get(request, self._deadline(context))
        except Exception as exc:
            await abort(context, exc, "Get")
            raise  # not reached: abort raises

    async def Set(self, request: pb.SetRequest, context: Context) -> pb.SetResponse:
        try:
            if isinstance(request, Undecodable):
                raise request.error
            return await self.calls.set(request, self._deadline(context))
        except Exception as exc:
            await abort(context, exc, "Set")
            raise

    async def Listen(self, request: pb.ListenRequest, context: Context) -> AsyncIterator[pb.ListenResponse]:
        # Responses are yielded rather than written with context.write: grpc.aio
        # delivers 20-35% more messages per second this way (measured by bench/).
        limits = self.config.limits
        wake = _Wake()
        try:
            if isinstance(request, Undecodable):
                raise request.error
            stream = self.hub.open(
                parse_selectors(request, limits), parse_options(request.options, limits), wake.set
            )
        except Exception as exc:
            await abort(context, exc, "Listen")
            return
        try:
            try:
                await stream.start()
            except Exception as exc:
                await abort(context, exc, "Listen")
            while True:
                await wake.wait()
                while (response := stream.take()) is not None:
                    yield response
                if stream.error is not None:
                    await abort(context, stream.error, "Listen")
                if stream.ended or stream.closed:
                    return
        finally:
            stream.close()

    async def Session(self, request_iterator: AsyncIterator[pb.SessionRequest], context: Context) -> None:
        from gateway.session import run_session

        await run_session(self, context)

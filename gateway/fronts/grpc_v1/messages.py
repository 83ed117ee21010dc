"""The contract's messages into the engine's types and back.

A request is translated at the door (:func:`get_call`, :func:`set_call`), the engine's answer on
the way out (:func:`get_response`, :func:`set_response`); a message that does not parse reaches a
handler as :class:`Undecodable` (:func:`lenient`), never as grpc's own UNKNOWN with a traceback.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from google.protobuf.message import DecodeError, Message

from gateway.engine.events import Event
from gateway.engine.history import HistoryQuery, HistoryReply
from gateway.engine.types import GetCall, GetReply, PropertyRef, SetCall
from gateway.wire_values import put, received
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.backend import NO_PARAMS
from services.kernel.errors import InvalidArgument
from services.kernel.values import Value

__all__ = [
    "Undecodable",
    "get_call",
    "get_response",
    "history_query",
    "history_response",
    "lenient",
    "set_call",
    "set_response",
]


class Undecodable:
    """A request that did not parse, e.g. a string field holding bytes that are not UTF-8."""

    __slots__ = ("error",)

    def __init__(self, error: InvalidArgument) -> None:
        self.error = error


def lenient(message: type[Message]) -> Callable[[bytes], Message | Undecodable]:
    """A deserializer of ``message`` that gives :class:`Undecodable` for bytes that do not parse."""
    # grpc's own handling of a deserializer that raises is UNKNOWN and a logged traceback.
    name = message.DESCRIPTOR.full_name

    def parse(data: bytes) -> Message | Undecodable:
        try:
            return message.FromString(data)
        except DecodeError as exc:
            return Undecodable(InvalidArgument(f"the request is not a valid {name}: {exc}"))

    return parse


def _params(params: Mapping[str, str]) -> Mapping[str, str]:
    return dict(params) if params else NO_PARAMS


def get_call(request: pb.GetRequest) -> GetCall:
    """The engine's Get for ``request``."""
    params = request.parameters
    more = request.more
    if not more:
        return GetCall(request.service, request.property, dict(params) if params else NO_PARAMS)
    return GetCall(
        request.service,
        request.property,
        _params(params),
        [PropertyRef(ref.service, ref.property, _params(ref.parameters)) for ref in more],
    )


def set_call(request: pb.SetRequest) -> SetCall:
    """The engine's Set for ``request``; INVALID_ARGUMENT when it carries both text and bytes."""
    return SetCall(request.service, request.property, received(request), _params(request.parameters))


def get_response(reply: GetReply) -> pb.GetResponse:
    """``reply`` as the contract's GetResponse, each value with its source time."""
    response = pb.GetResponse()
    put(response, reply.value)
    if reply.time_ns:
        stamp = response.time
        stamp.seconds, stamp.nanos = divmod(reply.time_ns, 1_000_000_000)
    for item in reply.more:
        entry = response.more.add(service=item.service, property=item.path)
        put(entry, item.value)
        if item.time_ns:
            stamp = entry.time
            stamp.seconds, stamp.nanos = divmod(item.time_ns, 1_000_000_000)
    return response


def set_response(value: Value) -> pb.SetResponse:
    """A Set's answer as the contract's SetResponse."""
    response = pb.SetResponse()
    put(response, value)
    return response


def history_query(request: pb.HistoryRequest) -> HistoryQuery:
    """The engine's History call for ``request`` (an unset ``since`` or ``until`` is open)."""
    since = request.since.ToNanoseconds() if request.HasField("since") else None
    until = request.until.ToNanoseconds() if request.HasField("until") else None
    return HistoryQuery(request.service, request.property, since, until, request.limit)


def _event(event: Event) -> pb.Event:
    message = pb.Event(
        service=event.service,
        property=event.path,
        sequence=event.sequence,
        conflated=event.conflated,
        gap=event.gap,
        removed=event.removed,
    )
    put(message, event.value)
    message.time.seconds, message.time.nanos = divmod(event.time_ns, 1_000_000_000)
    return message


def history_response(reply: HistoryReply) -> pb.HistoryResponse:
    """A History call's answer as the contract's HistoryResponse."""
    return pb.HistoryResponse(events=[_event(e) for e in reply.events], truncated=reply.truncated)

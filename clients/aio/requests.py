"""How the SDK's calls become protobuf requests, and how answers become values."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime, timedelta
from typing import Any, Protocol, TypedDict, TypeVar

from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp

from clients.errors import Unknown
from clients.values import Value, ValueFormatError, format_value, outgoing_value
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.values import as_text

__all__ = [
    "ListenOptions",
    "Selector",
    "binary",
    "decode",
    "format_params",
    "get_many_request",
    "get_many_values",
    "listen_request",
    "set_request",
    "value_of",
]

T = TypeVar("T")

#: A Listen selector: ``(service, property)`` or ``(service, property, parameters)``.
Selector = tuple[str, str] | tuple[str, str, Mapping[str, Any]]
#: A time a History call takes: a ``datetime`` (naive is UTC), a ``timedelta`` before now, seconds
#: since the epoch, or None (open).
TimeArg = datetime | timedelta | float | None


class ListenOptions(TypedDict, total=False):
    """The keyword options of every ``listen`` (see :meth:`clients.aio.AsyncClient.listen`)."""

    params: Mapping[str, Any] | None
    updates_only: bool
    min_interval: float | None
    sample_interval: float | None
    heartbeat: float | None
    max_batch: int


class _Carrier(Protocol):
    value: str
    data: bytes

    def HasField(self, field_name: str) -> bool: ...


def value_of(message: _Carrier) -> Value:
    """The value a reply or an event carries: bytes (``data``) for a binary property, else text."""
    return message.data if message.HasField("data") else message.value


def set_request(service: str, prop: str, value: Any, params: Mapping[str, Any]) -> pb.SetRequest:
    """The SetRequest writing ``value``: bytes in ``data``, anything else as text in ``value``."""
    request = pb.SetRequest(service=service, property=prop, parameters=format_params(params))
    sent = outgoing_value(value)
    if isinstance(sent, bytes):
        request.data = sent
    else:
        request.value = sent
    return request


def format_params(params: Mapping[str, Any]) -> dict[str, str]:
    """Request parameters as text, each value by :func:`clients.values.format_value`."""
    return {name: format_value(value) for name, value in params.items()}


def _duration(seconds: float | None, what: str) -> Duration | None:
    if seconds is None:
        return None
    if seconds < 0:
        raise ValueError(f"{what} must not be negative, got {seconds}")
    d = Duration()
    d.FromNanoseconds(round(seconds * 1e9))
    return d


def _timestamp(when: TimeArg, what: str) -> Timestamp | None:
    if when is None:
        return None
    if isinstance(when, timedelta):
        when = datetime.now(UTC) - when
    elif isinstance(when, int | float) and not isinstance(when, bool):
        if not when >= 0:
            raise ValueError(f"{what} must be seconds since the epoch (not negative), got {when!r}")
        when = datetime.fromtimestamp(when, UTC)
    elif not isinstance(when, datetime):
        raise TypeError(f"{what} must be a datetime, a timedelta or seconds since the epoch, got {when!r}")
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    stamp = Timestamp()
    stamp.FromDatetime(when)
    return stamp


def history_request(service: str, prop: str, since: TimeArg, until: TimeArg, limit: int) -> pb.HistoryRequest:
    """A HistoryRequest; ``since`` and ``until`` as :data:`TimeArg` says."""
    if limit < 0:
        raise ValueError(f"limit must not be negative, got {limit}")
    return pb.HistoryRequest(
        service=service,
        property=prop,
        since=_timestamp(since, "since"),
        until=_timestamp(until, "until"),
        limit=limit,
    )


def _ref(selector: Selector) -> pb.PropertyRef:
    if len(selector) == 3:
        service, prop, params = selector
        return pb.PropertyRef(service=service, property=prop, parameters=format_params(params))
    service, prop = selector[0], selector[1]
    return pb.PropertyRef(service=service, property=prop)


def listen_request(
    service: str,
    prop: str,
    more: Sequence[Selector],
    *,
    params: Mapping[str, Any] | None = None,
    updates_only: bool = False,
    min_interval: float | None = None,
    sample_interval: float | None = None,
    heartbeat: float | None = None,
    max_batch: int = 0,
) -> pb.ListenRequest:
    """The ListenRequest for ``(service, prop)``, the further selectors and the options."""
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
        parameters=format_params(params or {}),
        more=[_ref(s) for s in more],
        options=options,
    )


def get_many_request(refs: Sequence[Selector]) -> pb.GetRequest:
    """One GetRequest for several selectors: the first in the request itself, the rest in ``more``."""
    first = _ref(refs[0])
    more = [_ref(r) for r in refs[1:]]
    return pb.GetRequest(
        service=first.service, property=first.property, parameters=first.parameters, more=more
    )


def get_many_values(resp: pb.GetResponse, n: int) -> list[Value]:
    """The ``n`` values of a GetResponse to :func:`get_many_request`, in order."""
    if len(resp.more) != n - 1:
        raise Unknown(None, f"the gateway answered {len(resp.more) + 1} values for {n} paths")
    return [value_of(resp), *(value_of(v) for v in resp.more)]


def matching_values(resp: pb.GetResponse) -> dict[str, Value]:
    """Path → value of every match of a Get with a ``*`` pattern (the gateway lists them in ``more``)."""
    return {v.property: value_of(v) for v in resp.more}


def decode(parse: Callable[[str], T], text: Value, service: str, prop: str) -> T:
    """``parse(text)``; a :class:`ValueFormatError` names the property the value came from."""
    try:
        return parse(as_text(text))
    except ValueFormatError as e:
        raise ValueFormatError(f"{service} {prop}: {e}") from None


def binary(value: Value, service: str, prop: str) -> bytes:
    """``value`` when it is bytes; a :class:`ValueFormatError` for text (not a binary property)."""
    if isinstance(value, bytes):
        return value
    raise ValueFormatError(f"{service} {prop}: the value is text, not bytes (not a binary property)")

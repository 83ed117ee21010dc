"""Errors raised by the client: one class per gRPC status code.

Every failed call raises a :class:`PropertyServiceError` subclass carrying the
status code, the server's message and the (service, property) the call was
about, so that ``except NotFound:`` reads like the failure it handles.
"""

from __future__ import annotations

import grpc

__all__ = [
    "Aborted",
    "AlreadyExists",
    "Cancelled",
    "DataLoss",
    "DeadlineExceeded",
    "FailedPrecondition",
    "GatewayUnreachable",
    "Internal",
    "InvalidArgument",
    "NotFound",
    "OutOfRange",
    "PermissionDenied",
    "PropertyServiceError",
    "ResourceExhausted",
    "Unauthenticated",
    "Unavailable",
    "Unimplemented",
    "Unknown",
    "error_for_code",
    "error_from_rpc",
]


class PropertyServiceError(Exception):
    """A call failed with a gRPC status.

    ``str(err)`` reads ``NOT_FOUND: unknown service "scoutX"``; the
    (service, property) the call was about are kept in attributes and added to
    the text when the server's message does not name them.
    """

    default_code: grpc.StatusCode = grpc.StatusCode.UNKNOWN

    def __init__(
        self,
        code: grpc.StatusCode | None,
        message: str,
        service: str = "",
        property: str = "",
    ) -> None:
        self.code = code if code is not None else self.default_code
        self.message = message
        self.service = service
        self.property = property
        super().__init__(str(self))

    def __str__(self) -> str:
        text = f"{self.code.name}: {self.message}"
        where = " ".join(x for x in (self.service, self.property) if x)
        if where and not (self.service and self.service in self.message):
            text += f" [{where}]"
        return text

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.code.name}, {self.message!r}, "
            f"service={self.service!r}, property={self.property!r})"
        )


class Cancelled(PropertyServiceError):
    """The call was cancelled (a Listen ended by Cancel)."""

    default_code = grpc.StatusCode.CANCELLED


class Unknown(PropertyServiceError):
    """The server gave no more precise reason."""

    default_code = grpc.StatusCode.UNKNOWN


class InvalidArgument(PropertyServiceError):
    """Bad path, bad value or bad parameter."""

    default_code = grpc.StatusCode.INVALID_ARGUMENT


class DeadlineExceeded(PropertyServiceError):
    """The call or the device behind it took too long."""

    default_code = grpc.StatusCode.DEADLINE_EXCEEDED


class NotFound(PropertyServiceError):
    """Unknown service or property."""

    default_code = grpc.StatusCode.NOT_FOUND


class AlreadyExists(PropertyServiceError):
    """A name that is already taken."""

    default_code = grpc.StatusCode.ALREADY_EXISTS


class PermissionDenied(PropertyServiceError):
    """The caller may not do this."""

    default_code = grpc.StatusCode.PERMISSION_DENIED


class ResourceExhausted(PropertyServiceError):
    """A limit was reached."""

    default_code = grpc.StatusCode.RESOURCE_EXHAUSTED


class FailedPrecondition(PropertyServiceError):
    """The property cannot be written (read-only) or is not in a state to accept the call."""

    default_code = grpc.StatusCode.FAILED_PRECONDITION


class Aborted(PropertyServiceError):
    """The call was aborted by the server."""

    default_code = grpc.StatusCode.ABORTED


class OutOfRange(PropertyServiceError):
    """A value or index beyond the valid range."""

    default_code = grpc.StatusCode.OUT_OF_RANGE


class Unimplemented(PropertyServiceError):
    """The server does not offer this call."""

    default_code = grpc.StatusCode.UNIMPLEMENTED


class Internal(PropertyServiceError):
    """A fault inside the server or a service."""

    default_code = grpc.StatusCode.INTERNAL


class Unavailable(PropertyServiceError):
    """The service, its device or the gateway cannot be reached right now."""

    default_code = grpc.StatusCode.UNAVAILABLE


class GatewayUnreachable(Unavailable):
    """No connection to the gateway itself could be made."""


class DataLoss(PropertyServiceError):
    """Unrecoverable loss or corruption of data."""

    default_code = grpc.StatusCode.DATA_LOSS


class Unauthenticated(PropertyServiceError):
    """The call carried no valid credentials."""

    default_code = grpc.StatusCode.UNAUTHENTICATED


_BY_CODE: dict[grpc.StatusCode, type[PropertyServiceError]] = {
    cls.default_code: cls
    for cls in (
        Cancelled,
        Unknown,
        InvalidArgument,
        DeadlineExceeded,
        NotFound,
        AlreadyExists,
        PermissionDenied,
        ResourceExhausted,
        FailedPrecondition,
        Aborted,
        OutOfRange,
        Unimplemented,
        Internal,
        Unavailable,
        DataLoss,
        Unauthenticated,
    )
}
_BY_NUMBER: dict[int, grpc.StatusCode] = {code.value[0]: code for code in grpc.StatusCode}

# Phrases grpc core uses when no connection could be made at all (as opposed
# to a service behind the gateway being unavailable).
_NO_CONNECTION = ("failed to connect to all addresses", "connection refused", "dns resolution failed")


def error_for_code(
    code: grpc.StatusCode | int, message: str, service: str = "", property: str = ""
) -> PropertyServiceError:
    """The error for a status ``code`` (a ``grpc.StatusCode`` or its number, as in a Session reply)."""
    if isinstance(code, int):
        code = _BY_NUMBER.get(code, grpc.StatusCode.UNKNOWN)
    cls = _BY_CODE.get(code, PropertyServiceError)
    return cls(code, message, service, property)


def error_from_rpc(
    err: grpc.RpcError, service: str = "", property: str = "", target: str = ""
) -> PropertyServiceError:
    """Translate a grpc error (sync or aio) into a :class:`PropertyServiceError`."""
    code_fn = getattr(err, "code", None)
    details_fn = getattr(err, "details", None)
    code = code_fn() if callable(code_fn) else grpc.StatusCode.UNKNOWN
    message = (details_fn() if callable(details_fn) else None) or str(err)
    if code == grpc.StatusCode.UNAVAILABLE and any(p in message.lower() for p in _NO_CONNECTION):
        where = f" at {target}" if target else ""
        return GatewayUnreachable(code, f"cannot reach the gateway{where} ({message})", service, property)
    return error_for_code(code, message, service, property)

"""Errors raised by the client: one class per gRPC status code.

Every failed call raises a :class:`PropertyServiceError` subclass carrying the
status code, the server's message and the (service, property) the call was
about, so that ``except NotFound:`` reads like the failure it handles.

The codes and their classes are the one table of ``services.kernel.errors``: each
class here names the service-side class it reports (``reports=``), and
:func:`error_for_code` picks the class through ``services.kernel.errors.error_class``.
The client's errors keep grpc's own ``grpc.StatusCode`` in ``code``, so they
are not service-side errors themselves (a gateway never mistakes one for a
status it may pass on).
"""

from __future__ import annotations

from typing import Any, ClassVar

import grpc

from services.kernel import errors
from services.kernel.grpc_status import GRPC_STATUS

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


#: A service-side Code → grpc's status of the same number (the gateway's own table).
_STATUS = GRPC_STATUS
#: A service-side error class → the client's class that reports it (filled as the classes are made).
_CLIENT_CLASS: dict[type[errors.PropertyError], type[PropertyServiceError]] = {}


class PropertyServiceError(Exception):
    """A call failed with a gRPC status.

    ``str(err)`` reads ``NOT_FOUND: unknown service "scoutX"``; the
    (service, property) the call was about are kept in attributes and added to
    the text when the server's message does not name them.
    """

    #: The status of the class's code, from the service-side class it ``reports``.
    default_code: ClassVar[grpc.StatusCode] = grpc.StatusCode.UNKNOWN

    def __init_subclass__(cls, reports: type[errors.PropertyError] | None = None, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if reports is not None:
            cls.default_code = _STATUS[reports.default_code]
            _CLIENT_CLASS.setdefault(reports, cls)

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


class Cancelled(PropertyServiceError, reports=errors.Cancelled):
    """The call was cancelled (a Listen ended by Cancel)."""


class Unknown(PropertyServiceError, reports=errors.Unknown):
    """The server gave no more precise reason."""


class InvalidArgument(PropertyServiceError, reports=errors.InvalidArgument):
    """Bad path, bad value or bad parameter."""


class DeadlineExceeded(PropertyServiceError, reports=errors.DeadlineExceeded):
    """The call or the device behind it took too long."""


class NotFound(PropertyServiceError, reports=errors.NotFound):
    """Unknown service or property."""


class AlreadyExists(PropertyServiceError, reports=errors.AlreadyExists):
    """A name that is already taken."""


class PermissionDenied(PropertyServiceError, reports=errors.PermissionDenied):
    """The caller may not do this."""


class ResourceExhausted(PropertyServiceError, reports=errors.ResourceExhausted):
    """A limit was reached."""


class FailedPrecondition(PropertyServiceError, reports=errors.FailedPrecondition):
    """The property cannot be written (read-only) or is not in a state to accept the call."""


class Aborted(PropertyServiceError, reports=errors.Aborted):
    """The call was aborted by the server."""


class OutOfRange(PropertyServiceError, reports=errors.OutOfRange):
    """A value or index beyond the valid range."""


class Unimplemented(PropertyServiceError, reports=errors.Unimplemented):
    """The server does not offer this call."""


class Internal(PropertyServiceError, reports=errors.Internal):
    """A fault inside the server or a service."""


class Unavailable(PropertyServiceError, reports=errors.Unavailable):
    """The service, its device or the gateway cannot be reached right now."""


class GatewayUnreachable(Unavailable):
    """No connection to the gateway itself could be made.

    ``hint`` says what to try when the failure looks like a TLS mismatch (:func:`tls_hint`); it is
    added to ``str(err)`` after the message, so ``message`` stays grpc's reason alone.
    """

    #: Every gateway address tried, in order, when a client with several gave up on all of them.
    tried: tuple[str, ...] = ()
    #: What to try, when the reason suggests one ("" when it does not).
    hint: str = ""

    def __str__(self) -> str:
        text = super().__str__()
        return f"{text} ({self.hint})" if self.hint else text


class DataLoss(PropertyServiceError, reports=errors.DataLoss):
    """Unrecoverable loss or corruption of data."""


class Unauthenticated(PropertyServiceError, reports=errors.Unauthenticated):
    """The call carried no valid credentials."""


_CLIENT_CLASS[errors.PropertyError] = PropertyServiceError
assert set(_CLIENT_CLASS) >= set(errors.ERROR_CLASSES.values()), (
    "every service-side class has its client class"
)

# Phrases grpc core begins its message with when no connection could be made at all (as opposed
# to a service behind the gateway being unavailable). Only at the start: a gateway that could not
# reach what lies behind it (a device, the owner gateway of a cluster, etcd) quotes grpc's words
# after its own, and it was reached.
_NO_CONNECTION = ("failed to connect to all addresses", "connection refused", "dns resolution failed")


# What grpc core says when a connection was accepted and then closed before any answer, or its TLS
# handshake failed: a plaintext client on a TLS port sees "Socket closed", a client without the
# certificate a mutual-TLS gateway requires the same or a handshake error. A gateway past its
# connection bound closes a new connection the same way (docs/errors.md), so the hint is a
# condition, not a verdict. A refused connection (nothing listening) is not TLS's doing: no hint.
_TLS_SIGNS = ("socket closed", "handshake", "ssl", "wrong version number", "certificate")
_NOT_TLS = ("connection refused",)

#: The hint a TLS-looking failure to reach the gateway carries (psctl's flags, the SDK's arguments).
TLS_HINT = (
    "if the gateway serves TLS, give --ca; with client certificates, --cert and --key;"
    " in the SDK, ClientCredentials(ca=, cert=, key=)"
)


def tls_hint(reason: str) -> str:
    """:data:`TLS_HINT` when ``reason`` (grpc's words for a failed connection) plausibly comes from
    a TLS mismatch, else ""."""
    lowered = reason.lower()
    if any(sign in lowered for sign in _NOT_TLS):
        return ""
    return TLS_HINT if any(sign in lowered for sign in _TLS_SIGNS) else ""


def error_for_code(
    code: grpc.StatusCode | int, message: str, service: str = "", property: str = ""
) -> PropertyServiceError:
    """The error for a status ``code`` (a ``grpc.StatusCode`` or its number, as in a Session reply)."""
    known = errors.code_for(code if isinstance(code, int) else code.value[0])
    cls = _CLIENT_CLASS[errors.error_class(known)]
    return cls(_STATUS[known], message, service, property)


def error_from_rpc(
    err: grpc.RpcError, service: str = "", property: str = "", target: str = ""
) -> PropertyServiceError:
    """Translate a grpc error (sync or aio) into a :class:`PropertyServiceError`."""
    code_fn = getattr(err, "code", None)
    details_fn = getattr(err, "details", None)
    code = code_fn() if callable(code_fn) else grpc.StatusCode.UNKNOWN
    message = (details_fn() if callable(details_fn) else None) or str(err)
    if code == grpc.StatusCode.UNAVAILABLE and message.lower().startswith(_NO_CONNECTION):
        where = f" at {target}" if target else ""
        error = GatewayUnreachable(code, f"cannot reach the gateway{where} ({message})", service, property)
        error.hint = tls_hint(message)
        return error
    return error_for_code(code, message, service, property)

"""The one error vocabulary of every Property Service.

A service, a proxy or the gateway raises :class:`PropertyError` (or one of
its subclasses). The gateway turns it into a gRPC status with the same code;
the line protocol carries the same numeric code. ``Code`` numbers are the
gRPC (google.rpc.Code) numbers, so the mapping is the identity.

:data:`ERROR_CLASSES` is the one table from a code to its error class and
:func:`error_for` builds the error for a code: the line-protocol codec, the
proxies, the gateway and the client SDK all go through it.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from types import MappingProxyType
from typing import ClassVar, Final


class Code(enum.IntEnum):
    """Status codes, numbered exactly as gRPC numbers them."""

    OK = 0
    CANCELLED = 1
    UNKNOWN = 2
    INVALID_ARGUMENT = 3
    DEADLINE_EXCEEDED = 4
    NOT_FOUND = 5
    ALREADY_EXISTS = 6
    PERMISSION_DENIED = 7
    RESOURCE_EXHAUSTED = 8
    FAILED_PRECONDITION = 9
    ABORTED = 10
    OUT_OF_RANGE = 11
    UNIMPLEMENTED = 12
    INTERNAL = 13
    UNAVAILABLE = 14
    DATA_LOSS = 15
    UNAUTHENTICATED = 16


class PropertyError(Exception):
    """A request failed; ``code`` says how, the message says why in words a user understands."""

    default_code: ClassVar[Code] = Code.UNKNOWN

    def __init__(self, message: str, code: Code | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.code = code if code is not None else self.default_code

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.code.name}: {self.message!r})"


class Cancelled(PropertyError):
    """The call was cancelled (a Listen ended by its client)."""

    default_code = Code.CANCELLED


class Unknown(PropertyError):
    """No more precise reason is known (also: a code this table does not know)."""

    default_code = Code.UNKNOWN


class InvalidArgument(PropertyError):
    """Bad path, bad value, bad parameter."""

    default_code = Code.INVALID_ARGUMENT


class DeadlineExceeded(PropertyError):
    """The device did not answer in time."""

    default_code = Code.DEADLINE_EXCEEDED


class NotFound(PropertyError):
    """Unknown service or property."""

    default_code = Code.NOT_FOUND


class AlreadyExists(PropertyError):
    """A name that is already taken."""

    default_code = Code.ALREADY_EXISTS


class PermissionDenied(PropertyError):
    """The caller may not do this."""

    default_code = Code.PERMISSION_DENIED


class ResourceExhausted(PropertyError):
    """A limit was reached (line length, value size, subscriptions, ...)."""

    default_code = Code.RESOURCE_EXHAUSTED


class FailedPrecondition(PropertyError):
    """The property is not in a state to accept the call (e.g. a Get of a write-only property)."""

    default_code = Code.FAILED_PRECONDITION


class ReadOnly(FailedPrecondition):
    """Set on a property that cannot be written."""


class Aborted(PropertyError):
    """The call was aborted."""

    default_code = Code.ABORTED


class OutOfRange(PropertyError):
    """A value or index beyond the valid range."""

    default_code = Code.OUT_OF_RANGE


class Unimplemented(PropertyError):
    """The service or device does not offer this call."""

    default_code = Code.UNIMPLEMENTED


class Internal(PropertyError):
    """A bug: the service raised something it should not have."""

    default_code = Code.INTERNAL


class Unavailable(PropertyError):
    """The device or service cannot be reached right now."""

    default_code = Code.UNAVAILABLE


class DataLoss(PropertyError):
    """Unrecoverable loss or corruption of data (e.g. a line that fails its checksum)."""

    default_code = Code.DATA_LOSS


class Unauthenticated(PropertyError):
    """The call carried no valid credentials."""

    default_code = Code.UNAUTHENTICATED


#: The one table from a status code to the error a user catches. ``OK`` has no error class.
ERROR_CLASSES: Final[Mapping[Code, type[PropertyError]]] = MappingProxyType(
    {
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
)

assert set(ERROR_CLASSES) == set(Code) - {Code.OK}, "every failure code has its class"


def code_for(number: int) -> Code:
    """The :class:`Code` numbered ``number`` (as read off a wire); UNKNOWN for a number no code has."""
    try:
        return Code(number)
    except ValueError:
        return Code.UNKNOWN


def error_class(code: Code) -> type[PropertyError]:
    """The class of the error that reports ``code`` (the base :class:`PropertyError` for OK)."""
    return ERROR_CLASSES.get(code, PropertyError)


def error_for(code: Code | int, message: str) -> PropertyError:
    """The error that reports ``code`` (a :class:`Code` or its number) with ``message``.

    ``except NotFound`` matches what this returns for NOT_FOUND, wherever the
    code came from: an ERR line of a device, a remote gateway's status, a
    Session reply. A number no code has becomes UNKNOWN.
    """
    known = code if isinstance(code, Code) else code_for(code)
    return error_class(known)(message, known)

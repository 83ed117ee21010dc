"""The one error vocabulary of every Property Service.

A service, a proxy or the gateway raises :class:`PropertyError` (or one of
its subclasses). The gateway turns it into a gRPC status with the same code;
the line protocol carries the same numeric code. ``Code`` numbers are the
gRPC (google.rpc.Code) numbers, so the mapping is the identity.
"""

from __future__ import annotations

import enum
from typing import ClassVar


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


class NotFound(PropertyError):
    """Unknown service or property."""

    default_code = Code.NOT_FOUND


class InvalidArgument(PropertyError):
    """Bad path, bad value, bad parameter."""

    default_code = Code.INVALID_ARGUMENT


class ReadOnly(PropertyError):
    """Set on a property that cannot be written."""

    default_code = Code.FAILED_PRECONDITION


class AlreadyExists(PropertyError):
    """A name that is already taken."""

    default_code = Code.ALREADY_EXISTS


class PermissionDenied(PropertyError):
    default_code = Code.PERMISSION_DENIED


class Unauthenticated(PropertyError):
    default_code = Code.UNAUTHENTICATED


class Unavailable(PropertyError):
    """The device or service cannot be reached right now."""

    default_code = Code.UNAVAILABLE


class DeadlineExceeded(PropertyError):
    """The device did not answer in time."""

    default_code = Code.DEADLINE_EXCEEDED


class ResourceExhausted(PropertyError):
    """A limit was reached (line length, value size, subscriptions, ...)."""

    default_code = Code.RESOURCE_EXHAUSTED


class Internal(PropertyError):
    """A bug: the service raised something it should not have."""

    default_code = Code.INTERNAL

"""Errors as gRPC statuses, and statuses as errors, through the one table of ``services.errors``.

``Code`` numbers are the gRPC (google.rpc.Code) numbers, so the conversion is
the identity on numbers; it lives here so that every part of the gateway
turns an error into a status, and a remote status into an error
(:func:`error_from_status`, of the class ``services.errors.error_for``
picks), the same way. Every message leaves through here clipped to
:data:`MAX_MESSAGE_CHARS`. Which call returns which code when is documented in
``docs/errors.md``.
"""

from __future__ import annotations

import logging
from typing import Final

import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.errors import Code, Internal, PropertyError, error_for

log = logging.getLogger(__name__)

#: Most characters of a status message. grpc carries the message in a trailer, and a
#: peer refuses trailers over 16 KiB (grpc's default metadata hard limit) with
#: RESOURCE_EXHAUSTED instead of the real status; 1,000 characters say what happened
#: and stay far below it, even when every character takes four bytes in UTF-8.
MAX_MESSAGE_CHARS = 1000

#: Code → grpc.StatusCode, matched by number.
GRPC_STATUS: Final[dict[Code, grpc.StatusCode]] = {
    code: status for status in grpc.StatusCode for code in Code if status.value[0] == code.value
}

assert len(GRPC_STATUS) == len(Code), "every Code has a gRPC status of the same number"

#: grpc.StatusCode → Code, the reverse of :data:`GRPC_STATUS`.
CODE_OF_STATUS: Final[dict[grpc.StatusCode, Code]] = {status: code for code, status in GRPC_STATUS.items()}


def error_from_status(status: grpc.StatusCode, message: str) -> PropertyError:
    """The error for a gRPC status (a remote gateway's answer): ``NOT_FOUND`` → ``NotFound``."""
    return error_for(CODE_OF_STATUS.get(status, Code.UNKNOWN), message)


def error_from_remote(exc: grpc.aio.AioRpcError, label: str, timeout: float) -> PropertyError:
    """A remote gateway's failed call as an error whose message starts with ``label`` (which remote
    said it). Its message is cut to :data:`MAX_MESSAGE_CHARS` (a remote is not trusted to be brief),
    and a deadline of this side's own (grpc's bare "Deadline Exceeded", after ``timeout`` seconds)
    is said as such."""
    status = exc.code()
    details = (exc.details() or status.name)[:MAX_MESSAGE_CHARS]
    if status is grpc.StatusCode.DEADLINE_EXCEEDED and details == "Deadline Exceeded":
        details = f"no answer within {timeout:g} s"
    return error_from_status(status, f"{label}: {details}")


def to_property_error(exc: BaseException, what: str = "request") -> PropertyError:
    """Turn any exception into a :class:`PropertyError`.

    A ``PropertyError`` passes unchanged. Anything else is a bug in a service
    or in the gateway: it is logged with its traceback and becomes INTERNAL,
    with a message that names ``what`` failed but leaks no internals.
    """
    if isinstance(exc, PropertyError):
        return exc
    log.error("%s failed with an unexpected error", what, exc_info=exc, extra={"code": "INTERNAL"})
    return Internal(f"internal error in {what}: {type(exc).__name__}")


def clip_message(message: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``message`` cut to at most ``limit`` characters, saying how much was left out."""
    if len(message) <= limit:
        return message
    tail = f"... ({len(message) - limit} more characters)"
    return message[: limit - len(tail)] + tail


def status_message(err: PropertyError) -> pb.Status:
    """``err`` as the contract's ``Status`` message (used on Session replies), clipped."""
    return pb.Status(code=int(err.code), message=clip_message(err.message))


async def abort(context: grpc.aio.ServicerContext[object, object], exc: BaseException, what: str) -> None:
    """End the call with the status for ``exc``, its message clipped (never returns)."""
    err = to_property_error(exc, what)
    if log.isEnabledFor(logging.DEBUG):
        log.debug("%s: %s", what, err.message, extra={"code": err.code.name})
    await context.abort(GRPC_STATUS[err.code], clip_message(err.message))

"""Errors as gRPC statuses, and statuses as errors: the one ``Code`` → ``grpc.StatusCode`` table.

``Code`` numbers are the gRPC (google.rpc.Code) numbers, so the table is the
identity on numbers; it lives here so that the gRPC front turns an error into a
status, and the gRPC proxies turn a remote status into an error
(:func:`error_from_status`, of the class ``services.kernel.errors.error_for`` picks),
the same way. Every message leaves clipped (:func:`gateway.engine.status.clip_message`).
Which call returns which code when is documented in ``docs/errors.md``.
"""

from __future__ import annotations

import logging

import grpc

from gateway.engine.status import MAX_MESSAGE_CHARS, clip_message, to_property_error
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.errors import Code, PropertyError, error_for
from services.kernel.grpc_status import CODE_OF_STATUS, GRPC_STATUS

__all__ = [
    "CODE_OF_STATUS",
    "GRPC_STATUS",
    "abort",
    "error_from_remote",
    "error_from_status",
    "status_message",
]

log = logging.getLogger(__name__)


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


def status_message(err: PropertyError) -> pb.Status:
    """``err`` as the contract's ``Status`` message (used on Session replies), clipped."""
    return pb.Status(code=int(err.code), message=clip_message(err.message))


async def abort(context: grpc.aio.ServicerContext[object, object], exc: BaseException, what: str) -> None:
    """End the call with the status for ``exc``, its message clipped (never returns)."""
    err = to_property_error(exc, what)
    if log.isEnabledFor(logging.DEBUG):
        log.debug("%s: %s", what, err.message, extra={"code": err.code.name})
    await context.abort(GRPC_STATUS[err.code], clip_message(err.message))

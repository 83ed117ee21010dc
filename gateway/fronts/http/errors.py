"""Errors as JSON: ``{"error": {"code": "NOT_FOUND", "message": "..."}}`` with the matching HTTP status.

The code is the gRPC code name of the one error table (``services.kernel.errors.Code``); the
status is Google's mapping of gRPC codes to HTTP (``google/rpc/code.proto``), so a client
of either front end sees the same code for the same failure. Messages leave clipped by
:func:`gateway.engine.status.clip_message`, as on the gRPC port.
"""

from __future__ import annotations

import json
import logging
from typing import Final

from aiohttp import web

from gateway.engine.status import clip_message, to_property_error
from services.kernel.errors import Code, PropertyError, ResourceExhausted

log = logging.getLogger(__name__)

#: Code → HTTP status, as google/rpc/code.proto maps them.
HTTP_STATUS: Final[dict[Code, int]] = {
    Code.OK: 200,
    Code.CANCELLED: 499,
    Code.UNKNOWN: 500,
    Code.INVALID_ARGUMENT: 400,
    Code.DEADLINE_EXCEEDED: 504,
    Code.NOT_FOUND: 404,
    Code.ALREADY_EXISTS: 409,
    Code.PERMISSION_DENIED: 403,
    Code.RESOURCE_EXHAUSTED: 429,
    Code.FAILED_PRECONDITION: 400,
    Code.ABORTED: 409,
    Code.OUT_OF_RANGE: 400,
    Code.UNIMPLEMENTED: 501,
    Code.INTERNAL: 500,
    Code.UNAVAILABLE: 503,
    Code.DATA_LOSS: 500,
    Code.UNAUTHENTICATED: 401,
}

assert len(HTTP_STATUS) == len(Code), "every Code has an HTTP status"

#: A body over ``http.max_body``, a stream over ``http.max_streams`` and one over
#: ``http.max_streams_per_client`` are RESOURCE_EXHAUSTED with the status HTTP has for each:
#: 413 (the request is too large), 503 (come back later) and 429 (this client asks too much).
PAYLOAD_TOO_LARGE = 413
TOO_MANY_STREAMS = 503
TOO_MANY_REQUESTS = 429


def error_json(err: PropertyError) -> dict[str, str]:
    """``{"code", "message"}`` of ``err``, its message clipped."""
    return {"code": err.code.name, "message": clip_message(err.message)}


def error_response(exc: BaseException, what: str = "request", status: int | None = None) -> web.Response:
    """The JSON error response for ``exc`` (anything but a PropertyError is INTERNAL, logged)."""
    err = to_property_error(exc, what)
    if log.isEnabledFor(logging.DEBUG):  # as a failed gRPC call is (gateway.fronts.grpc_v1.status.abort)
        log.debug("%s: %s", what, err.message, extra={"code": err.code.name})
    body = json.dumps({"error": error_json(err)}, ensure_ascii=False)
    return web.Response(
        status=status or HTTP_STATUS[err.code],
        text=body,
        content_type="application/json",
        headers={"Cache-Control": "no-store"},
    )


def connection_refusal(reason: str) -> bytes:
    """What a connection refused at the door reads (plain HTTP): a 503 whose JSON names the bound."""
    err = ResourceExhausted(f"too many connections: {reason}; try again later")
    body = json.dumps({"error": error_json(err)}).encode()
    head = (
        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\nRetry-After: 1\r\nConnection: close\r\n\r\n"
    )
    return head.encode() + body

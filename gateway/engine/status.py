"""Any exception as a :class:`~services.kernel.errors.PropertyError`, and a message clipped to fit a status.

Every front end turns what a call raised into the error it reports through
:func:`to_property_error` (a bug in a service becomes INTERNAL, logged once
with its traceback), and clips its message with :func:`clip_message`; each
front then says it in its own terms (the gRPC front's status table is
:mod:`gateway.fronts.grpc_v1.status`, the HTTP front's :mod:`gateway.fronts.http.errors`).
Which call returns which code when is documented in ``docs/errors.md``.
"""

from __future__ import annotations

import logging

from services.kernel.errors import Internal, PropertyError

log = logging.getLogger(__name__)

#: Most characters of a status message. grpc carries the message in a trailer, and a
#: peer refuses trailers over 16 KiB (grpc's default metadata hard limit) with
#: RESOURCE_EXHAUSTED instead of the real status; 1,000 characters say what happened
#: and stay far below it, even when every character takes four bytes in UTF-8.
MAX_MESSAGE_CHARS = 1000


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

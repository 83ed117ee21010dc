"""Log lines: today's text or one JSON object a line, and the request each line belongs to.

A call sets :data:`current_request` (a :class:`RequestContext`: the request id and, where known,
the service, property and subject); every log line written while it runs, by any module, carries
those fields, because asyncio copies the context into the tasks and callbacks a call starts. A
line may add or override them with ``extra={"service": ..., "code": ...}``.

The formatters read the context when the line is written: a handler that writes at once (the
gateway's, on stderr) is in the call's context then.
"""

from __future__ import annotations

import json
import logging
import random
import sys
import time
from contextvars import Context, ContextVar, copy_context
from typing import Final

__all__ = [
    "FIELDS",
    "LOG_FORMATS",
    "MAX_REQUEST_ID_CHARS",
    "REQUEST_ID_HEADER",
    "JsonFormatter",
    "RequestContext",
    "TextFormatter",
    "background_service",
    "current_request",
    "current_request_id",
    "new_request_id",
    "outside_requests",
    "request_id_from",
    "setup_logging",
]

#: The formats of ``--log-format`` and ``[gateway] log_format``.
LOG_FORMATS: Final = ("text", "json")

#: The metadata key (gRPC) and header (HTTP) a client chooses its request id with; echoed back.
REQUEST_ID_HEADER: Final = "x-request-id"

#: Longest request id taken from a client: a UUID is 36, a W3C trace id 32; the id is copied into
#: every log line of the call, so a client must not make those lines arbitrarily long.
MAX_REQUEST_ID_CHARS: Final = 64

#: The optional fields of a JSON line, in the order they are written.
FIELDS: Final = ("request_id", "service", "property", "subject", "code")


class RequestContext:
    """What the log lines of one request say about it; ``None`` fields are not known."""

    __slots__ = ("property", "request_id", "service", "subject")

    def __init__(
        self,
        request_id: str,
        service: str | None = None,
        property: str | None = None,
        subject: str | None = None,
    ) -> None:
        self.request_id = request_id
        self.service = service
        self.property = property
        self.subject = subject


#: The request being served in this context; None outside any request.
current_request: ContextVar[RequestContext | None] = ContextVar("current_request", default=None)


#: The service a task outside any request works for (a proxy's connection, a device's process):
#: its lines carry it as ``service``, so that one service's lines can be selected.
background_service: ContextVar[str | None] = ContextVar("background_service", default=None)


def outside_requests(service: str | None = None) -> Context:
    """A copy of the current context without a request: for a task that outlives the call that
    starts it (a proxy's connection, a poll), whose lines belong to no one request. With
    ``service``, the task's lines (and those of the tasks it starts) name that service."""
    context = copy_context()
    context.run(current_request.set, None)
    if service is not None:
        context.run(background_service.set, service)
    return context


def current_request_id() -> str | None:
    """The id of the request being served here, or None."""
    context = current_request.get()
    return context.request_id if context is not None else None


def new_request_id() -> str:
    """A fresh request id: 16 hex digits (64 random bits; unique enough to grep a day of logs).

    The bits come from the process's pseudo-random generator (seeded from the OS, and again in a
    forked child), not from ``secrets``: an id must be unique, not unguessable, and ``secrets``
    asks the kernel on every call, a system call on the path of every unary call.
    """
    return f"{random.getrandbits(64):016x}"


def request_id_from(value: str | bytes | None) -> str:
    """The client's chosen id when it is usable (printable ASCII, at most 64 characters), else a new one."""
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    if value and len(value) <= MAX_REQUEST_ID_CHARS and value.isascii() and value.isprintable():
        return value.strip() or new_request_id()
    return new_request_id()


def _fields(record: logging.LogRecord) -> dict[str, str]:
    """The request fields of ``record``: the context's, overridden by the line's own ``extra``."""
    found: dict[str, str] = {}
    context = current_request.get()
    if context is not None:
        for name in ("request_id", "service", "property", "subject"):
            value = getattr(context, name)
            if value is not None:
                found[name] = value
    if "service" not in found:
        service = background_service.get()
        if service is not None:
            found["service"] = service
    for name in FIELDS:
        value = record.__dict__.get(name)
        if value is not None:
            found[name] = str(value)
    return found


class TextFormatter(logging.Formatter):
    """``TIME LEVEL LOGGER: MESSAGE``, then ``[request ID]`` when the line belongs to a request."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        request_id = record.__dict__.get("request_id") or current_request_id()
        if request_id is None:
            return line
        head, newline, rest = line.partition("\n")  # after the message, before a traceback
        return f"{head} [request {request_id}]{newline}{rest}"


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time, level, logger, message, the known request fields, and
    ``exception`` (the traceback as one string) when there is one.

    ``time`` is UTC in RFC 3339 with milliseconds, which log stores parse without a format hint.
    """

    def format(self, record: logging.LogRecord) -> str:
        seconds = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        line: dict[str, str] = {
            "time": f"{seconds}.{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        line.update(_fields(record))
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            line["exception"] = record.exc_text
        # ensure_ascii: a device's bytes in a message never break the line or the reader's decoder.
        return json.dumps(line, ensure_ascii=True)


def setup_logging(level: str, log_format: str = "text") -> None:
    """Log lines to stderr at ``level`` in ``log_format`` (``text`` or ``json``)."""
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {', '.join(LOG_FORMATS)}, got {log_format!r}")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if log_format == "json" else TextFormatter())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())

"""The rosbridge v2 protocol's messages, read and written without I/O.

rosbridge_suite's ROSBRIDGE_PROTOCOL.md: every message is a JSON object with an ``op`` and
mostly an ``id`` the answer repeats. :func:`parse` reads one text frame into an operation
(:class:`Subscribe`, :class:`Publish`, :class:`CallService`, …) or raises :class:`BadMessage`,
which the connection answers with a ``status`` message at level ``error`` naming the op and id,
as rosbridge does; the writers (:func:`publish`, :func:`service_response`, :func:`status`,
:func:`fragments`) build what the gateway sends.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from services.kernel.errors import InvalidArgument

#: Status levels, least to most severe (``set_level`` picks the least a client hears).
LEVELS = ("info", "warning", "error", "none")
#: An id is echoed in every answer; a longer one is refused rather than kept.
MAX_ID_CHARS = 256
#: The compression a client may ask for: only "none" is spoken (png and cbor are not).
COMPRESSIONS = ("none", "")


class BadMessage(InvalidArgument):
    """A message that cannot be acted on; ``op`` and ``id`` as far as they could be read."""

    def __init__(self, message: str, op: str = "", ident: str | None = None) -> None:
        super().__init__(message)
        self.op = op
        self.ident = ident


@dataclass(frozen=True, slots=True)
class Subscribe:
    ident: str | None
    topic: str
    type: str
    #: Milliseconds between messages at most (0: every change).
    throttle_rate: int
    #: Messages kept for a slow reader (0 or 1: the latest; the gateway always keeps the latest only).
    queue_length: int
    #: Largest message sent whole; a longer one goes as ``fragment`` ops (0: never fragmented).
    fragment_size: int


@dataclass(frozen=True, slots=True)
class Unsubscribe:
    ident: str | None
    topic: str


@dataclass(frozen=True, slots=True)
class Advertise:
    ident: str | None
    topic: str
    type: str


@dataclass(frozen=True, slots=True)
class Unadvertise:
    ident: str | None
    topic: str


@dataclass(frozen=True, slots=True)
class Publish:
    ident: str | None
    topic: str
    msg: Any


@dataclass(frozen=True, slots=True)
class CallService:
    ident: str | None
    service: str
    args: Any
    fragment_size: int
    #: Seconds the client waits for the answer (roslibjs sends it; 0: the gateway's call timeout).
    timeout: float = 0.0


@dataclass(frozen=True, slots=True)
class Auth:
    """rosauth's ``auth`` op; the gateway reads its bearer token from ``token`` or, so that
    roslibjs's and roslibpy's ``authenticate(mac, ...)`` work unchanged, from ``mac``."""

    token: str


@dataclass(frozen=True, slots=True)
class SetLevel:
    ident: str | None
    level: str


Operation = Subscribe | Unsubscribe | Advertise | Unadvertise | Publish | CallService | Auth | SetLevel


def _ident(message: Mapping[str, Any], op: str) -> str | None:
    ident = message.get("id")
    if ident is None:
        return None
    if isinstance(ident, int | float) and not isinstance(ident, bool):
        ident = str(ident)
    if not isinstance(ident, str) or len(ident) > MAX_ID_CHARS:
        raise BadMessage(f"{op}: id must be a string of at most {MAX_ID_CHARS} characters", op)
    return ident


def _text(message: Mapping[str, Any], key: str, op: str, ident: str | None, required: bool = True) -> str:
    value = message.get(key)
    if value is None and not required:
        return ""
    if not isinstance(value, str) or (required and not value):
        raise BadMessage(f"{op}: {key!r} must be a non-empty string", op, ident)
    return value


def _count(message: Mapping[str, Any], key: str, op: str, ident: str | None) -> int:
    value = message.get(key)
    if value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise BadMessage(f"{op}: {key!r} must be a number of at least 0", op, ident)
    return int(value)


def _seconds(message: Mapping[str, Any], key: str, op: str, ident: str | None) -> float:
    value = message.get(key)
    if value is None:
        return 0.0
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise BadMessage(f"{op}: {key!r} must be a number of seconds of at least 0", op, ident)
    return float(value)


def _compression(message: Mapping[str, Any], op: str, ident: str | None) -> None:
    compression = message.get("compression") or ""
    if compression not in COMPRESSIONS:
        raise BadMessage(
            f"{op}: compression {str(compression)[:50]!r} is not spoken here (send none)", op, ident
        )


def parse(text: str | bytes) -> Operation:
    """One message as an operation; BadMessage for JSON that is not one rosbridge op we speak."""
    try:
        message = json.loads(text)
    except (ValueError, RecursionError):
        raise BadMessage("the message is not JSON") from None
    if not isinstance(message, dict):
        raise BadMessage("a message must be a JSON object with an 'op'")
    op = message.get("op")
    if not isinstance(op, str):
        raise BadMessage("a message must have an 'op' string")
    ident = _ident(message, op[:50])
    if op == "subscribe":
        _compression(message, op, ident)
        return Subscribe(
            ident,
            _text(message, "topic", op, ident),
            _text(message, "type", op, ident, required=False),
            _count(message, "throttle_rate", op, ident),
            _count(message, "queue_length", op, ident),
            _count(message, "fragment_size", op, ident),
        )
    if op == "unsubscribe":
        return Unsubscribe(ident, _text(message, "topic", op, ident))
    if op == "publish":
        if "msg" not in message:
            raise BadMessage("publish: the message has no 'msg'", op, ident)
        return Publish(ident, _text(message, "topic", op, ident), message["msg"])
    if op == "advertise":
        return Advertise(
            ident, _text(message, "topic", op, ident), _text(message, "type", op, ident, required=False)
        )
    if op == "unadvertise":
        return Unadvertise(ident, _text(message, "topic", op, ident))
    if op == "call_service":
        _compression(message, op, ident)
        return CallService(
            ident,
            _text(message, "service", op, ident),
            message.get("args", {}),
            _count(message, "fragment_size", op, ident),
            _seconds(message, "timeout", op, ident),
        )
    if op == "auth":
        token = message.get("token", message.get("mac"))
        if not isinstance(token, str) or not token:
            raise BadMessage("auth: give the bearer token as 'token' (or 'mac')", op, ident)
        return Auth(token)
    if op == "set_level":
        level = message.get("level")
        if level not in LEVELS:
            raise BadMessage(f"set_level: level must be one of {', '.join(LEVELS)}", op, ident)
        return SetLevel(ident, level)
    raise BadMessage(
        f"unknown op {op[:50]!r} (spoken: subscribe, unsubscribe, publish, advertise, unadvertise,"
        " call_service, auth, set_level)",
        op[:50],
        ident,
    )


def _dump(message: Mapping[str, Any]) -> str:
    return json.dumps(message, ensure_ascii=False, separators=(",", ":"), allow_nan=False)


def publish(topic: str, msg: Mapping[str, Any]) -> str:
    """A message of a subscribed topic."""
    return _dump({"op": "publish", "topic": topic, "msg": msg})


def service_response(ident: str | None, service: str, values: Any, result: bool) -> str:
    """The answer to a ``call_service``: ``values`` the response (an error's text when not ``result``)."""
    message: dict[str, Any] = {
        "op": "service_response",
        "service": service,
        "values": values,
        "result": result,
    }
    if ident is not None:
        message["id"] = ident
    return _dump(message)


def status(level: str, text: str, ident: str | None = None) -> str:
    """A ``status`` message (rosbridge's way to tell a client what went wrong with its op)."""
    message: dict[str, Any] = {"op": "status", "level": level, "msg": text}
    if ident is not None:
        message["id"] = ident
    return _dump(message)


def heard(level: str, least: str) -> bool:
    """Whether a status of ``level`` reaches a client that asked for ``least`` (``set_level``)."""
    return LEVELS.index(level) >= LEVELS.index(least)


def fragments(message: str, size: int, ident: str) -> Iterator[str]:
    """``message`` whole when it has at most ``size`` characters (0: any), else as ``fragment``
    ops of ``size`` characters of it each, numbered from 0, which the client joins again."""
    if size <= 0 or len(message) <= size:
        yield message
        return
    total = math.ceil(len(message) / size)
    for num in range(total):
        piece = message[num * size : (num + 1) * size]
        yield _dump({"op": "fragment", "id": ident, "data": piece, "num": num, "total": total})

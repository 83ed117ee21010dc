"""The Foxglove WebSocket protocol's messages, read and written without I/O.

Text messages are JSON objects named by ``op``; binary ones start with a one-byte opcode, and
their integers are little-endian (the protocol's spec, "Binary messages"). This module turns the
server's messages into bytes or text and a client's into checked values; :mod:`.connection`
does the socket. A client's mistake is a :class:`ProtocolError`, which the connection answers
with an error ``status`` message and goes on: nothing a client sends ends the connection but a
close.
"""

from __future__ import annotations

import enum
import json
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

#: The subprotocol names a client may offer: ``foxglove.websocket.v1`` is the one the
#: ``@foxglove/ws-protocol`` clients and Foxglove's app offer; ``foxglove.sdk.v1`` the one
#: ``foxglove-sdk``'s own server accepts. The messages are the same.
SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")

JSON_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"

#: What this server does beyond sending messages (the spec's "Server Info" capabilities).
CAPABILITIES = ("clientPublish", "parameters", "parametersSubscribe", "services")


class ServerOp(enum.IntEnum):
    """Opcodes of the server's binary messages."""

    MESSAGE_DATA = 0x01
    TIME = 0x02
    SERVICE_CALL_RESPONSE = 0x03


class ClientOp(enum.IntEnum):
    """Opcodes of a client's binary messages."""

    MESSAGE_DATA = 0x01
    SERVICE_CALL_REQUEST = 0x02


class Level(enum.IntEnum):
    """A status message's level."""

    INFO = 0
    WARNING = 1
    ERROR = 2


class ProtocolError(Exception):
    """A client's message the protocol does not allow; its text is the status message sent back."""


_MESSAGE_HEAD = struct.Struct("<BIQ")
_CALL_HEAD = struct.Struct("<BIII")
_CLIENT_DATA_HEAD = struct.Struct("<BI")
#: The most characters of a client's text echoed back in a status message.
_ECHO = 100


def text(message: Mapping[str, Any]) -> str:
    """A server message as the text frame that carries it."""
    return json.dumps(message, ensure_ascii=False, separators=(",", ":"))


def server_info(name: str, session_id: str) -> str:
    return text(
        {
            "op": "serverInfo",
            "name": name,
            "capabilities": list(CAPABILITIES),
            "supportedEncodings": [JSON_ENCODING],
            "metadata": {},
            "sessionId": session_id,
        }
    )


def status(level: Level, message: str, status_id: str | None = None) -> str:
    body: dict[str, Any] = {"op": "status", "level": int(level), "message": message}
    if status_id is not None:
        body["id"] = status_id
    return text(body)


def message_head(subscription: int, time_ns: int) -> bytes:
    """The head of a Message Data frame; the JSON payload follows it."""
    return _MESSAGE_HEAD.pack(ServerOp.MESSAGE_DATA, subscription, time_ns)


def service_call_response(service_id: int, call_id: int, encoding: str, payload: bytes) -> bytes:
    name = encoding.encode()
    return _CALL_HEAD.pack(ServerOp.SERVICE_CALL_RESPONSE, service_id, call_id, len(name)) + name + payload


def service_call_failure(service_id: int, call_id: int, message: str) -> str:
    return text({"op": "serviceCallFailure", "serviceId": service_id, "callId": call_id, "message": message})


# --- what a client sends -------------------------------------------------------------------------


def read_json(frame: str) -> tuple[str, Mapping[str, Any]]:
    """A text frame as its ``op`` and body."""
    try:
        body = json.loads(frame)
    except ValueError as exc:
        raise ProtocolError(f"a text message must be a JSON object: {exc}") from None
    if not isinstance(body, dict) or not isinstance(body.get("op"), str):
        raise ProtocolError('a text message must be a JSON object with a string "op"')
    return body["op"], body


def uint32(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**32:
        raise ProtocolError(f"{what} must be an integer from 0 to 2^32-1, not {json.dumps(value)[:_ECHO]}")
    return value


def string(value: Any, what: str) -> str:
    if not isinstance(value, str):
        raise ProtocolError(f"{what} must be a string, not {json.dumps(value)[:_ECHO]}")
    return value


def items(body: Mapping[str, Any], key: str, limit: int) -> Sequence[Any]:
    """``body[key]``, a list of at most ``limit`` items."""
    value = body.get(key)
    if not isinstance(value, list):
        raise ProtocolError(f'"{key}" must be a list')
    if len(value) > limit:
        raise ProtocolError(f'"{key}" may hold at most {limit} items, not {len(value)}')
    return value


@dataclass(frozen=True, slots=True)
class Subscription:
    id: int
    channel: int


def subscriptions(body: Mapping[str, Any], limit: int) -> list[Subscription]:
    out = []
    for item in items(body, "subscriptions", limit):
        if not isinstance(item, dict):
            raise ProtocolError("each subscription must be an object {id, channelId}")
        out.append(
            Subscription(
                uint32(item.get("id"), "subscription id"), uint32(item.get("channelId"), "channelId")
            )
        )
    return out


@dataclass(frozen=True, slots=True)
class ClientChannel:
    """A channel a client advertised to publish on."""

    id: int
    topic: str
    encoding: str
    schema_name: str


def client_channels(body: Mapping[str, Any], limit: int) -> list[ClientChannel]:
    out = []
    for item in items(body, "channels", limit):
        if not isinstance(item, dict):
            raise ProtocolError("each channel must be an object {id, topic, encoding, schemaName}")
        out.append(
            ClientChannel(
                uint32(item.get("id"), "channel id"),
                string(item.get("topic"), "topic"),
                string(item.get("encoding"), "encoding"),
                string(item.get("schemaName", ""), "schemaName"),
            )
        )
    return out


def ids(body: Mapping[str, Any], key: str, limit: int) -> list[int]:
    return [uint32(item, key) for item in items(body, key, limit)]


def names(body: Mapping[str, Any], key: str, limit: int) -> list[str]:
    return [string(item, key) for item in items(body, key, limit)]


@dataclass(frozen=True, slots=True)
class ClientMessage:
    """A Client Message Data frame: a payload on a channel the client advertised."""

    channel: int
    payload: bytes


@dataclass(frozen=True, slots=True)
class ServiceCallRequest:
    service: int
    call: int
    encoding: str
    payload: bytes


def read_binary(frame: bytes) -> ClientMessage | ServiceCallRequest:
    """A client's binary frame by its opcode."""
    if not frame:
        raise ProtocolError("an empty binary message has no opcode")
    opcode = frame[0]
    if opcode == ClientOp.MESSAGE_DATA:
        if len(frame) < _CLIENT_DATA_HEAD.size:
            raise ProtocolError("a client message is shorter than its head (opcode and channel id)")
        _, channel = _CLIENT_DATA_HEAD.unpack_from(frame)
        return ClientMessage(channel, frame[_CLIENT_DATA_HEAD.size :])
    if opcode == ClientOp.SERVICE_CALL_REQUEST:
        if len(frame) < _CALL_HEAD.size:
            raise ProtocolError("a service call request is shorter than its head")
        _, service, call, length = _CALL_HEAD.unpack_from(frame)
        start = _CALL_HEAD.size
        if length > len(frame) - start:
            raise ProtocolError("a service call request's encoding runs past its end")
        try:
            encoding = frame[start : start + length].decode()
        except UnicodeDecodeError:
            raise ProtocolError("a service call request's encoding is not UTF-8") from None
        return ServiceCallRequest(service, call, encoding, frame[start + length :])
    raise ProtocolError(f"unknown binary opcode 0x{opcode:02x} (known: 0x01 message, 0x02 service call)")


def read_payload(payload: bytes, what: str) -> Mapping[str, Any]:
    """A JSON payload (a published message, a service call's request) as an object."""
    try:
        body = json.loads(payload)
    except ValueError as exc:
        raise ProtocolError(f"{what} is not JSON: {exc}") from None
    if not isinstance(body, dict):
        raise ProtocolError(f"{what} must be a JSON object")
    return body

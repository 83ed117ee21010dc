"""The Property Service line protocol (docs/device-spec.md) as a sans-IO codec.

``encode(frame) -> bytes`` writes one line; ``LineReceiver.receive_data(bytes)``
returns the frames of the lines completed so far, bad lines as ``BadLine``.
No sockets here: the device server, the gateway's proxies and its line
listener all drive this one codec.
"""

from services.kernel.line_protocol._checksum import crc8
from services.kernel.line_protocol._errors import LineProtocolError
from services.kernel.line_protocol._escaping import (
    BINARY_PREFIX,
    decode_value,
    encode_value,
    escape_field,
    escape_value,
    unescape,
)
from services.kernel.line_protocol._frames import (
    MAX_INFLIGHT,
    MAX_LINE,
    MAX_RXBUF,
    MIN_MAX_LINE,
    MIN_RXBUF,
    PROTOCOL_REVISION,
    PROTOCOL_VERSION,
    TAGGED,
    BadLine,
    Cancel,
    ErrorReply,
    Event,
    Frame,
    Get,
    Gone,
    Hello,
    HelloRequest,
    LineValue,
    Listen,
    Ok,
    Ping,
    Pong,
    Reply,
    Request,
    Set,
    Unlisten,
)
from services.kernel.line_protocol._reader import decode_line, tag_of
from services.kernel.line_protocol._receivebuffer import LineReceiver
from services.kernel.line_protocol._writer import encode

__all__ = [
    "BINARY_PREFIX",
    "MAX_INFLIGHT",
    "MAX_LINE",
    "MAX_RXBUF",
    "MIN_MAX_LINE",
    "MIN_RXBUF",
    "PROTOCOL_REVISION",
    "PROTOCOL_VERSION",
    "TAGGED",
    "BadLine",
    "Cancel",
    "ErrorReply",
    "Event",
    "Frame",
    "Get",
    "Gone",
    "Hello",
    "HelloRequest",
    "LineProtocolError",
    "LineReceiver",
    "LineValue",
    "Listen",
    "Ok",
    "Ping",
    "Pong",
    "Reply",
    "Request",
    "Set",
    "Unlisten",
    "crc8",
    "decode_line",
    "decode_value",
    "encode",
    "encode_value",
    "escape_field",
    "escape_value",
    "tag_of",
    "unescape",
]

"""The frames of the line protocol: one class per kind of line (docs/device-spec.md §3, §4)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from services.kernel.errors import Code, PropertyError, code_for, error_for

#: Wire version sent in the greeting: 1 for protocol 1.0 to 1.3 (1.1 only adds greeting
#: fields a 1.0 peer ignores; 1.2 only adds the ``\=`` form of a binary value, which a 1.1
#: peer refuses cleanly with ``ERR 3 bad escape``; 1.3 settles points the earlier texts left
#: open; docs/device-spec.md, "Versions").
PROTOCOL_VERSION = 1
#: The protocol revision this codec implements, for messages and docs.
PROTOCOL_REVISION = "1.3"

#: Longest line, first byte to LF inclusive. It fits every value of the standard
#: property sets (6-vector ~60 bytes, marker ~150, a 40-name ``properties`` list
#: ~600, a path at most 256) and keeps one line buffer per connection small; SMTP
#: settles on 1000 for the same reasons (RFC 5321 §4.5.3.1.6). A device with less
#: RAM announces a smaller ``maxline`` in its greeting.
MAX_LINE = 1024

#: Smallest ``maxline`` a device may announce: a GET of a short path and an
#: ERR reply with a short message must still fit.
MIN_MAX_LINE = 64

#: Bounds of the flow-control fields of a greeting (docs/device-spec.md §5).
#: ``inflight`` at most the proxies' own ceiling (``max_in_flight``); ``rxbuf`` at
#: least what a short tagged GET needs (``#1 GET speed`` and its LF are 13 bytes).
MAX_INFLIGHT = 4096
MIN_RXBUF = 16
MAX_RXBUF = 65536

_Params = Mapping[str, str]
#: A value on the line: text, or bytes written ``\=`` and base64 (docs/device-spec.md §2.6).
LineValue = str | bytes


def _no_params() -> dict[str, str]:
    return {}


@dataclass(frozen=True, slots=True)
class Get:
    """``GET [PARAMS] PATH``: read a property."""

    path: str
    params: _Params = field(default_factory=_no_params)
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Set:
    """``SET [PARAMS] PATH VALUE``: write a property or call a functional property."""

    path: str
    value: LineValue
    params: _Params = field(default_factory=_no_params)
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Listen:
    """``LISTEN [PARAMS] PATH``: subscribe; the OK reply carries the current value."""

    path: str
    params: _Params = field(default_factory=_no_params)
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Unlisten:
    """``UNLISTEN [PARAMS] PATH``: end a subscription."""

    path: str
    params: _Params = field(default_factory=_no_params)
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Ping:
    """``PING [DATA]``: keep-alive; either side may send it."""

    data: str = ""
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Pong:
    """``PONG [DATA]``: the answer to a PING, echoing its data."""

    data: str = ""
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Cancel:
    """``#TAG CANCEL``: the client gave up on request ``TAG``; a SET not started yet is not applied."""

    tag: str | None = None


@dataclass(frozen=True, slots=True)
class HelloRequest:
    """``HELLO`` with no fields: ask the device to send its greeting again."""

    tag: str | None = None


@dataclass(frozen=True, slots=True)
class Hello:
    """``HELLO VERSION name=.. type=.. push=0|1 maxline=N ...``: a device introduces itself."""

    name: str = ""
    type: str = ""
    #: The device sends EVENT lines itself; when False the client polls.
    push: bool = False
    max_line: int = MAX_LINE
    version: int = PROTOCOL_VERSION
    #: Further ``KEY=VALUE`` fields, kept for the application.
    extra: _Params = field(default_factory=_no_params)
    tag: str | None = None
    #: Requests the device takes at once (``inflight=``); None when it does not say.
    inflight: int | None = None
    #: Bytes of unanswered requests its receive buffer holds (``rxbuf=``); None when it does not say.
    rxbuf: int | None = None


@dataclass(frozen=True, slots=True)
class Ok:
    """``OK [VALUE]``: a request succeeded."""

    value: LineValue = ""
    tag: str | None = None


@dataclass(frozen=True, slots=True)
class ErrorReply:
    """``ERR CODE [MESSAGE]``: a request failed; CODE is a gRPC status number."""

    code: int
    message: str = ""
    tag: str | None = None

    @classmethod
    def from_exception(cls, error: PropertyError, tag: str | None = None) -> ErrorReply:
        """The reply that reports ``error``."""
        return cls(int(error.code), error.message, tag)

    def to_exception(self, context: str = "") -> PropertyError:
        """The error this reply reports, of the class for its code (``ERR 5`` → NotFound).

        An unknown code becomes UNKNOWN.
        """
        code = code_for(self.code)
        message = f"{context}: {self.message}" if context else self.message
        return error_for(code, message or code.name.lower().replace("_", " "))


@dataclass(frozen=True, slots=True)
class Event:
    """``EVENT PATH [VALUE]``: a listened property changed."""

    path: str
    value: LineValue = ""


@dataclass(frozen=True, slots=True)
class Gone:
    """``GONE PATH``: a listened property no longer exists; its subscription ends."""

    path: str


@dataclass(frozen=True, slots=True)
class BadLine:
    """A line that could not be decoded; the receiver goes on with the next line.

    Never encoded. ``tag`` is the line's tag when it could be read, so the
    error belongs to one request.
    """

    code: Code
    message: str
    tag: str | None = None
    #: The line began with ``$``: a reply to it carries a checksum (docs/device-spec.md §6.4).
    checksummed: bool = False
    #: The line was a greeting (``HELLO`` and a version) that cannot be accepted.
    greeting: bool = False


Request = Get | Set | Listen | Unlisten | Ping | HelloRequest
Reply = Ok | ErrorReply | Pong | Hello
Frame = (
    Get
    | Set
    | Listen
    | Unlisten
    | Ping
    | Pong
    | HelloRequest
    | Hello
    | Ok
    | ErrorReply
    | Event
    | Gone
    | Cancel
)

#: Frames that carry a request tag.
TAGGED = (Get, Set, Listen, Unlisten, Ping, Pong, HelloRequest, Hello, Ok, ErrorReply, Cancel)

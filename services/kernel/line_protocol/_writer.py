"""Frames in, bytes out."""

from __future__ import annotations

from collections.abc import Mapping

from services.kernel.errors import Code
from services.kernel.line_protocol._checksum import crc8
from services.kernel.line_protocol._errors import LineProtocolError
from services.kernel.line_protocol._escaping import encode_value, escape_field, escape_value
from services.kernel.line_protocol._frames import (
    MAX_LINE,
    Cancel,
    ErrorReply,
    Event,
    Frame,
    Get,
    Gone,
    Hello,
    HelloRequest,
    Listen,
    Ok,
    Ping,
    Pong,
    Set,
    Unlisten,
)
from services.kernel.line_protocol._syntax import ERROR_CODE, PARAM_NAME, PATH, TAG

_HELLO_KEYS = frozenset({"name", "type", "push", "maxline", "inflight", "rxbuf"})


def _tag(tag: str | None) -> str:
    if tag is None:
        return ""
    if not TAG.fullmatch(tag):
        raise LineProtocolError(f"bad tag {tag!r}: 1 to 8 characters of A-Z a-z 0-9 _ -")
    return f"#{tag} "


def _path(path: str) -> str:
    if not PATH.fullmatch(path):
        raise LineProtocolError(f"bad path {path[:80]!r}: use letters, digits, _ - and dots, at most 256")
    return path


def _params(params: Mapping[str, str]) -> str:
    out = []
    for name, value in params.items():
        if not PARAM_NAME.fullmatch(name):
            raise LineProtocolError(f"bad parameter name {name[:80]!r}: use letters, digits, _ . and -")
        out.append(f"{name}={escape_field(value)} ")
    return "".join(out)


def _rest(value: str | bytes) -> str:
    # Empty text is left out (``OK``); empty bytes are still binary (``OK \=``).
    return f" {encode_value(value)}" if value or type(value) is bytes else ""


def _message(text: str) -> str:
    return f" {escape_value(text)}" if text else ""


def _raw(text: str) -> str:
    if "\n" in text or "\r" in text:
        raise LineProtocolError("PING and PONG data cannot hold a line break")
    return f" {text}" if text else ""


def _body(frame: Frame) -> str:
    match frame:
        case Get(path, params, tag):
            return f"{_tag(tag)}GET {_params(params)}{_path(path)}"
        case Set(path, value, params, tag):
            return f"{_tag(tag)}SET {_params(params)}{_path(path)}{_rest(value)}"
        case Listen(path, params, tag):
            return f"{_tag(tag)}LISTEN {_params(params)}{_path(path)}"
        case Unlisten(path, params, tag):
            return f"{_tag(tag)}UNLISTEN {_params(params)}{_path(path)}"
        # PING data is opaque: echoed byte for byte, never escaped or decoded (docs/device-spec.md §3.6).
        case Ping(data, tag):
            return f"{_tag(tag)}PING{_raw(data)}"
        case Pong(data, tag):
            return f"{_tag(tag)}PONG{_raw(data)}"
        case HelloRequest(tag):
            return f"{_tag(tag)}HELLO"
        case Cancel(tag):
            if tag is None:
                raise LineProtocolError("CANCEL names the request it cancels by its tag: #TAG CANCEL")
            return f"{_tag(tag)}CANCEL"
        case Hello(name, type_, push, max_line, version, extra, tag, inflight, rxbuf):
            clash = _HELLO_KEYS.intersection(extra)
            if clash:
                raise LineProtocolError(f"greeting field {sorted(clash)[0]!r} is not an extra field")
            fields = {"name": name, "type": type_, "push": "1" if push else "0", "maxline": str(max_line)}
            if not name:
                del fields["name"]
            if not type_:
                del fields["type"]
            if inflight is not None:
                fields["inflight"] = str(inflight)
            if rxbuf is not None:
                fields["rxbuf"] = str(rxbuf)
            fields.update(extra)
            return f"{_tag(tag)}HELLO {int(version)} {_params(fields)}".rstrip(" ")
        case Ok(value, tag):
            return f"{_tag(tag)}OK{_rest(value)}"
        case ErrorReply(code, message, tag):
            if not ERROR_CODE.fullmatch(str(code)):
                raise LineProtocolError(f"bad error code {code!r}: 0 to 999")
            return f"{_tag(tag)}ERR {int(code)}{_message(message)}"
        case Event(path, value):
            return f"EVENT {_path(path)}{_rest(value)}"
        case Gone(path):
            return f"GONE {_path(path)}"
    raise TypeError(f"not a line-protocol frame: {frame!r}")


def encode(frame: Frame, *, checksum: bool = False, max_line: int = MAX_LINE) -> bytes:
    """The line for ``frame``, LF included; with ``checksum`` as ``$...*HH``.

    Raises LineProtocolError (RESOURCE_EXHAUSTED) when the line would be longer
    than ``max_line`` bytes, and (INVALID_ARGUMENT) for a field that cannot be
    written (a path with a space, a bad tag, ...).
    """
    data = _body(frame).encode("utf-8")
    if checksum:
        data = b"$" + data + b"*%02X" % crc8(data)
    if len(data) + 1 > max_line:
        raise LineProtocolError(
            f"line too long: {len(data) + 1} bytes, the limit is {max_line}",
            Code.RESOURCE_EXHAUSTED,
            getattr(frame, "tag", None),
        )
    return data + b"\n"

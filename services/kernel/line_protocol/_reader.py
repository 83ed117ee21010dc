"""One line of bytes in, one frame out."""

from __future__ import annotations

import re

from services.kernel.errors import Code
from services.kernel.line_protocol._checksum import crc8
from services.kernel.line_protocol._errors import LineProtocolError
from services.kernel.line_protocol._escaping import decode_value, unescape
from services.kernel.line_protocol._frames import (
    MAX_INFLIGHT,
    MAX_LINE,
    MAX_RXBUF,
    MIN_MAX_LINE,
    MIN_RXBUF,
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
from services.kernel.line_protocol._syntax import ERROR_CODE, PARAM_NAME, PATH, TAG, VERSION

_HEX = re.compile(rb"[0-9A-Fa-f]{2}")
_TAG_PREFIX = re.compile(rb"#([A-Za-z0-9_-]{1,8}) ")
#: The two commonest lines, read without splitting into fields: a tagged GET
#: without parameters and a tagged OK reply. Anything else takes the general path.
_TAGGED_GET = re.compile(r"#([A-Za-z0-9_-]{1,8}) GET ([A-Za-z0-9_.-]{1,256})")
_TAGGED_OK = re.compile(r"#([A-Za-z0-9_-]{1,8}) OK(?= |$)")


def _show(text: str) -> str:
    return repr(text if len(text) <= 40 else text[:37] + "...")


def tag_of(line: bytes | bytearray) -> str | None:
    """The tag a raw line begins with, if any; used to address errors for bad lines.

    A ``$`` line's tag is not read: its checksum failed or was not checked, so
    the tag may be damaged.
    """
    match = _TAG_PREFIX.match(line)
    return match.group(1).decode("ascii") if match else None


class _Fields:
    """A cursor over the fields of one line."""

    __slots__ = ("pos", "text")

    def __init__(self, text: str, pos: int = 0) -> None:
        self.text = text
        self.pos = pos

    def next(self) -> str:
        """The next space-separated field, '' at the end of the line."""
        text, pos = self.text, self.pos
        while pos < len(text) and text[pos] == " ":
            pos += 1
        end = text.find(" ", pos)
        if end < 0:
            end = len(text)
        self.pos = end
        return text[pos:end]

    def rest(self) -> str:
        """The text after the single space that follows the last field read, unescaped (a message)."""
        return unescape(self.text[self.pos + 1 :])

    def value(self) -> str | bytes:
        """The value after the single space that follows the last field read: text, or ``\\=`` bytes."""
        return decode_value(self.text[self.pos + 1 :])

    def raw_rest(self) -> str:
        """The rest of the line as sent, escapes and all (PING and PONG data: echoed byte for byte)."""
        return self.text[self.pos + 1 :]

    def at_end(self) -> bool:
        return not self.text[self.pos :].strip(" ")


def _params_and_path(fields: _Fields, word: str) -> tuple[dict[str, str], str]:
    params: dict[str, str] = {}
    while True:
        token = fields.next()
        if not token:
            raise LineProtocolError(f"{word} needs a property path")
        name, eq, value = token.partition("=")
        if not eq:
            if not PATH.fullmatch(token):
                raise LineProtocolError(
                    f"bad path {_show(token)}: use letters, digits, _ - and dots, at most 256 characters"
                )
            return params, token
        if not PARAM_NAME.fullmatch(name):
            raise LineProtocolError(f"bad parameter name {_show(name)}")
        if name in params:
            raise LineProtocolError(f"parameter {name!r} given twice")
        params[name] = unescape(value)


def _no_more(fields: _Fields, word: str) -> None:
    if not fields.at_end():
        raise LineProtocolError(
            f"unexpected text after the path of {word}: {_show(fields.text[fields.pos :])}"
        )


def _bad_greeting(message: str) -> LineProtocolError:
    return LineProtocolError(f"bad greeting: {message}", greeting=True)


def _number_field(values: dict[str, str], key: str, low: int, high: int) -> int | None:
    text = values.pop(key, None)
    if text is None:
        return None
    if not text.isascii() or not text.isdigit() or len(text) > 7:
        raise _bad_greeting(f"{key}={_show(text)} is not a number")
    number = int(text)
    if not low <= number <= high:
        raise _bad_greeting(f"{key}={number} is outside {low}..{high}")
    return number


def _hello(fields: _Fields, tag: str | None) -> Hello | HelloRequest:
    version = fields.next()
    if not version:
        _no_more(fields, "HELLO")
        return HelloRequest(tag)
    if not VERSION.fullmatch(version):
        raise LineProtocolError(f"bad protocol version {_show(version)} in greeting")
    values: dict[str, str] = {}
    while token := fields.next():
        key, eq, value = token.partition("=")
        if not eq or not PARAM_NAME.fullmatch(key):
            raise _bad_greeting(f"field {_show(token)} is not KEY=VALUE")
        if key in values:
            raise _bad_greeting(f"field {key!r} given twice")
        values[key] = unescape(value)
    push = values.pop("push", "0")
    if push not in ("0", "1"):
        raise _bad_greeting(f"push={_show(push)}: expected 0 or 1")
    max_line = _number_field(values, "maxline", MIN_MAX_LINE, 9_999_999)
    inflight = _number_field(values, "inflight", 1, MAX_INFLIGHT)
    rxbuf = _number_field(values, "rxbuf", MIN_RXBUF, MAX_RXBUF)
    return Hello(
        name=values.pop("name", ""),
        type=values.pop("type", ""),
        push=push == "1",
        max_line=MAX_LINE if max_line is None else max_line,
        version=int(version),
        extra=values,
        tag=tag,
        inflight=inflight,
        rxbuf=rxbuf,
    )


def _parse(text: str) -> Frame:
    if text.startswith("#"):
        match = _TAGGED_OK.match(text)
        if match is not None:
            return Ok(decode_value(text[match.end() + 1 :]), match.group(1))
        match = _TAGGED_GET.fullmatch(text)
        if match is not None:
            return Get(match.group(2), {}, match.group(1))
    fields = _Fields(text)
    tag: str | None = None
    if text.startswith("#"):
        token = fields.next()
        if not TAG.fullmatch(token[1:]):
            raise LineProtocolError(f"bad tag {_show(token)}: '#' and 1 to 8 of A-Z a-z 0-9 _ -")
        tag = token[1:]
    word = fields.next()
    verb = word.upper()
    if verb == "GET":
        params, path = _params_and_path(fields, verb)
        _no_more(fields, verb)
        return Get(path, params, tag)
    if verb == "SET":
        params, path = _params_and_path(fields, verb)
        return Set(path, fields.value(), params, tag)
    if verb == "LISTEN":
        params, path = _params_and_path(fields, verb)
        _no_more(fields, verb)
        return Listen(path, params, tag)
    if verb == "UNLISTEN":
        params, path = _params_and_path(fields, verb)
        _no_more(fields, verb)
        return Unlisten(path, params, tag)
    if verb == "OK":
        return Ok(fields.value(), tag)
    if verb == "ERR":
        code = fields.next()
        if not ERROR_CODE.fullmatch(code):
            raise LineProtocolError(f"bad error code {_show(code)}: expected a number", tag=tag)
        return ErrorReply(int(code), fields.rest(), tag)
    if verb == "CANCEL":
        _no_more(fields, verb)
        if tag is None:
            raise LineProtocolError("CANCEL names the request it cancels by its tag: #TAG CANCEL")
        return Cancel(tag)
    if verb == "PING":
        return Ping(fields.raw_rest(), tag)
    if verb == "PONG":
        return Pong(fields.raw_rest(), tag)
    if verb == "HELLO":
        return _hello(fields, tag)
    if verb in ("EVENT", "GONE"):
        if tag is not None:
            raise LineProtocolError(f"{verb} lines carry no tag")
        path = fields.next()
        if not PATH.fullmatch(path):
            raise LineProtocolError(f"bad path {_show(path)} in {verb}")
        if verb == "GONE":
            _no_more(fields, verb)
            return Gone(path)
        return Event(path, fields.value())
    if not word:
        raise LineProtocolError("a tag but no word")
    raise LineProtocolError(f"unknown word {_show(word)}", Code.UNIMPLEMENTED)


def decode_line(line: bytes | bytearray, max_line: int = MAX_LINE) -> Frame:
    """Decode one line (without its LF; a trailing CR is ignored).

    Raises LineProtocolError, and nothing else, for any line that is not a
    frame or is longer than ``max_line`` bytes with its LF; its ``tag`` is set
    when the line's tag could be read.
    """
    raw = line if type(line) is bytes else bytes(line)
    if raw.endswith(b"\r"):
        raw = raw[:-1]
    if raw.startswith(b" "):
        raw = raw.lstrip(b" ")  # spaces before the first field are skipped (docs/device-spec.md §1.4)
    if len(raw) + 1 > max_line:
        raise LineProtocolError(
            f"line too long: {len(raw) + 1} bytes, the limit is {max_line}",
            Code.RESOURCE_EXHAUSTED,
            tag_of(raw),
        )
    if raw.startswith(b"$"):
        if len(raw) < 4 or raw[-3:-2] != b"*" or not _HEX.fullmatch(raw[-2:]):
            raise LineProtocolError("checksum mismatch: a '$' line must end with '*HH'", Code.DATA_LOSS)
        body = raw[1:-3]
        if crc8(body) != int(raw[-2:], 16):
            raise LineProtocolError(
                f"checksum mismatch: line says {raw[-2:].decode().upper()}, content gives {crc8(body):02X}",
                Code.DATA_LOSS,
            )
        if body.startswith(b" "):
            # Nothing stands between '$' and the tag or word (docs/device-spec.md §6.3): a device
            # that finds the tag right after the '$' must not have to skip spaces there too.
            raise LineProtocolError("a space after '$': the tag or word follows it directly")
        raw = body
    # The tag is read only when the line turns out bad: it addresses the error.
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise LineProtocolError(f"line is not valid UTF-8 (byte {exc.start})", tag=tag_of(raw)) from None
    if "\r" in text or "\n" in text:
        raise LineProtocolError("raw CR or LF inside a line; write \\r or \\n", tag=tag_of(raw))
    if not text.strip(" "):
        raise LineProtocolError("empty line", tag=tag_of(raw))
    try:
        return _parse(text)
    except LineProtocolError as exc:
        if exc.tag is None:
            exc.tag = tag_of(raw)
        raise

"""Backslash escapes of values and parameter values, and the ``\\=`` form of a binary value
(docs/device-spec.md §2.5, §2.6)."""

from __future__ import annotations

import binascii
import re

from services.kernel.line_protocol._errors import LineProtocolError

_UNESCAPE = {"n": "\n", "r": "\r", "\\": "\\", "s": " "}
_ESCAPE_SEQUENCE = re.compile(r"\\(.?)", re.DOTALL)
_VALUE_SPECIALS = re.compile(r"[\\\n\r]")
_FIELD_SPECIALS = re.compile(r"[\\\n\r ]")
_ESCAPE = {"\\": "\\\\", "\n": "\\n", "\r": "\\r", " ": "\\s"}

#: The two characters that open a binary value: the rest of the value is standard base64
#: (RFC 4648 §4, with padding, no line breaks). ``\=`` is an escape a 1.1 peer does not know,
#: so it refuses such a value with ``ERR 3 bad escape`` instead of taking it for text.
BINARY_PREFIX = "\\="


def escape_value(text: str) -> str:
    """Escape a value that runs to the end of the line (spaces stay as they are)."""
    return _VALUE_SPECIALS.sub(lambda m: _ESCAPE[m.group()], text)


def escape_field(text: str) -> str:
    """Escape a value that is one space-separated field (parameter values, greeting fields)."""
    return _FIELD_SPECIALS.sub(lambda m: _ESCAPE[m.group()], text)


def _replace(match: re.Match[str]) -> str:
    char = match.group(1)
    try:
        return _UNESCAPE[char]
    except KeyError:
        if char == "=":
            raise LineProtocolError(
                "bad escape: '\\=' (a binary value) may only open a SET, OK or EVENT value; "
                "a text backslash is written \\\\"
            ) from None
        shown = "a backslash at the end of the line" if not char else f"'\\{char}'"
        raise LineProtocolError(f"bad escape: {shown} (use \\n, \\r, \\\\ or \\s)") from None


def unescape(text: str) -> str:
    """Undo :func:`escape_value` / :func:`escape_field`; raise LineProtocolError on an unknown escape."""
    if "\\" not in text:
        return text
    return _ESCAPE_SEQUENCE.sub(_replace, text)


def encode_value(value: str | bytes) -> str:
    """The wire form of a value that runs to the end of the line: escaped text, or ``\\=`` and base64."""
    if type(value) is bytes or isinstance(value, bytes):
        return BINARY_PREFIX + binascii.b2a_base64(value, newline=False).decode("ascii")
    return escape_value(value)


def decode_value(text: str) -> str | bytes:
    """Undo :func:`encode_value`: ``bytes`` for a value that opens with ``\\=``, else unescaped text.

    Raises LineProtocolError (INVALID_ARGUMENT) for base64 that is not standard, padded base64
    with zero padding bits, and for a bad escape.
    """
    if not text.startswith(BINARY_PREFIX):
        return unescape(text)
    encoded = text[2:]
    try:
        data = binascii.a2b_base64(encoded, strict_mode=True)
    except (binascii.Error, ValueError):
        raise LineProtocolError(f"bad base64 after '\\=': {_why_not_base64(encoded)}") from None
    # Padding bits must be zero (RFC 4648 §3.5): one value has one spelling, so a device's
    # off-by-one in its encoder shows here rather than as a silently different image.
    if (
        encoded.endswith("=")
        and binascii.b2a_base64(data[-(len(data) % 3) :], newline=False).decode("ascii") != encoded[-4:]
    ):
        raise LineProtocolError("bad base64 after '\\=': the padding bits of the last quantum are not zero")
    return data


def _why_not_base64(encoded: str) -> str:
    for position, char in enumerate(encoded):
        if not (char.isascii() and (char.isalnum() or char in "+/=")):
            return f"{char!r} at position {position} is not in the base64 alphabet (A-Z a-z 0-9 + / =)"
    if len(encoded) % 4:
        count = len(encoded)
        return f"{count} character{'s' * (count != 1)}; base64 comes in groups of 4 (pad the last with '=')"
    return "'=' is padding and may only end the value"

"""Backslash escapes of values and parameter values (docs/line-protocol.md §2)."""

from __future__ import annotations

import re

from services.line_protocol._errors import LineProtocolError

_UNESCAPE = {"n": "\n", "r": "\r", "\\": "\\", "s": " "}
_ESCAPE_SEQUENCE = re.compile(r"\\(.?)", re.DOTALL)
_VALUE_SPECIALS = re.compile(r"[\\\n\r]")
_FIELD_SPECIALS = re.compile(r"[\\\n\r ]")
_ESCAPE = {"\\": "\\\\", "\n": "\\n", "\r": "\\r", " ": "\\s"}


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
        shown = "a backslash at the end of the line" if not char else f"'\\{char}'"
        raise LineProtocolError(f"bad escape: {shown} (use \\n, \\r, \\\\ or \\s)") from None


def unescape(text: str) -> str:
    """Undo :func:`escape_value` / :func:`escape_field`; raise LineProtocolError on an unknown escape."""
    if "\\" not in text:
        return text
    return _ESCAPE_SEQUENCE.sub(_replace, text)

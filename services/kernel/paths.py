"""Property paths, service names and Listen wildcard patterns.

A property path is dot-separated segments (``robots.scout1.location``); a
segment is 1–64 characters of ``A-Z a-z 0-9 _ -``, and a whole path is at
most 256 characters. A service name is one such segment. A pattern is a path
in which a segment may be ``*``, matching exactly one segment (never a dot).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable

from services.kernel.errors import InvalidArgument

__all__ = [
    "MAX_PATH_LENGTH",
    "MAX_SEGMENT_LENGTH",
    "WILDCARD",
    "compile_pattern",
    "is_below",
    "is_pattern",
    "match",
    "split_path",
    "validate_path",
    "validate_pattern",
    "validate_service_name",
]

MAX_SEGMENT_LENGTH = 64
#: A path fits comfortably in one line-protocol request next to its value;
#: deep trees (group → member → tool → property) stay well under it.
MAX_PATH_LENGTH = 256
WILDCARD = "*"

_SEGMENT_CHARS = r"[A-Za-z0-9_-]"
_SEGMENT = re.compile(f"{_SEGMENT_CHARS}{{1,{MAX_SEGMENT_LENGTH}}}")
_PATH = re.compile(rf"{_SEGMENT.pattern}(?:\.{_SEGMENT.pattern})*")
_BAD_CHAR = re.compile(r"[^A-Za-z0-9_.-]")


def _shown_char(c: str) -> str:
    return c if c.isprintable() else c.encode("unicode_escape").decode("ascii")


def _show(text: str) -> str:
    # Control characters are escaped; every other character, ASCII or not, shows as itself.
    shown = "".join(_shown_char(c) for c in text[:100]).replace('"', '\\"')
    return '"' + (shown if len(shown) <= 80 else shown[:77] + "...") + '"'


def _check(text: str, what: str, allow_wildcard: bool) -> None:
    """Raise InvalidArgument saying exactly what is wrong with ``text``."""
    if not isinstance(text, str):
        raise InvalidArgument(f"bad {what}: expected text, got a {type(text).__name__}")
    if not text:
        raise InvalidArgument(f'bad {what} "": it is empty')
    if len(text) > MAX_PATH_LENGTH:
        raise InvalidArgument(
            f"bad {what} {_show(text)}: {len(text)} characters, the limit is {MAX_PATH_LENGTH}"
        )
    start = 0
    for segment in text.split("."):
        if not segment:
            raise InvalidArgument(f"bad {what} {_show(text)}: empty segment at position {start}")
        if not (allow_wildcard and segment == WILDCARD):
            bad = _BAD_CHAR.search(segment)
            if bad is not None:
                hint = "; * matches a whole segment only" if allow_wildcard and bad.group() == "*" else ""
                raise InvalidArgument(
                    f"bad {what} {_show(text)}: character {bad.group()!r} at position {start + bad.start()} "
                    f"(use letters, digits, _ and -{hint})"
                )
            if len(segment) > MAX_SEGMENT_LENGTH:
                raise InvalidArgument(
                    f"bad {what} {_show(text)}: segment at position {start} has {len(segment)} characters, "
                    f"the limit is {MAX_SEGMENT_LENGTH}"
                )
        start += len(segment) + 1


def validate_path(path: str) -> str:
    """Return ``path`` when it is a valid property path, else raise InvalidArgument saying why."""
    if isinstance(path, str) and len(path) <= MAX_PATH_LENGTH and _PATH.fullmatch(path) is not None:
        return path
    _check(path, "property path", allow_wildcard=False)
    raise AssertionError("unreachable: _check accepted an invalid path")  # pragma: no cover


def validate_service_name(name: str) -> str:
    """Return ``name`` when it is a valid service name (one segment), else raise InvalidArgument."""
    if isinstance(name, str) and _SEGMENT.fullmatch(name) is not None:
        return name
    if isinstance(name, str) and "." in name:
        raise InvalidArgument(f"bad service name {_show(name)}: a service name has no dots")
    if isinstance(name, str) and len(name) > MAX_SEGMENT_LENGTH:
        raise InvalidArgument(
            f"bad service name {_show(name)}: {len(name)} characters, the limit is {MAX_SEGMENT_LENGTH}"
        )
    _check(name, "service name", allow_wildcard=False)
    raise AssertionError("unreachable: _check accepted an invalid service name")  # pragma: no cover


def split_path(path: str) -> list[str]:
    """The segments of a valid ``path``: ``"a.b.c"`` → ``["a", "b", "c"]``."""
    return validate_path(path).split(".")


def is_pattern(s: str) -> bool:
    """True when ``s`` holds a wildcard segment (it is a selector, not a concrete path)."""
    return WILDCARD in s


def is_below(path: str, name: str) -> bool:
    """True when ``path`` is ``name`` or lies below it (``name.…``): ``a.b`` is below ``a``, ``ab`` is not."""
    return path.startswith(name) and (len(path) == len(name) or path[len(name)] == ".")


def validate_pattern(pattern: str) -> str:
    """Return ``pattern`` when it is a valid path or wildcard pattern, else raise InvalidArgument."""
    _check(pattern, "property pattern", allow_wildcard=True)
    return pattern


@functools.lru_cache(maxsize=1024)
def compile_pattern(pattern: str) -> Callable[[str], bool]:
    """A fast predicate telling whether a path matches ``pattern`` (validated; cached)."""
    validate_pattern(pattern)
    if not is_pattern(pattern):

        def equals(path: str) -> bool:
            return path == pattern

        return equals
    regex = re.compile(
        r"\.".join(
            _SEGMENT.pattern if segment == WILDCARD else re.escape(segment) for segment in pattern.split(".")
        )
    )

    def matches(path: str) -> bool:
        return regex.fullmatch(path) is not None

    return matches


def match(pattern: str, path: str) -> bool:
    """True when ``path`` matches ``pattern``: ``*`` stands for exactly one segment."""
    return compile_pattern(pattern)(path)

"""The ``find`` query of a storage service: files by name pattern, size and modification time."""

from __future__ import annotations

import fnmatch
import functools
import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

from services.apps.storage.disk import FileInfo
from services.kernel.errors import InvalidArgument

__all__ = ["FindQuery", "format_time", "glob_matcher", "parse_size", "parse_time"]

#: A glob longer than this is refused (a pattern is a name pattern; names are at most 1024 characters).
MAX_PATTERN_CHARS = 1024


@functools.lru_cache(maxsize=256)
def glob_matcher(pattern: str) -> Callable[[str], bool]:
    """A predicate matching whole relative names against ``pattern`` (cached).

    Shell-style: ``*`` and ``?`` match any characters, ``/`` included (``*.png``
    finds PNG files in every sub-directory, ``charts/*`` everything under
    ``charts``), ``[abc]`` one of the characters. Case matters.
    """
    if len(pattern) > MAX_PATTERN_CHARS:
        raise InvalidArgument(f"bad pattern: {len(pattern)} characters, the limit is {MAX_PATTERN_CHARS}")
    regex = re.compile(fnmatch.translate(pattern))

    def matches(name: str) -> bool:
        return regex.match(name) is not None

    return matches


def parse_size(text: str, what: str) -> int | None:
    """A size in bytes (a whole number); None for ""."""
    text = text.strip()
    if not text:
        return None
    if not text.isdigit():
        raise InvalidArgument(f"bad {what}: expected a number of bytes like 1024, got {text[:40]!r}")
    return int(text)


def parse_time(text: str, what: str) -> int | None:
    """An ISO 8601 time (``2026-11-23T08:00:00Z``; a time without a zone is UTC) as ns; None for ""."""
    text = text.strip()
    if not text:
        return None
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise InvalidArgument(
            f"bad {what}: expected an ISO 8601 time like 2026-11-23T08:00:00Z, got {text[:40]!r}"
        ) from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return int(when.timestamp() * 1_000_000) * 1000


def format_time(ns: int) -> str:
    """Nanoseconds since the epoch as ISO 8601 UTC with microseconds: ``2026-11-23T08:00:00.000000Z``."""
    when = datetime.fromtimestamp(ns // 1000 / 1_000_000, tz=UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


@dataclass(frozen=True, slots=True)
class FindQuery:
    """What ``find`` asks: every given condition must hold."""

    pattern: str = ""
    min_size: int | None = None
    max_size: int | None = None
    #: Modified strictly after / strictly before, ns since the epoch.
    newer_ns: int | None = None
    older_ns: int | None = None

    @classmethod
    def parse(cls, *, pattern: str, min_size: str, max_size: str, newer: str, older: str) -> FindQuery:
        """Read the query's parameters; InvalidArgument naming the bad one."""
        query = cls(
            pattern=pattern,
            min_size=parse_size(min_size, "min_size"),
            max_size=parse_size(max_size, "max_size"),
            newer_ns=parse_time(newer, "newer"),
            older_ns=parse_time(older, "older"),
        )
        if pattern:
            glob_matcher(pattern)  # a pattern too long fails here
        return query

    def matches(self, info: FileInfo) -> bool:
        """True when the file meets every condition."""
        if self.pattern and not glob_matcher(self.pattern)(info.name):
            return False
        if self.min_size is not None and info.size < self.min_size:
            return False
        if self.max_size is not None and info.size > self.max_size:
            return False
        if self.newer_ns is not None and info.mtime_ns <= self.newer_ns:
            return False
        return self.older_ns is None or info.mtime_ns < self.older_ns

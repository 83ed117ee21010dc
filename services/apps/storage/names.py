"""File names as a storage service carries them: relative paths, ``/`` between directories.

A name travels in a request parameter (``name=charts/door.scxml``) and in the
``files`` list, whose grammar (:func:`services.kernel.values.format_names`) holds
words without whitespace or parentheses. So a name is:

* relative: never absolute (``/etc/passwd``), never ``.`` or ``..`` as a
  segment, no empty segment (``a//b``, ``a/``);
* printable: no whitespace, no ``(`` or ``)``, no control characters, no
  backslash (a path separator elsewhere) and nothing UTF-8 cannot encode;
* what Linux filesystems hold: a segment of at most 255 bytes in UTF-8
  (``NAME_MAX``); at most :data:`MAX_DEPTH` segments and
  :data:`MAX_NAME_CHARS` characters in all;
* not the service's own temporary files (:data:`TEMP_PREFIX`).
"""

from __future__ import annotations

import re

from services.kernel.errors import InvalidArgument

__all__ = ["MAX_DEPTH", "MAX_NAME_CHARS", "MAX_SEGMENT_BYTES", "TEMP_PREFIX", "check_name", "is_carried"]

#: Linux's NAME_MAX: the longest file name (one segment) ext4, xfs, btrfs and tmpfs hold, in bytes.
MAX_SEGMENT_BYTES = 255
#: Sub-directories below the storage directory a name may reach; real trees nest a few levels.
MAX_DEPTH = 16
#: A whole name, in characters: well under PATH_MAX (4096) and short enough for a message.
MAX_NAME_CHARS = 1024
#: Temporary files of a Set in progress start so; they are never listed, read or named.
TEMP_PREFIX = ".storage-tmp-"

# Whitespace, parentheses (the list grammar), backslash and control characters (C0, DEL, C1).
_BAD_CHAR = re.compile(r"[\s()\\\x00-\x1f\x7f-\x9f]")


def _shown(name: str) -> str:
    clipped = name if len(name) <= 80 else name[:77] + "..."
    return repr(clipped)


def _problem(name: str) -> str | None:
    """Why ``name`` is not a file name the service carries, or None when it is one."""
    if not name:
        return "it is empty"
    if len(name) > MAX_NAME_CHARS:
        return f"{len(name)} characters, the limit is {MAX_NAME_CHARS}"
    if name.startswith("/"):
        return "an absolute path; names are relative to the storage directory"
    bad = _BAD_CHAR.search(name)
    if bad is not None:
        char = bad.group()
        what = (
            "whitespace"
            if char.isspace()
            else "a control character"
            if not char.isprintable()
            else repr(char)
        )
        return (
            f"{what} at position {bad.start()} "
            "(names carry no whitespace, parentheses, backslashes or control characters)"
        )
    segments = name.split("/")
    if len(segments) > MAX_DEPTH:
        return f"{len(segments)} segments deep, the limit is {MAX_DEPTH}"
    for segment in segments:
        if not segment:
            return "an empty segment (a leading, trailing or doubled /)"
        if segment in (".", ".."):
            return f"the segment {segment!r}; a name never leaves the storage directory"
        if segment.startswith(TEMP_PREFIX):
            return f"names starting with {TEMP_PREFIX!r} are the service's temporary files"
        try:
            size = len(segment.encode("utf-8"))
        except UnicodeEncodeError:
            return "it holds characters UTF-8 cannot encode"
        if size > MAX_SEGMENT_BYTES:
            return f"a segment of {size} bytes; the filesystem holds at most {MAX_SEGMENT_BYTES}"
    return None


def check_name(name: str) -> str:
    """Return ``name`` when it is a file name the service carries; else InvalidArgument saying why."""
    if not isinstance(name, str):
        raise InvalidArgument(f"bad file name: expected text, got a {type(name).__name__}")
    problem = _problem(name)
    if problem is not None:
        raise InvalidArgument(f"bad file name {_shown(name)}: {problem}")
    return name


def is_carried(name: str) -> bool:
    """True when ``name`` (found on disk) can be listed and named: see the module docstring."""
    return _problem(name) is None

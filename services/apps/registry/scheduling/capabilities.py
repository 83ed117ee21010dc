"""Capability names and sets: what a request asks for and what a provider offers."""

from __future__ import annotations

import re
from collections.abc import Iterable

from services.kernel.errors import InvalidArgument
from services.kernel.values import ValueFormatError, parse_names

__all__ = ["MAX_CAPABILITIES", "check_capabilities", "parse_capabilities"]

#: Capabilities one request or one provider may name. The seed's "logic minterm" has five
#: (video capture, PTZ, mobile platform, communication, power); 32 leaves room for richer tasks
#: while keeping a set a small bit mask.
MAX_CAPABILITIES = 32

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")


def check_capabilities(names: Iterable[str], what: str = "capabilities") -> frozenset[str]:
    """``names`` as a set of capability names, or InvalidArgument naming the bad one."""
    found: set[str] = set()
    for name in names:
        if not isinstance(name, str) or _NAME.fullmatch(name) is None:
            raise InvalidArgument(
                f"{what}: {str(name)[:64]!r} is not a capability name "
                "(letters, digits, '_', '.', '-'; at most 64 characters)"
            )
        found.add(name)
    if len(found) > MAX_CAPABILITIES:
        raise InvalidArgument(f"{what}: at most {MAX_CAPABILITIES} capabilities, got {len(found)}")
    return frozenset(found)


def parse_capabilities(text: str, what: str = "capabilities") -> frozenset[str]:
    """A list ``(video ptz mobile)`` or one bare name ``survey``, as a non-empty set."""
    text = text.strip()
    if not text.startswith("("):
        names = [text] if text else []
    else:
        try:
            names = parse_names(text)
        except ValueFormatError as e:
            raise InvalidArgument(f"{what}: {e.message}") from None
    found = check_capabilities(names, what)
    if not found:
        raise InvalidArgument(f"{what}: name at least one capability, e.g. (survey) or (video mobile)")
    return found

"""The paths a wildcard matched on one service, kept in order so that "which lie below this
name" costs a binary search, not a scan.

A wildcard's expansion is told where the service's property list changed (a registry entry
``services.scout7`` came or went) and asks the service again for the matches below that name
alone; what it matched there before is :meth:`MatchedPaths.below`. With 10,000 matches, a
scan per registration would cost more than the registration itself.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Iterator

#: The character right after ``.`` in code-point order: every path that starts with ``name.``
#: sorts at or after ``name.`` and before ``name/``.
_AFTER_DOT = chr(ord(".") + 1)
#: Paths added one by one (each a binary search and a move of the longer part); more are sorted
#: again with the others at once (a wildcard asked about everything after a burst of changes).
_ONE_BY_ONE = 64


class MatchedPaths:
    """A set of property paths, also kept sorted (see the module docstring)."""

    __slots__ = ("_members", "_sorted")

    def __init__(self, paths: Iterable[str] = ()) -> None:
        self._members = set(paths)
        self._sorted = sorted(self._members)

    def __contains__(self, path: object) -> bool:
        return path in self._members

    def __len__(self) -> int:
        return len(self._members)

    def __iter__(self) -> Iterator[str]:
        return iter(self._sorted)

    def add(self, path: str) -> None:
        if path not in self._members:
            self._members.add(path)
            bisect.insort(self._sorted, path)

    def update(self, paths: Iterable[str]) -> None:
        """Add every one of ``paths``: one by one when they are few, else sorted again at once."""
        new = [p for p in paths if p not in self._members]
        if len(new) <= _ONE_BY_ONE:
            for path in new:
                self.add(path)
            return
        self._members.update(new)
        self._sorted = sorted(self._members)

    def discard(self, path: str) -> None:
        if path in self._members:
            self._members.discard(path)
            del self._sorted[bisect.bisect_left(self._sorted, path)]

    def below(self, name: str) -> set[str]:
        """The paths that are ``name`` or lie below it (``name.…``); every path for ""."""
        if not name:
            return set(self._members)
        found = {name} if name in self._members else set()
        start = bisect.bisect_left(self._sorted, name + ".")
        end = bisect.bisect_left(self._sorted, name + _AFTER_DOT, start)
        found.update(self._sorted[start:end])
        return found

"""The conflating queue: the latest value per key, never a growing backlog.

A reader that falls behind a fast source (a Listen stream, a device-side
connection, an SDK listen reader) must not make memory grow with the rate of
changes. Each holds one :class:`ConflatingQueue`: a new value for a key that
is still waiting replaces the old one and counts it in ``conflated``, the
way gNMI coalesces updates for a slow subscriber and KUKSA's buffer of size
0 keeps "latest value only". Memory is bounded by the number of keys, which
each user bounds itself (topics of a stream, listens of a connection).

Keys leave in the order they first arrived, so a busy key cannot starve a
quiet one. Plain data and no I/O: the gateway, the device side and the SDK
share it.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Generic, TypeVar

K = TypeVar("K")
V = TypeVar("V")


class Slot(Generic[V]):
    """What waits for one key: the latest value and what happened before it.

    Made only by :meth:`ConflatingQueue.put` (one a key that was not waiting), which fills it in.
    """

    __slots__ = ("conflated", "gap", "removed", "stamp", "value")

    value: V
    #: When the latest value arrived (the user's clock, e.g. ``time.monotonic_ns``).
    stamp: int
    #: How many earlier values this one replaced.
    conflated: int
    #: Values were lost before this one (sticky until taken).
    gap: bool
    #: The key's property no longer exists (the latest news wins).
    removed: bool


_new_slot = object.__new__


class ConflatingQueue(Generic[K, V]):
    """Latest value per key, oldest key first; see the module docstring."""

    __slots__ = ("_slots",)

    def __init__(self) -> None:
        self._slots: dict[K, Slot[V]] = {}

    def put(self, key: K, value: V, stamp: int = 0, gap: bool = False, removed: bool = False) -> bool:
        """Queue ``value`` for ``key``, replacing a waiting one; True when ``key`` was not waiting.

        A removal that replaces a removal is not counted as conflated: nothing was lost.
        """
        slots = self._slots
        slot = slots.get(key)
        if slot is None:
            # Filled in here rather than by a Slot.__init__: calling a class with an __init__ costs
            # more, and this runs for every value of every queue (each Listen stream's).
            slot = _new_slot(Slot)
            slot.value = value
            slot.stamp = stamp
            slot.conflated = 0
            slot.gap = gap
            slot.removed = removed
            slots[key] = slot
            return True
        if not (removed and slot.removed):
            slot.conflated += 1
        slot.value = value
        slot.stamp = stamp
        slot.gap = slot.gap or gap
        slot.removed = removed
        return False

    def take(self, limit: int | None = None) -> list[tuple[K, Slot[V]]]:
        """Remove and return up to ``limit`` waiting keys (all when None), oldest first."""
        slots = self._slots
        if limit is None or limit >= len(slots):
            taken = list(slots.items())
            slots.clear()
            return taken
        taken = []
        for key in slots:
            taken.append((key, slots[key]))
            if len(taken) >= limit:
                break
        for key, _ in taken:
            del slots[key]
        return taken

    def get(self, key: K) -> Slot[V] | None:
        """What waits for ``key``, or None."""
        return self._slots.get(key)

    def discard(self, key: K) -> None:
        """Forget what waits for ``key`` (its listen ended)."""
        self._slots.pop(key, None)

    def clear(self) -> None:
        self._slots.clear()

    def items(self) -> Iterator[tuple[K, Slot[V]]]:
        """(key, slot) of every waiting key, oldest first, without taking them."""
        return iter(self._slots.items())

    def __len__(self) -> int:
        return len(self._slots)

    def __bool__(self) -> bool:
        return bool(self._slots)

    def __contains__(self, key: object) -> bool:
        return key in self._slots

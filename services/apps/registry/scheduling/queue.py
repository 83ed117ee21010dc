"""Requests waiting for a provider: bounded in all and per consumer, each with a deadline (``Tr``)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator

from services.apps.registry.scheduling.model import Request, Waiting
from services.kernel.errors import ResourceExhausted

__all__ = ["DEFAULT_MAX_QUEUED", "MAX_QUEUED_PER_CONSUMER", "RequestQueue"]

#: Requests waiting at once. A waiting request is retried on every release, expiry and change
#: of the registry's table, at a cost that grows with the queue; 64 keeps a retry round short
#: and is more than the robots of any one site would ask for at the same moment.
DEFAULT_MAX_QUEUED = 64
#: Requests one consumer may have waiting: a flood from one consumer cannot fill the queue.
MAX_QUEUED_PER_CONSUMER = 8


class RequestQueue:
    """Waiting requests in arrival order (retried first come, first served)."""

    def __init__(self, limit: int = DEFAULT_MAX_QUEUED, per_consumer: int = MAX_QUEUED_PER_CONSUMER) -> None:
        self._waiting: OrderedDict[str, Waiting] = OrderedDict()
        self.limit = limit
        self.per_consumer = per_consumer

    def __len__(self) -> int:
        return len(self._waiting)

    def __iter__(self) -> Iterator[Waiting]:
        return iter(list(self._waiting.values()))

    def add(self, id: str, request: Request, now: float) -> Waiting:
        """Queue ``request`` until ``now + request.wait``; ResourceExhausted when a bound is reached."""
        if len(self._waiting) >= self.limit:
            raise ResourceExhausted(
                f"the scheduler's queue is full ({self.limit} requests waiting); try again later"
            )
        mine = sum(1 for w in self._waiting.values() if w.request.consumer == request.consumer)
        if mine >= self.per_consumer:
            raise ResourceExhausted(
                f"{request.consumer} already has {mine} requests waiting (at most {self.per_consumer})"
            )
        waiting = Waiting(id, request, now, now + request.wait)
        self._waiting[id] = waiting
        return waiting

    def put_back(self, waiting: Waiting) -> bool:
        """Queue a request again with its own deadline (its providers rejected it); False when full."""
        if len(self._waiting) >= self.limit:
            return False
        self._waiting[waiting.id] = waiting
        return True

    def get(self, id: str) -> Waiting | None:
        return self._waiting.get(id)

    def remove(self, id: str) -> Waiting | None:
        return self._waiting.pop(id, None)

    def overdue(self, now: float) -> list[Waiting]:
        """Remove and return the requests whose deadline passed."""
        gone = [w for w in self._waiting.values() if w.deadline <= now]
        for w in gone:
            del self._waiting[w.id]
        return gone

    def next_deadline(self) -> float | None:
        return min((w.deadline for w in self._waiting.values()), default=None)

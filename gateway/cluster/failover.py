"""Failover: who takes over a registration whose owner is gone, and when.

When a gateway dies its lease expires and its ``owners`` keys go. Every live gateway sees the
same registrations without an owner (*orphans*) and the same loads (``owners`` keys per gateway),
and works out the same plan (:func:`takeover_ranks`, as gnmic does with its targets): the orphans,
in name order, are dealt one at a time to the least-loaded gateway (ties by id), whose load then
counts one more. Each gateway waits ``rank × step`` seconds for each orphan (rank 0: it is the one
the plan names), then ``create``\\ s the owners key unless somebody has: the first to try wins, and
when it cannot (it died too, it lost the store), the next one in the order takes over a step later.

A device that dialled in is never taken over: nobody can dial it. Its registration leaves with
its gateway's lease, and it comes back when the device dials in to another gateway.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Iterable, Mapping

__all__ = ["BATCH_DELAY", "Takeover", "takeover_ranks"]

log = logging.getLogger(__name__)

#: Seconds orphans are gathered before a plan is made: a dead gateway's keys expire together,
#: and one plan for all of them spreads them over the survivors.
BATCH_DELAY = 0.05


def takeover_ranks(orphans: Iterable[str], loads: Mapping[str, int], me: str) -> dict[str, int]:
    """For each orphan, where ``me`` stands in the order of gateways that may take it over (0: first).

    The orphans are dealt in name order to the least-loaded gateway (ties by id), each raising
    that gateway's load by one, so that a dead gateway's services spread over the survivors.
    ``loads`` holds every live gateway's count of owned services, ``me`` among them.
    """
    if me not in loads:
        return {}
    counts = dict(loads)
    ranks: dict[str, int] = {}
    for name in sorted(orphans):
        order = sorted(counts, key=lambda gateway: (counts[gateway], gateway))
        ranks[name] = order.index(me)
        counts[order[0]] += 1
    return ranks


class Takeover:
    """Schedules this gateway's attempts to take over orphans (see the module docstring).

    ``plan()`` gives the orphans and the loads now; ``attempt(name)`` creates the owners key if the
    registration is still an orphan (the cluster node does, and opens the device when it wins).
    """

    def __init__(
        self,
        me: str,
        *,
        step: float,
        plan: Callable[[], tuple[list[str], dict[str, int]]],
        attempt: Callable[[str], Awaitable[None]],
    ) -> None:
        self.me = me
        self.step = step
        self._plan = plan
        self._attempt = attempt
        self._batch: asyncio.TimerHandle | None = None
        #: One pending attempt per orphan (bounded by the registrations).
        self._pending: dict[str, asyncio.Task[None]] = {}

    def orphaned(self) -> None:
        """Some registration lost its owner: make a plan shortly (one plan for a burst)."""
        if self._batch is None:
            self._batch = asyncio.get_running_loop().call_later(BATCH_DELAY, self._make_plan)

    def _make_plan(self) -> None:
        self._batch = None
        orphans, loads = self._plan()
        ranks = takeover_ranks(orphans, loads, self.me)
        loop = asyncio.get_running_loop()
        for name, rank in ranks.items():
            if name in self._pending:
                continue
            self._pending[name] = loop.create_task(
                self._after(name, rank * self.step), name=f"cluster: take over {name}"
            )

    async def _after(self, name: str, delay: float) -> None:
        try:
            if delay > 0:
                await asyncio.sleep(delay)
            await self._attempt(name)
        finally:
            self._pending.pop(name, None)

    async def aclose(self) -> None:
        """Stop every pending attempt."""
        if self._batch is not None:
            self._batch.cancel()
            self._batch = None
        pending = list(self._pending.values())
        self._pending.clear()
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)

"""Failover: who takes over a registration whose owner is gone, and when.

When a gateway dies its lease expires and its ``owners`` keys go. Every live gateway sees the
same registrations without an owner (*orphans*) and the same loads (``owners`` keys per gateway),
and works out the same plan (:func:`takeover_ranks`, as gnmic does with its targets): the orphans,
in name order, are dealt one at a time to the least-loaded gateway (ties by id), whose load then
counts one more. Each gateway waits ``rank × step`` seconds for each orphan (rank 0: it is the one
the plan names), then ``create``\\ s the owners key unless somebody has: the first to try wins, and
when it cannot (it died too, it lost the store), the next one in the order takes over a step later.

The orphans of one rank are claimed together, in one call (:meth:`SharedStore.create_many
<services.apps.registry.store.SharedStore.create_many>`: 128 owners keys a transaction on etcd), not
one transaction each: a dead gateway's thousand devices are a few dozen transactions, not a
thousand at once that etcd would apply behind every gateway's lease renewal.

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

    ``plan()`` gives the orphans and the loads now; ``attempt(names)`` creates the owners keys of
    those still orphans, in one go (the cluster node does, and opens the devices it wins). A plan
    makes one attempt per rank, so the tasks waiting are at most the gateways of the cluster per plan.
    """

    def __init__(
        self,
        me: str,
        *,
        step: float,
        plan: Callable[[], tuple[list[str], dict[str, int]]],
        attempt: Callable[[list[str]], Awaitable[None]],
    ) -> None:
        self.me = me
        self.step = step
        self._plan = plan
        self._attempt = attempt
        self._batch: asyncio.TimerHandle | None = None
        #: The orphans an attempt is waiting for (bounded by the registrations).
        self._pending: set[str] = set()
        #: The attempts waiting, one per rank of a plan.
        self._tasks: set[asyncio.Task[None]] = set()

    def orphaned(self) -> None:
        """Some registration lost its owner: make a plan shortly (one plan for a burst)."""
        if self._batch is None:
            self._batch = asyncio.get_running_loop().call_later(BATCH_DELAY, self._make_plan)

    def _make_plan(self) -> None:
        self._batch = None
        orphans, loads = self._plan()
        by_rank: dict[int, list[str]] = {}
        for name, rank in takeover_ranks(orphans, loads, self.me).items():
            if name not in self._pending:
                by_rank.setdefault(rank, []).append(name)
        loop = asyncio.get_running_loop()
        for rank, names in sorted(by_rank.items()):
            self._pending.update(names)
            task = loop.create_task(
                self._after(names, rank * self.step), name=f"cluster: take over {len(names)} at rank {rank}"
            )
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _after(self, names: list[str], delay: float) -> None:
        try:
            if delay > 0:
                await asyncio.sleep(delay)
            await self._attempt(names)
        finally:
            self._pending.difference_update(names)

    async def aclose(self) -> None:
        """Stop every pending attempt."""
        if self._batch is not None:
            self._batch.cancel()
            self._batch = None
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self._pending.clear()

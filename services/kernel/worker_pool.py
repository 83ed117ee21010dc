"""Running one piece of async work per item with a fixed number of workers."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Iterable

__all__ = ["run_bounded"]


async def run_bounded(items: Iterable[str], work: Callable[[str], Awaitable[None]], limit: int) -> None:
    """Run ``work(item)`` for every item, at most ``limit`` at once.

    A fixed pool of workers pulls from one iterator: no task or semaphore
    waiter per item, so ten thousand items cost what a thousand do, per item.
    The registry's liveness checks and ``find``, and a group's calls to its
    members, fan out through it.
    """
    todo = list(items)
    pending = iter(todo)

    async def worker() -> None:
        for item in pending:
            await work(item)

    await asyncio.gather(*(worker() for _ in range(min(limit, len(todo)))))

"""Liveness: which services answer, which are down, which have been down too long."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Collection

from services.apps.registry.entry import ServiceEntry, now
from services.apps.registry.table import ServiceTable
from services.kernel.backend import Backend
from services.kernel.directory import Directory
from services.kernel.errors import PropertyError
from services.kernel.worker_pool import run_bounded

__all__ = ["MAX_CONCURRENT_CHECKS", "Liveness"]

log = logging.getLogger(__name__)

#: Liveness checks running at once; a registry of thousands of devices does not dial them all at once.
MAX_CONCURRENT_CHECKS = 64


class Liveness:
    """Checks the services of ``table`` that are not in-process (see :mod:`services.apps.registry`).

    Every ``period`` seconds each polled service gets ``timeout`` seconds to
    answer :meth:`Backend.check`; after ``misses`` misses in a row it is down.
    A service with a lease is not polled: it is down once the lease lapses.
    One that is neither ``static`` nor local is removed (``unregister``)
    after ``grace`` seconds down. ``busy(name)``: being (un)registered now,
    left alone. ``answered(name, backend)``: a service answered a check.
    """

    def __init__(
        self,
        table: ServiceTable,
        directory: Directory | None,
        *,
        period: float,
        timeout: float,
        misses: int,
        grace: float,
        static: Collection[str],
        busy: Callable[[str], bool],
        unregister: Callable[[str], Awaitable[None]],
        answered: Callable[[str, Backend], None],
    ) -> None:
        self.table = table
        self.directory = directory
        self.period = period
        self.timeout = timeout
        self.misses = misses
        self.grace = grace
        self._static = static
        self._busy = busy
        self._unregister = unregister
        self._answered = answered
        self._loop: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Check every ``period`` seconds from now on (nothing when ``period`` is 0)."""
        if self.period > 0 and self._loop is None:
            self._loop = asyncio.get_running_loop().create_task(self._run(), name="registry: liveness")

    async def stop(self) -> None:
        """Stop checking."""
        loop, self._loop = self._loop, None
        if loop is not None:
            loop.cancel()
            await asyncio.gather(loop, return_exceptions=True)

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(self.period)
            await self.check_all()

    async def check_all(self) -> None:
        """One round of liveness checks."""
        directory = self.directory
        if directory is None:
            return
        at = now()
        polled: list[str] = []
        for name, entry in self.table.entries():
            if entry.is_local() or self._busy(name):
                continue
            if entry.has_lease():
                if entry.lease_lapsed(at):
                    self.table.missed(name, entry, allowed=self.misses, lapsed=True)
            else:
                polled.append(name)

        async def check(name: str) -> None:
            entry = self.table.get(name)
            if entry is not None:
                await self._check(directory, name, entry)

        await run_bounded(polled, check, MAX_CONCURRENT_CHECKS)
        for name, entry in self.table.entries():
            down_for = entry.down_for(now())
            if down_for is None or name in self._static or entry.is_local() or self._busy(name):
                continue
            if down_for >= self.grace:
                log.info("service %s was down for %g s: removing it", name, self.grace)
                try:
                    await self._unregister(name)
                except PropertyError as e:
                    log.warning("removing %s failed: %s", name, e.message)

    async def _check(self, directory: Directory, name: str, entry: ServiceEntry) -> None:
        try:
            backend = directory.backend(name)
            async with asyncio.timeout(self.timeout):
                await backend.check()
        except (PropertyError, TimeoutError):
            self.table.missed(name, entry, allowed=self.misses)
            return
        self._answered(name, backend)
        self.table.answered(name, entry)

"""Keys written in the background, the latest value of each key winning.

A state change or a new count of owned services is heard in a plain callback, which cannot
await a write to the store. :class:`LatestWrites` takes the write, keeps only the newest value
per key (a burst of state changes is one write of the last state), and one task writes them in
the order their keys were first touched: the puts waiting side by side in one folder go in one
bulk write (a gateway that took a thousand devices over reports their states in a few
transactions, not a thousand). A write the store refuses (it cannot be reached) is
dropped with a log line: when the store is back, the cluster writes every key it holds again
(:meth:`gateway.cluster.ClusterNode` on reconnect), so nothing waits unbounded here.
"""

from __future__ import annotations

import asyncio
import logging

from services.apps.registry.store import Kind, SharedStore
from services.kernel.errors import PropertyError

__all__ = ["LatestWrites"]

log = logging.getLogger(__name__)


class LatestWrites:
    """Puts (or deletes, with None) waiting to be written, one per key; see the module docstring."""

    def __init__(self, store: SharedStore) -> None:
        self._store = store
        #: (kind, name) → (value or None to delete, leased); one entry per key, so bounded by the keys.
        self._waiting: dict[tuple[Kind, str], tuple[str | None, bool]] = {}
        self._writer: asyncio.Task[None] | None = None
        self._closed = False

    def put(self, kind: Kind, name: str, value: str | None, *, leased: bool = True) -> None:
        """Write ``value`` to the key soon (delete it when None); a newer value replaces a waiting one."""
        if self._closed:
            return
        self._waiting[(kind, name)] = (value, leased)
        if self._writer is None or self._writer.done():
            self._writer = asyncio.get_running_loop().create_task(self._write(), name="cluster: key writer")

    async def _write(self) -> None:
        while self._waiting:
            kind, leased, deleting, values = self._take_run()
            try:
                if deleting:
                    for name in values:
                        await self._store.delete(kind, name)
                else:
                    await self._store.put_many(kind, values, leased=leased)
            except PropertyError as exc:
                log.info("cluster: cannot write %d keys of %s now: %s", len(values), kind.value, exc.message)

    def _take_run(self) -> tuple[Kind, bool, bool, dict[str, str]]:
        """Take the first waiting writes that are alike (one folder, leased or not, puts or deletes):
        (kind, leased, deleting, name → value)."""
        run: dict[str, str] = {}
        first: tuple[Kind, bool, bool] | None = None
        for (kind, name), (value, leased) in self._waiting.items():
            alike = (kind, leased, value is None)
            if first is None:
                first = alike
            elif alike != first:
                break
            run[name] = value or ""
        assert first is not None
        for name in run:
            del self._waiting[(first[0], name)]
        return first[0], first[1], first[2], run

    async def flush(self) -> None:
        """Wait until every waiting write is done."""
        writer = self._writer
        if writer is not None:
            await asyncio.shield(writer)

    async def aclose(self) -> None:
        """Write what waits, then take no more."""
        await self.flush()
        self._closed = True

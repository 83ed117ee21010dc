"""The types of services on another gateway, asked of its registry many names at a time.

A gRPC proxy learns its service's type from the remote gateway's registry
(``services.NAME.type``). A gateway of a cluster forwards thousands of services to each owner,
and opens their proxies together when it joins; asked one Get per service, that is thousands of
calls in a burst, again each time the owners report their devices ``up``. :class:`RemoteTypes`
(one per shared channel, :mod:`gateway.proxies.grpc_channels`) gathers the names asked while a
query is on its way and asks them all in the next one: one Get with ``more`` paths, at most
:data:`MAX_NAMES_PER_GET` names each, one query in flight per remote gateway.

A Get is all or nothing: when one name makes it fail (the remote registry does not know it: it
was unregistered meanwhile), the batch is asked again in halves, so every other name still gets
its answer and the failing one its own error.
"""

from __future__ import annotations

import asyncio
import contextvars
import functools
import itertools
from collections.abc import Callable, Iterable
from typing import Any

import grpc

from gateway.fronts.grpc_v1.status import error_from_remote
from gateway.peer_protocol import SPOKEN_HEADER
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.errors import Code, PropertyError, Unavailable

__all__ = ["MAX_NAMES_PER_GET", "REMOTE_REGISTRY", "RemoteTypes"]

#: The name a gateway serves its registry under (``gateway.config.REGISTRY_NAME``), asked for the types.
REMOTE_REGISTRY = "registry"
#: Names one Get asks for. A gateway reads at most ``[limits] max_get_paths`` paths in one Get
#: (1,000 by default); a quarter of that leaves room for a remote that lowered it, and one that
#: refuses (RESOURCE_EXHAUSTED) is asked in halves.
MAX_NAMES_PER_GET = 250
#: Codes a batch can get because of one of its names, not because of the remote: asked in halves.
_ONE_NAMES_FAULT = frozenset({Code.NOT_FOUND, Code.INVALID_ARGUMENT, Code.RESOURCE_EXHAUSTED})


def _retrieved(future: asyncio.Future[str]) -> None:
    # Whoever asked may have stopped waiting (a timeout): the error was still seen, not leaked.
    if not future.cancelled():
        future.exception()


class RemoteTypes:
    """``services.NAME.type`` of one remote gateway's registry, asked in batches (module docstring).

    What waits is bounded by the proxies on the channel: each name is asked at most once per
    batch, however many ask for it.
    """

    def __init__(self, stub: Any, target: str, timeout: float) -> None:
        """``stub``: the PropertyService stub of the shared channel; ``target``: the remote's
        ``host:port`` (for messages); ``timeout``: seconds one Get may take."""
        self._stub = stub
        self.target = target
        self.timeout = timeout
        #: Names to ask in the next Get, with the future each asker waits on.
        self._pending: dict[str, asyncio.Future[str]] = {}
        self._asking: asyncio.Task[None] | None = None
        self._closed = False
        #: Gets made so far (for tests and measurements).
        self.queries = 0

    def _label(self) -> str:
        return f"registry on gateway {self.target}"

    def ask(self, name: str) -> asyncio.Future[str]:
        """The future of ``services.NAME.type`` in the remote registry: its value (``unknown`` while
        the remote has not heard from the service's device), or the remote's error as a
        :class:`~services.kernel.errors.PropertyError` (Unavailable when the channel closes first)."""
        loop = asyncio.get_running_loop()
        future = self._pending.get(name)
        if future is not None:
            return future
        future = loop.create_future()
        future.add_done_callback(_retrieved)
        if self._closed:
            self._fail([future], self._closed_error)
            return future
        self._pending[name] = future
        if self._asking is None:
            # Asked on behalf of no request (several requests' names share one Get): a fresh
            # context, so that no caller's request id or ps-via chain goes with it.
            self._asking = loop.create_task(
                self._ask_pending(), name=f"types from {self.target}", context=contextvars.Context()
            )
        return future

    async def _ask_pending(self) -> None:
        try:
            while self._pending:
                names = list(itertools.islice(self._pending, MAX_NAMES_PER_GET))
                batch = {name: self._pending.pop(name) for name in names}
                try:
                    await self._answer(batch)
                finally:
                    # only those left unanswered: the channel closed
                    self._fail(batch.values(), self._closed_error)
        finally:
            self._asking = None

    async def _answer(self, batch: dict[str, asyncio.Future[str]]) -> None:
        names = list(batch)
        paths = [f"services.{name}.type" for name in names]
        request = pb.GetRequest(
            service=REMOTE_REGISTRY, property=paths[0], more=[pb.PropertyRef(property=p) for p in paths[1:]]
        )
        self.queries += 1
        try:
            # Asked on no client's behalf: no ps-via chain, only the versions this gateway speaks.
            reply = await self._stub.Get(request, timeout=self.timeout, metadata=(SPOKEN_HEADER,))
        except grpc.aio.AioRpcError as exc:
            error = error_from_remote(exc, self._label(), self.timeout)
            if len(names) > 1 and error.code in _ONE_NAMES_FAULT:
                half = len(names) // 2
                await self._answer({name: batch[name] for name in names[:half]})
                await self._answer({name: batch[name] for name in names[half:]})
                return
            self._fail(batch.values(), functools.partial(error_from_remote, exc, self._label(), self.timeout))
            return
        values = [reply.value, *(item.value for item in reply.more)]
        if len(values) != len(names):
            message = f"{self._label()}: {len(values)} values for {len(names)} paths"
            self._fail(batch.values(), lambda: PropertyError(message, Code.INTERNAL))
            return
        for future, value in zip(batch.values(), values, strict=True):
            if not future.done():
                future.set_result(value)

    def _closed_error(self) -> PropertyError:
        return Unavailable(f"{self._label()}: the channel is closed")

    @staticmethod
    def _fail(futures: Iterable[asyncio.Future[str]], error: Callable[[], PropertyError]) -> None:
        """Fail each of ``futures`` not answered yet with an error of its own, made by ``error``."""
        for future in futures:
            if not future.done():
                future.set_exception(error())

    async def aclose(self) -> None:
        """Stop asking; whoever waits gets Unavailable."""
        self._closed = True
        asking, self._asking = self._asking, None
        if asking is not None:
            asking.cancel()
            await asyncio.gather(asking, return_exceptions=True)
        pending = list(self._pending.values())
        self._pending.clear()
        self._fail(pending, self._closed_error)

"""The synchronous client: :class:`Client`, the blocking twin of :class:`AsyncClient`.

It runs one :class:`AsyncClient` on a private event loop in a background
thread, so both clients share one implementation, one error mapping and one
Session protocol; each call hands a coroutine to that loop and waits for it.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import AsyncIterator, Awaitable, Iterable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Generic, Self, TypeVar

from clients.aio import (
    DEFAULT_FAILOVER_LIMIT,
    DEFAULT_KEEPALIVE,
    DEFAULT_MAX_IN_FLIGHT,
    DEFAULT_SESSION_QUEUE,
    DEFAULT_TARGET,
    DEFAULT_TIMEOUT,
    AsyncClient,
    Event,
    History,
    ListenCalls,
    Mark,
    Reading,
    Selector,
    TimeArg,
)
from clients.aio import Session as AsyncSession
from clients.credentials import ClientCredentials
from clients.errors import DeadlineExceeded
from clients.values import Marker, Value
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.model import ServiceModel

if TYPE_CHECKING:
    from clients.values import Vector

__all__ = ["Client", "ListenIterator", "SyncSession"]

T = TypeVar("T")

# Extra seconds the calling thread waits beyond a call's own deadline, so that
# the call reports its own DEADLINE_EXCEEDED rather than the thread giving up first.
_GRACE = 5.0


class _LoopThread:
    """An event loop running forever in a daemon thread; ``call_limit`` bounds each :meth:`call`."""

    def __init__(self, call_limit: float | None) -> None:
        self.call_limit = call_limit
        self.loop = asyncio.new_event_loop()
        ready = threading.Event()
        self.loop.call_soon(ready.set)
        self.thread = threading.Thread(target=self.loop.run_forever, name="psclient", daemon=True)
        self.thread.start()
        ready.wait(_GRACE)

    def run(self, aw: Awaitable[T], timeout: float | None) -> T:
        if not self.loop.is_running():
            raise RuntimeError("the client is closed")
        future = asyncio.run_coroutine_threadsafe(_await(aw), self.loop)
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise DeadlineExceeded(None, f"no answer within {timeout} s") from None
        except BaseException:
            future.cancel()  # e.g. KeyboardInterrupt in the caller: do not leave the call running
            raise

    def call(self, aw: Awaitable[T]) -> T:
        """Run one call of the client on the loop, waiting at most ``call_limit`` seconds."""
        return self.run(aw, self.call_limit)

    def stop(self) -> None:
        if self.loop.is_running():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(_GRACE)
        if not self.thread.is_alive() and not self.loop.is_closed():
            self.loop.close()


async def _await(aw: Awaitable[T]) -> T:
    return await aw


class _ClosedOnExit:
    """``with`` support for a class with a ``close()``: leaving the block closes it."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        raise NotImplementedError


class ListenIterator(_ClosedOnExit, Generic[T]):
    """A blocking iterator over a Listen; ``close()`` (or leaving ``with``) ends the stream."""

    def __init__(self, runner: _LoopThread, agen: AsyncIterator[T]) -> None:
        self._runner = runner
        self._agen = agen
        self._closed = False

    def __iter__(self) -> Self:
        return self

    def __next__(self) -> T:
        if self._closed:
            raise StopIteration
        try:
            return self._runner.run(self._agen.__anext__(), None)
        except StopAsyncIteration:
            self._closed = True
            raise StopIteration from None
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """End the stream. Idempotent."""
        if self._closed:
            return
        self._closed = True
        aclose = getattr(self._agen, "aclose", None)
        if aclose is not None and self._runner.loop.is_running():
            self._runner.run(aclose(), _GRACE)

    def __del__(self) -> None:
        if not self._closed and self._runner.loop.is_running():
            aclose = getattr(self._agen, "aclose", None)
            if aclose is not None:
                asyncio.run_coroutine_threadsafe(_await(aclose()), self._runner.loop)


class _BlockingCalls(_ClosedOnExit, ListenCalls[ListenIterator[Event], ListenIterator[Event | Mark]]):
    """Get, Set and Listen of an asyncio client or session, each call run on the loop thread."""

    def __init__(self, runner: _LoopThread, calls: AsyncClient | AsyncSession) -> None:
        self._runner = runner
        self._calls = calls

    def get(self, service: str, prop: str, /, **params: Any) -> Value:
        """See :meth:`clients.aio.AsyncClient.get`."""
        return self._runner.call(self._calls.get(service, prop, **params))

    def get_matching(self, service: str, pattern: str, /, **params: Any) -> dict[str, Value]:
        """See :meth:`clients.aio.AsyncClient.get_matching`."""
        return self._runner.call(self._calls.get_matching(service, pattern, **params))

    def get_many(self, refs: Iterable[Selector]) -> list[Value]:
        """See :meth:`clients.aio.AsyncClient.get_many`."""
        return self._runner.call(self._calls.get_many(list(refs)))

    def set(self, service: str, prop: str, value: Any, /, **params: Any) -> Value:
        """See :meth:`clients.aio.AsyncClient.set`."""
        return self._runner.call(self._calls.set(service, prop, value, **params))

    def start_listen(
        self, request: pb.ListenRequest, marks: bool, resume: bool = False
    ) -> ListenIterator[Any]:
        """A blocking iterator over the Listen for ``request``; see :meth:`listen`. Close it when done."""
        return ListenIterator(self._runner, self._calls.start_listen(request, marks, resume))


class Client(_BlockingCalls):
    """Blocking client of a Property Service gateway; same methods as :class:`AsyncClient`.

    Use as ``with Client("127.0.0.1:50051") as c: c.get("scout1", "location")``.
    Safe to call from several threads at once.
    """

    def __init__(
        self,
        target: str | Sequence[str] = DEFAULT_TARGET,
        *,
        timeout: float | None = DEFAULT_TIMEOUT,
        metadata: Iterable[tuple[str, str]] | None = None,
        max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
        credentials: ClientCredentials | None = None,
        separate_listens: bool = False,
        keepalive: float | None = DEFAULT_KEEPALIVE,
        failover_limit: float | None = DEFAULT_FAILOVER_LIMIT,
    ) -> None:
        """``target``: one gateway address or several to fail over between; ``credentials``: TLS
        and a bearer token; ``separate_listens``: each listen on a stream of its own rather than
        inside one shared Session; ``keepalive``, ``failover_limit``: how soon a dead or frozen
        gateway is left, and how long a resumed listen tries; all as for
        :class:`~clients.aio.AsyncClient`."""
        self.timeout = timeout
        self._aio = AsyncClient(
            target,
            timeout=timeout,
            metadata=metadata,
            max_in_flight=max_in_flight,
            credentials=credentials,
            separate_listens=separate_listens,
            keepalive=keepalive,
            failover_limit=failover_limit,
        )
        super().__init__(_LoopThread(None if timeout is None else timeout + _GRACE), self._aio)

    @property
    def target(self) -> str:
        """The gateway address in use now."""
        return self._aio.target

    def close(self) -> None:
        """Close the channel and stop the background loop. Idempotent."""
        if self._runner.loop.is_running():
            self._runner.run(self._aio.close(), _GRACE)
        self._runner.stop()

    def get_with_time(self, service: str, prop: str, /, **params: Any) -> Reading:
        """See :meth:`AsyncClient.get_with_time`."""
        return self._runner.call(self._aio.get_with_time(service, prop, **params))

    def history(
        self,
        service: str,
        prop: str,
        /,
        *,
        since: TimeArg = None,
        until: TimeArg = None,
        limit: int = 0,
    ) -> History:
        """See :meth:`AsyncClient.history`."""
        return self._runner.call(self._aio.history(service, prop, since=since, until=until, limit=limit))

    def get_bytes(self, service: str, prop: str, /, **params: Any) -> bytes:
        """See :meth:`AsyncClient.get_bytes`."""
        return self._runner.call(self._aio.get_bytes(service, prop, **params))

    def get_number(self, service: str, prop: str, /, **params: Any) -> float:
        """See :meth:`AsyncClient.get_number`."""
        return self._runner.call(self._aio.get_number(service, prop, **params))

    def get_vector(self, service: str, prop: str, /, **params: Any) -> Vector:
        """See :meth:`AsyncClient.get_vector`."""
        return self._runner.call(self._aio.get_vector(service, prop, **params))

    def get_vectors(self, service: str, prop: str, /, **params: Any) -> list[Vector]:
        """See :meth:`AsyncClient.get_vectors`."""
        return self._runner.call(self._aio.get_vectors(service, prop, **params))

    def get_names(self, service: str, prop: str, /, **params: Any) -> list[str]:
        """See :meth:`AsyncClient.get_names`."""
        return self._runner.call(self._aio.get_names(service, prop, **params))

    def get_marker(self, service: str, prop: str, /, **params: Any) -> Marker:
        """See :meth:`AsyncClient.get_marker`."""
        return self._runner.call(self._aio.get_marker(service, prop, **params))

    def services(self) -> list[str]:
        """See :meth:`AsyncClient.services`."""
        return self._runner.call(self._aio.services())

    def properties(self, service: str) -> list[str]:
        """See :meth:`AsyncClient.properties`."""
        return self._runner.call(self._aio.properties(service))

    def describe(self, service: str) -> ServiceModel:
        """See :meth:`AsyncClient.describe`."""
        return self._runner.call(self._aio.describe(service))

    def session(self, *, max_pending: int = DEFAULT_SESSION_QUEUE) -> SyncSession:
        """An open :class:`SyncSession`: ``with client.session() as s: s.get(...)``."""
        session = self._aio.session(max_pending=max_pending)
        self._runner.run(session.open(), _GRACE)
        return SyncSession(self._runner, session)


class SyncSession(_BlockingCalls):
    """Blocking view of a :class:`clients.aio.Session`; calls from several threads share one stream."""

    def __init__(self, runner: _LoopThread, session: AsyncSession) -> None:
        super().__init__(runner, session)
        self._session = session

    def close(self) -> None:
        """End the session. Idempotent."""
        if self._runner.loop.is_running():
            self._runner.run(self._session.aclose(), _GRACE)

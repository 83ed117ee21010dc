"""How a chart reaches Property Services: Get, Set and Listen through the gateway's directory.

The directory is the gateway's router (:class:`services.kernel.directory.Directory`), so a
chart reaches every service the gateway does: in-process, proxied to a device,
or another gateway's. Every call has a time limit; a call that fails or runs
out of time raises a :class:`~services.kernel.errors.PropertyError`, which the
interpreter turns into an ``error.action`` event of the chart.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Coroutine, Mapping
from typing import Any, TypeVar

from services.kernel.backend import NO_PARAMS, Backend, Notify, Subscription
from services.kernel.directory import Directory
from services.kernel.eager import Started, step
from services.kernel.errors import DeadlineExceeded
from services.kernel.values import Value

T = TypeVar("T")

__all__ = ["DEFAULT_ACTION_TIMEOUT", "PropertyBinding"]

#: Seconds an action (a Set or a Get) may take unless the chart says otherwise: the gateway's call timeout.
DEFAULT_ACTION_TIMEOUT = 5.0


class PropertyBinding:
    """Get, Set and Listen any service of ``directory``, each under a time limit."""

    def __init__(self, directory: Directory, timeout: float = DEFAULT_ACTION_TIMEOUT) -> None:
        self.directory = directory
        self.timeout = timeout

    async def set(
        self,
        service: str,
        path: str,
        value: Value,
        params: Mapping[str, str] = NO_PARAMS,
        limit_s: float | None = None,
    ) -> Value:
        limit = self.timeout if limit_s is None else limit_s
        backend = self.directory.backend(service)
        return await _bounded(backend, backend.set(path, value, params), limit, f"Set of {service}/{path}")

    async def get(
        self, service: str, path: str, params: Mapping[str, str] = NO_PARAMS, limit_s: float | None = None
    ) -> Value:
        limit = self.timeout if limit_s is None else limit_s
        backend = self.directory.backend(service)
        return await _bounded(backend, backend.get(path, params), limit, f"Get of {service}/{path}")

    async def listen(self, service: str, path: str, notify: Notify) -> Subscription:
        backend = self.directory.backend(service)
        try:
            async with asyncio.timeout(self.timeout):
                return await backend.listen(path, notify)
        except TimeoutError:
            why = f"Listen to {service}/{path}: no answer within {self.timeout:g} s"
            raise DeadlineExceeded(why) from None


async def _bounded(backend: Backend, call: Coroutine[Any, Any, T], limit: float, what: str) -> T:
    """``call`` under ``limit`` seconds; an in-process answer that needs no wait costs no timer."""
    pending: Awaitable[T] = call
    if backend.answers_inline:
        first = step(call)
        if not isinstance(first, Started):
            return first
        pending = first.rest()
    try:
        async with asyncio.timeout(limit):
            return await pending
    except TimeoutError:
        raise DeadlineExceeded(f"{what}: no answer within {limit:g} s") from None

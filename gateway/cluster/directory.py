"""The registry's directory on a gateway of a cluster: (un)registrations go through the cluster.

The registry turns a Set of ``services.NAME`` into ``directory.register(NAME, URL)``. On a gateway
of a cluster it is handed a :class:`ClusterDirectory`: the same live set of services as the router's
own directory, but registering claims the name in the shared store first (its ``owners`` and
``services`` keys, see :meth:`gateway.cluster.node.ClusterNode.register`), and unregistering
deletes them, on whichever gateway the Set arrives.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from gateway.engine.router import RouterDirectory
from services.kernel.backend import Backend, BackendInfo
from services.kernel.directory import DirectoryListener

__all__ = ["ClusterDirectory", "ClusterRegistrar"]


class ClusterRegistrar(Protocol):
    """What registers and unregisters a service in the cluster (a
    :class:`gateway.cluster.node.ClusterNode`)."""

    async def register(
        self, name: str, url: str, options: Mapping[str, Any] | None = None
    ) -> BackendInfo: ...

    async def unregister(self, name: str) -> None: ...


class ClusterDirectory:
    """A :class:`services.kernel.directory.Directory` whose changes go through a :class:`ClusterRegistrar`."""

    def __init__(self, router: RouterDirectory, node: ClusterRegistrar) -> None:
        self._node = node
        self._router = router

    def names(self) -> list[str]:
        return self._router.names()

    def __contains__(self, name: object) -> bool:
        return name in self._router

    def backend(self, name: str) -> Backend:
        return self._router.backend(name)

    def watch(self, listener: DirectoryListener) -> Callable[[], None]:
        return self._router.watch(listener)

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        return await self._node.register(name, url, options)

    async def serve(self, name: str, backend: Backend) -> None:
        # A service's own in-process backends are this gateway's, as its configured services are:
        # served here, not claimed in the cluster's store.
        await self._router.serve(name, backend)

    async def unregister(self, name: str) -> None:
        await self._node.unregister(name)

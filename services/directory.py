"""How a service reaches other services: the gateway's directory of backends.

System services (the registry, groups of robots) hold other services. They
never import the gateway; the gateway hands them an object that satisfies
:class:`Directory` (its router), and tests can hand them a small in-memory one.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from services.backend import Backend, BackendInfo

#: Called with (name, backend) when a service appears, (name, None) when it goes.
DirectoryListener = Callable[[str, Backend | None], None]


class Directory(Protocol):
    """The live set of services behind one gateway."""

    def names(self) -> list[str]:
        """Names of every service right now."""
        ...

    def __contains__(self, name: object) -> bool:
        """Whether ``name`` is served right now, down or not (a dict lookup: no list is made)."""
        ...

    def backend(self, name: str) -> Backend:
        """The backend serving ``name``; raises ``NotFound``."""
        ...

    def watch(self, listener: DirectoryListener) -> Callable[[], None]:
        """Call ``listener`` on every join and leave; returns a function that stops watching."""
        ...

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        """Create a backend for ``url`` (``tcp://``, ``serial://``, ``grpc://``) and serve it as ``name``.

        Raises ``InvalidArgument`` for a malformed URL or name, ``AlreadyExists``
        for a taken name, ``Unavailable`` when the device cannot be reached.
        """
        ...

    async def unregister(self, name: str) -> None:
        """Stop serving ``name`` and close its backend; raises ``NotFound``."""
        ...

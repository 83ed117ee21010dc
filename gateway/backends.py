"""Open a backend from a configuration entry or a registration.

An entry with ``type`` is an in-process service: ``services.apps.catalog.build(type,
options)`` builds the resource and ``services.kernel.core.serve`` serves it (a LocalService, or
the subclass its class names).
An entry with ``url`` is a proxy: the URL's scheme picks a factory from the
static table :data:`PROXY_SCHEMES`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from gateway.proxies.grpc_proxy import open_grpc_backend
from gateway.proxies.serial import open_serial_backend
from gateway.proxies.tcp import open_tcp_backend
from services.apps.catalog import build
from services.kernel.backend import Backend
from services.kernel.core import serve
from services.kernel.errors import InvalidArgument, PropertyError

if TYPE_CHECKING:
    from gateway.config import ServiceEntry
    from services.kernel.directory import Directory
    from services.kernel.follow import Follow

#: (service name, url, options) → a Backend that is not started yet.
ProxyFactory = Callable[[str, str, Mapping[str, Any]], Backend]

#: URL scheme → proxy factory. Every proxy ships with the gateway, so the table is fixed.
PROXY_SCHEMES: Mapping[str, ProxyFactory] = MappingProxyType(
    {
        "tcp": open_tcp_backend,
        "serial": open_serial_backend,
        "grpc": open_grpc_backend,
        "grpcs": open_grpc_backend,
    }
)


def open_proxy(name: str, url: str, options: Mapping[str, Any]) -> Backend:
    """A proxy backend for ``url`` (not started); raises InvalidArgument for an unknown scheme."""
    factory = PROXY_SCHEMES.get(urlsplit(url).scheme)
    if factory is None:
        known = ", ".join(f"{s}://" for s in sorted(PROXY_SCHEMES))
        raise InvalidArgument(f"service {name!r}: unknown URL scheme in {url!r} (known: {known})")
    return factory(name, url, options)


def open_backend(
    entry: ServiceEntry, directory: Directory | None = None, follow: Follow | None = None
) -> Backend:
    """The backend a config entry describes (not started); raises PropertyError when it cannot be built.

    ``directory`` is the gateway's directory of services
    (:attr:`gateway.engine.router.Router.directory`), handed to the kinds that reach
    other services (``type = "group"``), and ``follow`` (:class:`gateway.engine.listen.follow.HubFollow`)
    to the kinds that follow changes as a Listen does (``type = "recorder"``).
    """
    if entry.url:
        return open_proxy(entry.name, entry.url, entry.options)
    try:
        resource = build(entry.type, entry.options, directory, follow)
    except PropertyError:
        raise
    except TypeError as exc:
        raise InvalidArgument(f"service {entry.name!r} of type {entry.type!r}: bad options: {exc}") from None
    return serve(resource)

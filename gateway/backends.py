"""Open a backend from a configuration entry.

An entry with ``type`` is an in-process service: ``services.catalog.create(type,
**options)`` builds the resource and ``services.core.LocalService`` serves it.
An entry with ``url`` is a proxy: the URL's scheme picks a factory from
:data:`PROXY_SCHEMES`.

Proxies plug in here. The package ``gateway.proxies`` registers its factories
when imported, e.g. in ``gateway/proxies/__init__.py``::

    from gateway.backends import PROXY_SCHEMES
    PROXY_SCHEMES["tcp"] = TcpProxy.from_url      # (name, url, options) -> Backend

and may offer a raw-TCP line-protocol listener by setting
:data:`LINE_LISTENER` (used when ``gateway.line_listen`` is configured).
This module imports ``gateway.proxies`` (when it exists) before resolving a
scheme, so nothing else needs to import it first.
"""

from __future__ import annotations

import importlib
from collections.abc import Awaitable, Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import urlsplit

from services.backend import Backend
from services.errors import InvalidArgument, PropertyError

if TYPE_CHECKING:
    from gateway.config import ServiceEntry
    from gateway.router import Router
    from services.directory import Directory

#: (service name, url, options) → a Backend that is not started yet.
ProxyFactory = Callable[[str, str, Mapping[str, Any]], Backend]

#: URL scheme → factory. ``gateway.proxies`` registers "tcp" and "serial".
PROXY_SCHEMES: dict[str, ProxyFactory] = {}


class Closeable(Protocol):
    """Something that runs until closed."""

    async def aclose(self) -> None: ...


#: Starts the raw-TCP line-protocol listener on "host:port"; devices that dial
#: in are served through ``router``. Set by ``gateway.proxies``; None = not available.
LINE_LISTENER: Callable[[str, Router], Awaitable[Closeable]] | None = None

_proxies_loaded = False


def load_proxies() -> None:
    """Import ``gateway.proxies`` once so that it registers its schemes (absent = no proxies)."""
    global _proxies_loaded
    if _proxies_loaded:
        return
    _proxies_loaded = True
    try:
        importlib.import_module("gateway.proxies")
    except ModuleNotFoundError as exc:
        if exc.name != "gateway.proxies":
            raise


def open_proxy(name: str, url: str, options: Mapping[str, Any]) -> Backend:
    """A proxy backend for ``url`` (not started); raises InvalidArgument for an unknown scheme."""
    load_proxies()
    scheme = urlsplit(url).scheme
    factory = PROXY_SCHEMES.get(scheme)
    if factory is None:
        known = ", ".join(f"{s}://" for s in sorted(PROXY_SCHEMES)) or "none are installed"
        raise InvalidArgument(f"service {name!r}: unknown URL scheme in {url!r} (known: {known})")
    return factory(name, url, options)


def open_backend(entry: ServiceEntry, router: Router | Directory | None = None) -> Backend:
    """The backend a config entry describes (not started); raises PropertyError when it cannot be built.

    ``router`` is the gateway's directory of services, handed to the kinds
    that reach other services (``type = "group"``); a router hands on its
    :attr:`~gateway.router.Router.directory`.
    """
    if entry.url:
        return open_proxy(entry.name, entry.url, entry.options)
    from gateway.router import Router
    from services.catalog import create
    from services.core import LocalService

    directory = router.directory if isinstance(router, Router) else router
    try:
        resource = create(entry.type, directory=directory, **entry.options)
    except PropertyError:
        raise
    except TypeError as exc:
        raise InvalidArgument(f"service {entry.name!r} of type {entry.type!r}: bad options: {exc}") from None
    return LocalService(resource)

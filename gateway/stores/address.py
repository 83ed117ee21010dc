"""Where a shared store is: the ``[registry] store`` URL, parsed and checked.

``etcd://HOST:PORT[,HOST:PORT...]`` names the client ports of one etcd cluster in plain text,
``etcds://`` the same over TLS; an empty value means the embedded store. Each endpoint is tried in
turn when the one in use cannot be reached.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SCHEMES", "StoreAddress", "parse_store_url"]

#: URL scheme → whether it speaks TLS.
SCHEMES = {"etcd": False, "etcds": True}
#: Endpoints one URL may name: an etcd cluster has a handful of members (etcd advises 3, 5 or 7).
MAX_ENDPOINTS = 16


@dataclass(frozen=True, slots=True)
class StoreAddress:
    """A parsed store URL: the scheme and the ``host:port`` of each endpoint."""

    scheme: str
    endpoints: tuple[str, ...]

    @property
    def tls(self) -> bool:
        """True for ``etcds://``."""
        return SCHEMES[self.scheme]

    def __str__(self) -> str:
        return f"{self.scheme}://{','.join(self.endpoints)}"


def parse_store_url(url: str) -> StoreAddress:
    """``etcd://h:p[,h:p...]`` or ``etcds://...`` as a :class:`StoreAddress`; raises ValueError
    saying what is wrong (an unknown scheme, a missing port, no endpoint)."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        raise ValueError(f"expected a URL like 'etcd://127.0.0.1:2379', got {url!r}")
    if scheme not in SCHEMES:
        known = ", ".join(f"{s}://" for s in SCHEMES)
        raise ValueError(f"unknown store scheme {scheme + '://'!r} in {url!r} (known: {known})")
    endpoints = tuple(part.strip() for part in rest.split(","))
    if not rest or len(endpoints) > MAX_ENDPOINTS:
        raise ValueError(f"name 1 to {MAX_ENDPOINTS} endpoints host:port in {url!r}")
    for endpoint in endpoints:
        _check_endpoint(endpoint, url)
    return StoreAddress(scheme, endpoints)


def _check_endpoint(endpoint: str, url: str) -> None:
    host, sep, port = endpoint.rpartition(":")
    if "/" in endpoint or not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise ValueError(f"expected host:port like '127.0.0.1:2379', got {endpoint!r} in {url!r}")

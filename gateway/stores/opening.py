"""The registry store a config names: the embedded one, or etcd (``[registry] store``)."""

from __future__ import annotations

import re
import socket
from pathlib import Path
from typing import TYPE_CHECKING

from gateway.stores.address import parse_store_url
from gateway.stores.etcd import EtcdStore, EtcdTls
from services.apps.registry.embedded import EmbeddedStore
from services.apps.registry.store import RegistryStore

if TYPE_CHECKING:
    from gateway.config import Config

__all__ = ["default_gateway_id", "open_store"]


def default_gateway_id(listen: str) -> str:
    """A stable id for the gateway listening on ``listen`` (host:port): this host's name and the
    port, so that a gateway started again on the same host and port is the same gateway."""
    port = listen.rpartition(":")[2]
    host = re.sub(r"[^A-Za-z0-9._-]", "-", socket.gethostname()) or "gateway"
    return f"{host}-{port}"


def open_store(config: Config, *, listen: str = "") -> RegistryStore:
    """The store of ``config.registry`` (not started yet). ``listen``: the gRPC address the gateway
    listens on, once known (a port 0 in the config is chosen at start); it makes the default
    gateway id."""
    section = config.registry
    if not section.store:
        return EmbeddedStore(Path(section.persist) if section.persist else None)
    return EtcdStore(
        parse_store_url(section.store),
        gateway_id=section.gateway_id or default_gateway_id(listen or config.gateway.listen),
        prefix=section.store_prefix,
        lease=section.store_lease,
        tls=EtcdTls(section.store_ca, section.store_cert, section.store_key),
    )

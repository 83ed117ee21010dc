"""The registry's stores (:mod:`services.apps.registry.store`) as the gateway opens them: etcd
(:mod:`gateway.stores.etcd`), the URL that names it (:mod:`gateway.stores.address`), and
:func:`open_store`, which picks the store a config names (:mod:`gateway.stores.opening`)."""

from gateway.stores.address import StoreAddress, parse_store_url
from gateway.stores.etcd import DEFAULT_LEASE, DEFAULT_PREFIX, EtcdStore, EtcdTls
from gateway.stores.opening import default_gateway_id, open_store

__all__ = [
    "DEFAULT_LEASE",
    "DEFAULT_PREFIX",
    "EtcdStore",
    "EtcdTls",
    "StoreAddress",
    "default_gateway_id",
    "open_store",
    "parse_store_url",
]

"""Many gateways, one registry: the cluster of gateways that share a registry store (docs/scale-out.md).

With ``[registry] store = "etcd://..."`` every gateway runs a :class:`ClusterNode`: it joins the
cluster (its leased ``gateways/ID`` key), serves every registration of the cluster through one
router entry each (a :class:`SwitchingBackend`: the device's own proxy on its owner, a gRPC proxy
to the owner elsewhere), mirrors the owners' states, takes over the registrations of a gateway
that died (:mod:`gateway.cluster.failover`), claims licences with compare-and-set
(:class:`ClusterLicences`) and serves read-only while the store cannot be reached.

Modules: ``records`` (what the keys hold), ``view`` (the cluster as last heard), ``switching``
(the router entry whose target follows the owner), ``writer`` (keys written in the background),
``failover`` (who takes over, and when), ``licences`` (licences by compare-and-set), ``directory``
(the registry's directory on a cluster), ``moves`` (drain and rebalance: who takes devices, how many
move), ``node`` (:class:`ClusterNode`: all of it for one gateway), ``report`` (the registry's
``cluster`` view and its admin actions).
"""

from gateway.cluster.directory import ClusterDirectory
from gateway.cluster.failover import Takeover, takeover_ranks
from gateway.cluster.licences import ClusterLicences
from gateway.cluster.node import ClusterNode
from gateway.cluster.records import GatewayRecord, Registration, read_gateway, read_registration
from gateway.cluster.report import ClusterReport
from gateway.cluster.switching import SwitchingBackend
from gateway.cluster.view import ClusterView

__all__ = [
    "ClusterDirectory",
    "ClusterLicences",
    "ClusterNode",
    "ClusterReport",
    "ClusterView",
    "GatewayRecord",
    "Registration",
    "SwitchingBackend",
    "Takeover",
    "read_gateway",
    "read_registration",
    "takeover_ranks",
]

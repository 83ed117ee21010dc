"""The cluster as the registry shows it: ``registry/cluster`` and ``cluster.members.ID``, live.

:class:`ClusterReport` is attached to a clustered gateway's registry as ``cluster``:

* ``cluster``: JSON of the whole cluster as this gateway sees it (:meth:`ClusterNode.status
  <gateway.cluster.node.ClusterNode.status>`): every member with its address, version, lease
  expiry, health, devices owned, load (calls/s, Listens), read-only state and whether it is
  drained; the rebalance policy; the drain orders. Listen to it to follow the cluster.
* ``cluster.members``: the members' ids; ``cluster.members.ID``: one member's JSON (a member whose
  id is no valid path segment, a host name with dots, is only in ``cluster``).
* ``cluster.drain`` / ``cluster.undrain`` (Set the gateway's id) and ``cluster.rebalance`` (Set,
  no value): the admin actions (a Set on the registry is ``admin`` by the rules).

Per-device owners are the registry's own ``services.NAME.owner`` and ``services.NAME.owner_since``.
A store change, a move or a load report asks for a refresh, made at most every
:data:`REFRESH_EVERY`: a burst of thousands of changes is one refresh, not thousands.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Annotated, Any

from gateway.cluster.node import ClusterNode
from services.kernel.core import Prop, Resource, action
from services.kernel.errors import PropertyError
from services.kernel.paths import validate_service_name
from services.kernel.values import format_names

__all__ = ["REFRESH_EVERY", "ClusterReport", "MemberReport"]

log = logging.getLogger(__name__)

#: Seconds between two refreshes of the view's listeners, at most.
REFRESH_EVERY = 0.25


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"))


class MemberReport(Resource):
    """``cluster.members.ID``: one gateway of the cluster, as JSON (see the module docstring)."""

    resource_type = "cluster_member"

    def __init__(self, node: ClusterNode, gateway: str) -> None:
        self._node = node
        self._gateway = gateway

    def _value(self) -> str:
        status = self._node.member_status(self._gateway)
        return _json(status) if status is not None else ""

    @property
    def draining(self) -> Annotated[bool, Prop(doc="it hands what it owns over and takes nothing new")]:
        status = self._node.member_status(self._gateway)
        return bool(status and status["draining"])


class MemberList(Resource):
    """``cluster.members``: the ids of the live gateways; one child each."""

    resource_type = "cluster_members"

    def __init__(self, node: ClusterNode) -> None:
        self._node = node

    def _value(self) -> str:
        return format_names(sorted({*self._node.view.gateways, self._node.me}))


class ClusterReport(Resource):
    """``registry/cluster``: the cluster view and its admin actions (see the module docstring)."""

    resource_type = "cluster"

    members: MemberList

    def __init__(self, node: ClusterNode) -> None:
        self._node = node
        self.members = MemberList(node)
        self._refresh: asyncio.TimerHandle | None = None
        node.on_view = self.soon

    def _value(self) -> str:
        return _json(self._node.status())

    @property
    def gateway(self) -> Annotated[str, Prop(doc="this gateway's id in the cluster")]:
        return self._node.me

    @action(doc="drain the gateway named by the value: it hands its devices over and takes no new ones")
    async def drain(self, gateway: str) -> str:
        await self._node.set_drain(gateway.strip(), True)
        self.soon()
        return f"draining {gateway.strip()}"

    @action(doc="undrain the gateway named by the value: it takes devices again")
    async def undrain(self, gateway: str) -> str:
        await self._node.set_drain(gateway.strip(), False)
        self.soon()
        return f"undrained {gateway.strip()}"

    @action(doc="every gateway hands devices over until the loads are within the spread")
    async def rebalance(self) -> str:
        await self._node.ask_rebalance()
        return "rebalancing"

    def soon(self) -> None:
        """The view may have changed: refresh its listeners shortly (one refresh for a burst)."""
        if self._refresh is not None:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return
        self._refresh = loop.call_later(REFRESH_EVERY, self._tell)

    def _tell(self) -> None:
        self._refresh = None
        members = self.members
        live = {gateway for gateway in {*self._node.view.gateways, self._node.me} if _valid(gateway)}
        shown = set(members.children())
        for gone in sorted(shown - live):
            members.detach(gone)
        for new in sorted(live - shown):
            members.attach(new, MemberReport(self._node, new))
        for child in members.children().values():
            if isinstance(child, MemberReport):
                child.changed()
                child.changed("draining")
        members.changed()
        self.changed()

    def close(self) -> None:
        """Stop refreshing (the gateway stops)."""
        if self._refresh is not None:
            self._refresh.cancel()
            self._refresh = None
        self._node.on_view = lambda: None


def _valid(gateway: str) -> bool:
    try:
        validate_service_name(gateway)
    except PropertyError:
        return False
    return True

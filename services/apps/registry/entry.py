"""One row of the registry's table: a known service, its state and its lease."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated

import numpy as np

from services.apps.registry.lease import MAX_LEASE, Lease, check_lease, now, parse_lease, wall_clock
from services.kernel.backend import BackendInfo
from services.kernel.core import Prop, Resource
from services.kernel.errors import Unavailable
from services.kernel.values import Vector

__all__ = [
    "AVAILABILITIES",
    "MAX_LEASE",
    "STATES",
    "ServiceEntry",
    "ServiceList",
    "check_lease",
    "now",
    "parse_lease",
    "wall_clock",
]

#: What ``services.<name>.state`` can be: "connecting" until a service of unknown type (a proxy)
#: is first reached, then "up", or "down" after missed checks.
STATES = ("up", "down", "connecting")

#: What ``services.<name>.availability`` can be (the service states of the SOA layer):
#: "death" (down: it is logged off after ``grace``), "dormant" (declared but not running, or
#: not reached yet: woken when a call or the scheduler needs it), "ready" (running, free),
#: "active" (running, held under a licence: nobody else may invoke it).
AVAILABILITIES = ("death", "dormant", "ready", "active")


class ServiceEntry(Resource):
    """One known service; its own value is its contact URL."""

    type: Annotated[str, Prop(readonly=True, doc="resource type: mobile_robot, sensor, registry, group, ...")]
    url: Annotated[
        str, Prop(readonly=True, doc="contact URL: local, tcp://host:port, serial://..., grpc://...")
    ]
    state: Annotated[str, Prop(readonly=True, doc="up, down, or connecting (never reached yet)")]
    last_seen: Annotated[
        float, Prop(readonly=True, gui="time", doc="when it was last heard of, unix seconds")
    ]
    misses: Annotated[int, Prop(readonly=True, doc="liveness checks missed in a row")]
    features: Annotated[
        list[str], Prop(readonly=True, doc="capabilities it offers the scheduler beside its type; () if none")
    ]
    licence: Annotated[str, Prop(readonly=True, doc="id of a licence held on it (or a subtree); empty: none")]
    owner: Annotated[
        str,
        Prop(
            readonly=True,
            doc="in a cluster of gateways: the id of the gateway holding its connection; else empty",
        ),
    ]
    owner_since: Annotated[
        float,
        Prop(
            readonly=True,
            gui="time",
            doc="in a cluster: when this gateway heard that owner take it, unix seconds; else 0",
        ),
    ]

    def __init__(
        self,
        name: str,
        info: BackendInfo,
        state: str = "up",
        renew: Callable[[str, float], None] | None = None,
        want_location: Callable[[str], None] | None = None,
    ) -> None:
        self.type = info.type
        self.url = info.url
        self.state = state
        self.last_seen = wall_clock()
        self.misses = 0
        self.features = []
        self.licence = ""
        self.owner = ""
        self.owner_since = 0.0
        self._location: Vector = np.zeros(0)
        self._want_location = want_location
        self._name = name
        self._renew = renew
        self._lease = Lease()
        self._down_since: float | None = None  # now()
        self._dormant = False

    def _value(self) -> str:
        return self.url

    @property
    def location(
        self,
    ) -> Annotated[
        Vector,
        Prop(
            gui="pose",
            doc="the service's own location; () if none or not known yet (followed from the first ask)",
        ),
    ]:
        # Followed on demand: a device's location is listened to only once somebody
        # asks for it (docs/line-protocol.md §12), never at connect.
        if self._want_location is not None:
            self._want_location(self._name)
        return self._location

    def store_location(self, location: Vector) -> None:
        """Record the location the registry heard (a plain method, not a property)."""
        self._location = location
        self.changed("location")

    @property
    def lease(
        self,
    ) -> Annotated[float, Prop(doc="seconds left on the lease; 0: no lease (polled). Set to renew")]:
        return round(self._lease.left(), 3)

    @lease.setter
    def lease(self, seconds: float) -> None:
        if self._renew is None:
            raise Unavailable("this registry holds no leases")
        self._renew(self._name, seconds)

    @property
    def availability(
        self,
    ) -> Annotated[
        str,
        Prop(
            choices=AVAILABILITIES,
            doc="death (down), dormant (not running: woken on demand), ready (free), active (licensed)",
        ),
    ]:
        if self.state == "down":
            return "death"
        if self._dormant or self.state == "connecting":
            return "dormant"
        return "active" if self.licence else "ready"

    # -- what the registry changes (plain methods: not properties) ----------

    def set_dormant(self, dormant: bool) -> bool:
        """The service is declared but not running (True), or running (False); True when it changed."""
        if self._dormant == dormant:
            return False
        self._dormant = dormant
        self.changed("availability")
        return True

    def set_licence(self, licence_id: str) -> None:
        """The licence held on this service now ("" for none)."""
        if self.licence != licence_id:
            self.licence = licence_id
            self.changed("availability")

    def is_local(self) -> bool:
        """Served inside the gateway (from the config): never checked, never unregistered."""
        return self.url == "local"

    def has_lease(self) -> bool:
        """The service renews a lease rather than being polled."""
        return self._lease.held

    def lease_lapsed(self, at: float) -> bool:
        """The service has a lease and it ran out before ``at`` (a :func:`now` time)."""
        return self._lease.lapsed(at)

    def set_lease(self, seconds: float) -> None:
        """A lease of ``seconds`` from now; 0 ends it (the service is polled again)."""
        if seconds == 0:
            self._lease.end()
        else:
            self._lease.renew(seconds)

    def seen(self) -> None:
        """The service answered: no misses, ``last_seen`` now."""
        self.last_seen = wall_clock()
        self.misses = 0

    def mark(self, state: str) -> bool:
        """Set ``state``; True when it changed."""
        if self.state == state:
            return False
        self.state = state
        self._down_since = now() if state == "down" else None
        self.changed("availability")
        return True

    def down_for(self, at: float) -> float | None:
        """Seconds the service has been down at ``at`` (a :func:`now` time), None when it is up."""
        if self.state != "down" or self._down_since is None:
            return None
        return at - self._down_since


class ServiceList(Resource):
    """The known services, one child namespace each."""

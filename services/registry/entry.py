"""One row of the registry's table: a known service, its state and its lease."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Annotated

import numpy as np

from services.backend import BackendInfo
from services.core import Prop, Resource
from services.errors import InvalidArgument, Unavailable
from services.values import Vector, format_number, parse_number

__all__ = ["MAX_LEASE", "STATES", "ServiceEntry", "ServiceList", "check_lease", "parse_lease"]

#: What ``services.<name>.state`` can be: "connecting" until a service of unknown type (a proxy)
#: is first reached, then "up", or "down" after missed checks.
STATES = ("up", "down", "connecting")
#: A lease longer than a day is a mistake rather than a plan.
MAX_LEASE = 86_400.0


def now() -> float:
    """The clock of leases and of time spent down (monotonic seconds)."""
    return time.monotonic()


def wall_clock() -> float:
    """``last_seen``: unix seconds, to the millisecond."""
    return round(time.time(), 3)


def check_lease(seconds: float) -> float:
    """``seconds`` as a lease length, or InvalidArgument."""
    if not (math.isfinite(seconds) and 0 <= seconds <= MAX_LEASE):
        raise InvalidArgument(f"a lease is 0 to {format_number(MAX_LEASE)} seconds, got {seconds}")
    return float(seconds)


def parse_lease(text: str) -> float:
    """The ``lease`` request parameter of a registration."""
    try:
        return check_lease(parse_number(text))
    except InvalidArgument as e:
        raise InvalidArgument(f"bad parameter lease: {e.message}") from None


class ServiceEntry(Resource):
    """One known service; its own value is its contact URL."""

    type: Annotated[str, Prop(readonly=True, doc="resource type: mobile_robot, sensor, registry, group, ...")]
    url: Annotated[
        str, Prop(readonly=True, doc="contact URL: local, tcp://host:port, serial://..., grpc://...")
    ]
    state: Annotated[str, Prop(readonly=True, doc="up, down, or connecting (never reached yet)")]
    last_seen: Annotated[float, Prop(readonly=True, doc="when it was last heard of, unix seconds")]
    misses: Annotated[int, Prop(readonly=True, doc="liveness checks missed in a row")]

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
        self._location: Vector = np.zeros(0)
        self._want_location = want_location
        self._name = name
        self._renew = renew
        self._lease_until: float | None = None  # now()
        self._down_since: float | None = None  # now()

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
        # asks for it (docs/line-protocol.md §5), never at connect.
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
        if self._lease_until is None:
            return 0.0
        return round(max(0.0, self._lease_until - now()), 3)

    @lease.setter
    def lease(self, seconds: float) -> None:
        if self._renew is None:
            raise Unavailable("this registry holds no leases")
        self._renew(self._name, seconds)

    # -- what the registry changes (plain methods: not properties) ----------

    def is_local(self) -> bool:
        """Served inside the gateway (from the config): never checked, never unregistered."""
        return self.url == "local"

    def has_lease(self) -> bool:
        """The service renews a lease rather than being polled."""
        return self._lease_until is not None

    def lease_lapsed(self, at: float) -> bool:
        """The service has a lease and it ran out before ``at`` (a :func:`now` time)."""
        return self._lease_until is not None and at > self._lease_until

    def set_lease(self, seconds: float) -> None:
        """A lease of ``seconds`` from now; 0 ends it (the service is polled again)."""
        self._lease_until = None if seconds == 0 else now() + seconds

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
        return True

    def down_for(self, at: float) -> float | None:
        """Seconds the service has been down at ``at`` (a :func:`now` time), None when it is up."""
        if self.state != "down" or self._down_since is None:
            return None
        return at - self._down_since


class ServiceList(Resource):
    """The known services, one child namespace each."""

"""The resource service: which services exist, how to reach them, whether they are alive.

``services`` lists the known service names; ``services.<name>`` is the
contact URL and ``services.<name>.type``, ``.url``, ``.state`` and
``.last_seen`` tell more. The gateway's router keeps it up to date through
:meth:`Registry.add`, :meth:`Registry.remove` and :meth:`Registry.set_state`;
a Listen on ``services`` hears every join and leave.
"""

from __future__ import annotations

import time
from typing import Annotated

from services.backend import BackendInfo
from services.core import Prop, Resource
from services.errors import InvalidArgument, NotFound
from services.paths import validate_service_name

__all__ = ["STATES", "Registry", "ServiceEntry", "ServiceList"]

#: What ``services.<name>.state`` can be.
STATES = ("up", "down")


class ServiceEntry(Resource):
    """One known service; its own value is its contact URL."""

    type: Annotated[str, Prop(readonly=True, doc="resource type: mobile_robot, sensor, registry, group, ...")]
    url: Annotated[
        str, Prop(readonly=True, doc="contact URL: local, tcp://host:port, serial://..., grpc://...")
    ]
    state: Annotated[str, Prop(readonly=True, doc="up or down")]
    last_seen: Annotated[float, Prop(readonly=True, doc="when it was last heard of, unix seconds")]

    def __init__(self, info: BackendInfo, state: str = "up") -> None:
        self.type = info.type
        self.url = info.url
        self.state = state
        self.last_seen = round(time.time(), 3)

    def _value(self) -> str:
        return self.url


class ServiceList(Resource):
    """The known services, one child namespace each."""


class Registry(Resource):
    """The resource service: who exists and how to reach them."""

    resource_type = "registry"

    services: ServiceList

    def __init__(self) -> None:
        self.services = ServiceList()

    def _entry(self, name: str) -> ServiceEntry:
        entry = self.services.children().get(name)
        if not isinstance(entry, ServiceEntry):
            raise NotFound(f"no service named {name!r} in the registry")
        return entry

    def names(self) -> list[str]:
        """The known service names, in the order they joined."""
        return list(self.services.children())

    def add(self, name: str, info: BackendInfo) -> None:
        """Record service ``name``, or refresh it: new type and URL, state up, ``last_seen`` now."""
        validate_service_name(name)
        existing = self.services.children().get(name)
        if isinstance(existing, ServiceEntry):
            url_changed = existing.url != info.url
            existing.type = info.type
            existing.url = info.url
            existing.state = "up"
            existing.last_seen = round(time.time(), 3)
            if url_changed:
                existing.changed()
            return
        self.services.attach(name, ServiceEntry(info))

    def remove(self, name: str) -> None:
        """Forget service ``name``; NotFound if it is not known."""
        self._entry(name)
        self.services.detach(name)

    def set_state(self, name: str, state: str) -> None:
        """Mark ``name`` up or down; going (or staying) up also refreshes ``last_seen``."""
        if state not in STATES:
            raise InvalidArgument(f"bad state {state!r}: use one of {', '.join(STATES)}")
        entry = self._entry(name)
        entry.state = state
        if state == "up":
            entry.last_seen = round(time.time(), 3)

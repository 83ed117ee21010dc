"""``grpc.health.v1.Health``: the whole gateway, and each Property Service by its name.

The empty name (and ``propertyservice.v1.PropertyService``) is the gateway itself: SERVING once it
has started, NOT_SERVING while it starts and from the moment it stops. Any other name is a service
the router serves, following the registry's states: SERVING when ``up``, NOT_SERVING when ``down``
or still ``connecting`` (a proxy whose device has not answered yet), and NOT_SERVING from the moment
its backend loses its device (a proxy's connection drops), before the registry's liveness checks
notice (:meth:`HealthService.follow_link`). A name nobody serves is
NOT_FOUND on ``Check`` and SERVICE_UNKNOWN on ``Watch``, which goes on and reports the service when
it is registered, as the health protocol says
(https://github.com/grpc/grpc/blob/master/doc/health-checking.md).

grpcio-health-checking's own servicer has no way to forget a name (an unregistered service would
stay NOT_SERVING for ever, where the protocol says unknown); this one is as small, and each Watch
holds only the latest status, never a queue.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

__all__ = ["MAX_WATCHES", "HealthService", "state_status"]

#: A ``HealthCheckResponse.ServingStatus`` number.
Status = int
SERVING: Status = health_pb2.HealthCheckResponse.SERVING
NOT_SERVING: Status = health_pb2.HealthCheckResponse.NOT_SERVING
SERVICE_UNKNOWN: Status = health_pb2.HealthCheckResponse.SERVICE_UNKNOWN

#: Most Watch calls open at once: a probe per service per orchestrator is a few hundred; each
#: holds a task and an event, so a client opening them without end gets RESOURCE_EXHAUSTED.
MAX_WATCHES = 10_000

Context = grpc.aio.ServicerContext[Any, Any]


def state_status(state: str) -> Status:
    """The health status of a registry state: ``up`` serves; ``down`` and ``connecting`` do not."""
    return SERVING if state == "up" else NOT_SERVING


class HealthService(health_pb2_grpc.HealthServicer):  # type: ignore[misc]
    """Statuses by name, and the Watch calls that follow them."""

    def __init__(self) -> None:
        self._status: dict[str, Status] = {}
        #: Each service's status as the registry's state gives it, before its link is taken into account.
        self._by_state: dict[str, Status] = {}
        #: Services whose backend lost its device: NOT_SERVING whatever the registry still says.
        self._link_down: set[str] = set()
        #: The events of the Watch calls on each name, set on every change of its status.
        self._watches: dict[str, set[asyncio.Event]] = {}
        self._open = 0
        self._shut = False

    def status_of(self, name: str) -> Status:
        """The status of ``name`` now; SERVICE_UNKNOWN when it has none."""
        return self._status.get(name, SERVICE_UNKNOWN)

    def set(self, name: str, status: Status) -> None:
        """Give ``name`` a status (after shutdown began, only NOT_SERVING is taken)."""
        if self._shut and status != NOT_SERVING:
            return
        if self._status.get(name) != status:
            self._status[name] = status
            self._wake(name)

    def follow_state(self, name: str, state: str) -> None:
        """The registry's state of service ``name``: its status, unless its link is down."""
        self._by_state[name] = state_status(state)
        self._publish(name)

    def follow_link(self, name: str, connected: bool) -> None:
        """The backend of ``name`` lost its device (False) or has it back (True).

        NOT_SERVING at once on a loss: the registry learns it only after its liveness checks
        miss (``[registry] period`` times ``misses``), while calls fail UNAVAILABLE already.
        """
        if connected:
            self._link_down.discard(name)
        else:
            self._link_down.add(name)
        self._publish(name)

    def _publish(self, name: str) -> None:
        status = self._by_state.get(name)
        if status is not None:
            self.set(name, NOT_SERVING if name in self._link_down else status)

    def forget(self, name: str) -> None:
        """``name`` is served no more: Check says NOT_FOUND, Watch SERVICE_UNKNOWN."""
        self._by_state.pop(name, None)
        self._link_down.discard(name)
        if self._status.pop(name, None) is not None:
            self._wake(name)

    def shut_down(self) -> None:
        """Every name NOT_SERVING, for good: the gateway is stopping."""
        for name in list(self._status):
            self.set(name, NOT_SERVING)
        self._shut = True

    def _wake(self, name: str) -> None:
        for event in self._watches.get(name, ()):
            event.set()

    async def Check(self, request: health_pb2.HealthCheckRequest, context: Context) -> Any:
        status = self._status.get(request.service)
        if status is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no service named {request.service!r}")
        return health_pb2.HealthCheckResponse(status=status)

    async def Watch(
        self, request: health_pb2.HealthCheckRequest, context: Context
    ) -> AsyncIterator[health_pb2.HealthCheckResponse]:
        if self._open >= MAX_WATCHES:
            await context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED, f"{MAX_WATCHES} health watches are open already"
            )
        name = request.service
        event = asyncio.Event()
        watches = self._watches.setdefault(name, set())
        watches.add(event)
        self._open += 1
        try:
            sent: Status | None = None
            while True:
                status = self.status_of(name)
                if status != sent:
                    sent = status
                    yield health_pb2.HealthCheckResponse(status=status)
                await event.wait()
                event.clear()
        finally:
            self._open -= 1
            watches.discard(event)
            if not watches and self._watches.get(name) is watches:
                del self._watches[name]

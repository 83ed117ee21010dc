"""A system service nobody wrote a rule check for: what it reads and writes for a client is checked as
that client, its own work is not, and with no rules it reaches everything as before."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.router import Router
from gateway.engine.rules import Rule, Rules, Subject
from gateway.engine.types import GetCall, SetCall
from services.apps.simulators import SimRobot
from services.kernel.core import Resource, action, query, serve
from services.kernel.directory import Directory, own_context
from services.kernel.errors import PermissionDenied

VIEWER = Subject("viewer", authenticated=True, via="token")
ADMIN = Subject("admin", authenticated=True, via="token")


class Relay(Resource):
    """A service of the kind a user adds: it reaches scout1 through the directory it is handed."""

    def __init__(self, directory: Directory) -> None:
        self._directory = directory
        self.heard = ""

    @query(doc="scout1's battery, read for the caller")
    async def battery(self) -> str:
        return str(await self._directory.backend("scout1").get("sensors.battery"))

    @action(doc="set scout1's speed for the caller")
    async def slow_down(self) -> str:
        return str(await self._directory.backend("scout1").set("speed", "0.1"))

    async def read_on_its_own(self) -> None:
        self.heard = str(await self._directory.backend("scout1").get("sensors.battery"))


def _rules() -> Rules:
    return Rules(
        [
            Rule.build(
                0, subject="*", service="relay", path="**", operations=["read", "invoke"], effect="permit"
            ),
            Rule.build(
                1, subject="viewer", service="scout1", path="speed", operations=["read"], effect="permit"
            ),
            Rule.build(
                2, subject="admin", service="*", path="**", operations=["read", "write"], effect="permit"
            ),
        ]
    )


@pytest.fixture
async def routers() -> AsyncIterator[list[Router]]:
    made: list[Router] = []
    yield made
    for router in made:
        for _, backend in router.items():
            await backend.aclose()


async def _gateway(guard: Guard, made: list[Router]) -> tuple[Router, Calls, Relay]:
    router = Router(guard)
    made.append(router)
    scout1 = serve(SimRobot())
    await scout1.start()
    router.add("scout1", scout1)
    relay = Relay(router.directory)
    router.add("relay", serve(relay))
    return router, Calls(router, 5.0, 64, guard), relay


async def test_what_a_service_reads_or_writes_for_a_caller_is_checked_as_that_caller(
    routers: list[Router],
) -> None:
    _, calls, _ = await _gateway(Guard(_rules()), routers)
    with pytest.raises(PermissionDenied, match=r"read scout1/sensors\.battery: viewer may not"):
        await calls.get(GetCall("relay", "battery"), 5.0, VIEWER)
    with pytest.raises(PermissionDenied, match=r"write scout1/speed: viewer may not"):
        await calls.set(SetCall("relay", "slow_down", ""), 5.0, VIEWER)
    answer = await calls.get(GetCall("relay", "battery"), 5.0, ADMIN)
    assert float(answer.value) > 0
    await calls.set(SetCall("relay", "slow_down", ""), 5.0, ADMIN)
    assert (await calls.get(GetCall("scout1", "speed"), 5.0, VIEWER)).value == "0.1"


async def test_a_service_s_own_work_is_not_checked_even_when_a_caller_started_it(
    routers: list[Router],
) -> None:
    _, calls, relay = await _gateway(Guard(_rules()), routers)
    # A viewer's call ran first in this task: the service's background task is still its own.
    with pytest.raises(PermissionDenied):
        await calls.get(GetCall("relay", "battery"), 5.0, VIEWER)
    await asyncio.get_running_loop().create_task(relay.read_on_its_own(), context=own_context())
    assert float(relay.heard) > 0


async def test_with_no_rules_a_service_reaches_everything_as_before(routers: list[Router]) -> None:
    router, calls, _ = await _gateway(Guard(), routers)
    assert router.directory.backend("scout1") is router.lookup("scout1")
    answer = await calls.get(GetCall("relay", "battery"), 5.0, VIEWER)
    assert float(answer.value) > 0

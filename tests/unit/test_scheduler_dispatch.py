"""The registry's scheduler in one process: composition, published costs, all-or-nothing licensing."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

import pytest

from gateway.engine.router import Router
from services.apps.registry import Registry, RegistryService
from services.apps.registry.scheduling import Plan
from services.apps.simulators import SimRobot
from services.kernel.core import LocalService, Prop, Resource
from services.kernel.values import parse_list


class Camera(Resource):
    """A fixed camera that publishes what using it costs."""

    resource_type = "sensor"
    price: Annotated[float, Prop(doc="what using it costs")]

    def __init__(self, price: float) -> None:
        self.price = price


FEATURES = {
    "cam1": ("video", "ptz"),
    "cam2": ("video", "ptz"),
    "cart": ("mobile", "power"),
    "radio": ("communication",),
    "rover": ("video", "ptz", "mobile", "power", "communication"),
}


@pytest.fixture
async def registry() -> AsyncIterator[tuple[Registry, RegistryService]]:
    router = Router()
    services: dict[str, Resource] = {
        "cam1": Camera(5.0),
        "cam2": Camera(1.0),
        "cart": SimRobot(start=(1.0, 0.0), tick_hz=0.1),
        "radio": Camera(0.0),
        "rover": SimRobot(start=(1.0, 0.0), tick_hz=0.1),
    }
    backends = []
    for name, obj in services.items():
        backend = LocalService(obj)
        await backend.start()
        router.add(name, backend)
        backends.append(backend)
    registry = Registry(directory=router, period=0, features=FEATURES)
    service = RegistryService(registry)
    await service.start()
    try:
        yield registry, service
    finally:
        await service.aclose()
        for backend in backends:
            await backend.aclose()


def providers(answer: str) -> list[str]:
    _, status, pairs = parse_list(answer)
    assert status == "granted", answer
    return [p for p, _ in pairs]


async def test_a_minterm_is_covered_by_as_few_providers_as_possible(
    registry: tuple[Registry, RegistryService],
) -> None:
    _, service = registry
    minterm = "(video ptz mobile communication power)"
    assert providers(await service.set("request", minterm, {"consumer": "A"})) == ["rover"]
    # The rover is busy: three providers cover it now (of the two equal cameras, the first by name).
    answer = await service.set("request", minterm, {"consumer": "B"})
    assert sorted(providers(answer)) == ["cam1", "cart", "radio"]


async def test_a_published_cost_ranks_providers(registry: tuple[Registry, RegistryService]) -> None:
    _, service = registry
    assert providers(
        await service.set("request", "(video)", {"consumer": "A", "cost": "price", "weight": "1"})
    ) == ["cam2"]
    # cam2 is busy; cam1 (5) costs less than the rover, which publishes no price and is left out.
    assert providers(
        await service.set("request", "(ptz)", {"consumer": "B", "cost": "price", "weight": "1"})
    ) == ["cam1"]


async def test_a_provider_that_refuses_its_licence_is_left_out_and_nothing_stays_held(
    registry: tuple[Registry, RegistryService],
) -> None:
    reg, service = registry
    dispatcher = reg._dispatcher
    request = dispatcher.scheduler
    # A plan is made for cam1 and cam2 (both video cameras, as a team of two) ...
    from services.apps.registry.scheduling import Request

    plan = request.submit(
        Request("A", frozenset({"video"}), count=2, duration=10.0, weight=0.0), dispatcher.providers(), 0.0
    )
    assert isinstance(plan, Plan)
    # ... and before its licences are granted someone licenses the second one directly.
    second = plan.providers[1]
    outside = await reg.licensing.grant(second, "someone", 10.0)
    allocation, refused = await dispatcher._carry_out(plan, "A", "")
    assert allocation is None and refused == {second}
    # All or nothing: the first licence was released again and both are free in the scheduler.
    assert [lic.id for lic in reg.licensing.held()] == [outside.id]
    assert request.holder(plan.providers[0]) is None and request.allocations == {}
    # The request made through the registry chooses around it (rule d), licensing the rest.
    answer = await service.set("request", "(video)", {"consumer": "A", "count": "2"})
    assert second not in providers(answer)


async def test_a_registration_declares_its_features_and_bad_ones_register_nothing() -> None:
    from support.group_support import MemoryDirectory, sim_robot

    from services.kernel.errors import InvalidArgument

    directory = MemoryDirectory()
    directory.devices["tcp://127.0.0.1:7001"] = lambda: sim_robot(5, 5)
    registry = Registry(directory=directory, period=0)
    service = RegistryService(registry)
    await directory.add("registry", service)
    try:
        with pytest.raises(InvalidArgument, match="bad parameter features"):
            await service.set("services.scout", "tcp://127.0.0.1:7001", {"features": "(laser"})
        assert "scout" not in registry.names()
        assert await service.get("services.registry.features") == "()"
        await service.set(
            "services.scout", "tcp://127.0.0.1:7001", {"type": "mobile_robot", "features": "(laser)"}
        )
        assert registry.features_of("scout") == frozenset({"laser"})
        assert await service.get("services.scout.features") == "(laser)"
        assert providers(await service.set("request", "(laser mobile_robot)", {"consumer": "A"})) == ["scout"]
    finally:
        await directory.aclose()


async def test_listeners_of_requests_and_allocations_hear_the_queue_move(
    registry: tuple[Registry, RegistryService],
) -> None:
    from support.waiting import wait_until

    _, service = registry
    heard: dict[str, list[str]] = {"requests": [], "allocations": []}
    subs = [
        await service.listen(path, lambda change, path=path: heard[path].append(change.value))
        for path in heard
    ]
    try:
        first = parse_list(
            await service.set("request", "(communication)", {"consumer": "A", "exclude": "(rover)"})
        )[0]
        only_radio = {"consumer": "B", "wait": "5", "exclude": "(rover)"}
        waiting = parse_list(await service.set("request", "(communication)", only_radio))
        assert waiting[1] == "queued"
        await wait_until(lambda: any(f"({waiting[0]} B" in v for v in heard["requests"]), what="queued")
        await service.set("release", "", {"allocation": first})
        await wait_until(lambda: heard["requests"][-1:] == ["()"], what="the queue emptied")
        await wait_until(lambda: any(f"({waiting[0]} B" in v for v in heard["allocations"]), what="served")
    finally:
        for sub in subs:
            await sub.close()


def test_a_request_is_invoked_like_the_licence_actions_not_an_administration() -> None:
    from gateway.engine.guard import registry_operation
    from gateway.engine.rules import Operation

    assert registry_operation("request", "(survey)") is Operation.INVOKE
    assert registry_operation("release", "") is Operation.INVOKE
    assert registry_operation("period", "1") is Operation.ADMIN


async def test_the_locations_a_request_needs_are_followed_from_its_first_ask() -> None:
    router = Router()
    robots = {
        "a_far": SimRobot(start=(9.0, 0.0), tick_hz=0.1),
        "z_near": SimRobot(start=(1.0, 0.0), tick_hz=0.1),
    }
    backends = []
    for name, obj in robots.items():
        backend = LocalService(obj)
        await backend.start()
        router.add(name, backend)
        backends.append(backend)
    registry = Registry(directory=router, period=0)
    service = RegistryService(registry)
    await service.start()
    try:
        # Nobody asked where they are yet: the request does, and waits for the answers.
        assert providers(
            await service.set("request", "(mobile_robot)", {"consumer": "A", "location": "(0 0)"})
        ) == ["z_near"]
    finally:
        await service.aclose()
        for backend in backends:
            await backend.aclose()

"""The registry as the gateway's router uses it, seen through Get and Listen."""

from __future__ import annotations

import pytest

from services.apps.registry import Registry
from services.kernel.backend import BackendInfo, Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, InvalidArgument, NotFound, PropertyError
from services.kernel.values import parse_names


@pytest.fixture
def registry() -> Registry:
    return Registry()


@pytest.fixture
def svc(registry: Registry) -> LocalService:
    return LocalService(registry)


async def test_known_services_and_their_details(svc: LocalService, registry: Registry) -> None:
    assert svc.info.type == "registry"
    assert await svc.get("services") == "()"
    registry.add("scout1", BackendInfo(type="mobile_robot", url="tcp://10.0.0.7:7000"))
    registry.add("temp1", BackendInfo(type="sensor", url="local"))
    assert await svc.get("services") == "(scout1 temp1)"
    assert await svc.get("services.scout1") == "tcp://10.0.0.7:7000"
    assert await svc.get("services.scout1.type") == "mobile_robot"
    assert await svc.get("services.scout1.url") == "tcp://10.0.0.7:7000"
    assert await svc.get("services.scout1.state") == "up"
    assert float(await svc.get("services.scout1.last_seen")) > 1.6e9
    assert parse_names(await svc.get("properties"))[:3] == [
        "services",
        "services.scout1",
        "services.scout1.type",
    ]
    assert registry.names() == ["scout1", "temp1"]


async def test_listen_on_services_sees_joins_and_leaves(svc: LocalService, registry: Registry) -> None:
    changes: list[Change] = []
    await svc.listen("services", changes.append)
    registry.add("scout1", BackendInfo(type="mobile_robot", url="tcp://a:1"))
    registry.add("scout2", BackendInfo(type="mobile_robot", url="tcp://b:1"))
    registry.remove("scout1")
    assert [c.value for c in changes] == ["(scout1)", "(scout1 scout2)", "(scout2)"]


async def test_state_changes_are_heard(svc: LocalService, registry: Registry) -> None:
    registry.add("scout1", BackendInfo(type="mobile_robot", url="tcp://a:1"))
    states: list[Change] = []
    await svc.listen("services.scout1.state", states.append)
    registry.set_state("scout1", "down")
    registry.set_state("scout1", "up")
    registry.remove("scout1")
    assert states == [
        Change("services.scout1.state", "down"),
        Change("services.scout1.state", "up"),
        Change("services.scout1.state", "", removed=True),
    ]


async def test_adding_again_refreshes_the_entry(svc: LocalService, registry: Registry) -> None:
    registry.add("scout1", BackendInfo(type="mobile_robot", url="tcp://a:1"))
    registry.set_state("scout1", "down")
    urls: list[Change] = []
    await svc.listen("services.scout1", urls.append)
    registry.add("scout1", BackendInfo(type="mobile_robot", url="tcp://a:2"))
    assert await svc.get("services.scout1.state") == "up"
    assert urls == [Change("services.scout1", "tcp://a:2")]
    assert await svc.get("services") == "(scout1)"


async def test_entries_are_read_only_and_errors_are_clear(svc: LocalService, registry: Registry) -> None:
    registry.add("scout1", BackendInfo(type="mobile_robot", url="tcp://a:1"))
    with pytest.raises(PropertyError) as info:
        await svc.set("services.scout1.url", "tcp://evil:1")
    assert info.value.code is Code.FAILED_PRECONDITION
    with pytest.raises(NotFound):
        await svc.get("services.scout9")
    with pytest.raises(NotFound):
        registry.remove("scout9")
    with pytest.raises(NotFound):
        registry.set_state("scout9", "up")
    with pytest.raises(InvalidArgument):
        registry.set_state("scout1", "sleeping")
    with pytest.raises(InvalidArgument):
        registry.add("bad name", BackendInfo())

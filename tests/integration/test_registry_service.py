"""The full registry in-process: registration by Set, liveness, leases, find, persistence, bad input."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support.group_support import (
    MemoryDirectory,
    Switchable,
    mute_robot,
    sim_robot,
    unreachable_robot,
    wait_for,
)

from services.apps.registry import Registry, RegistryService, check_url
from services.apps.simulators import SimSensor
from services.kernel.backend import Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, PropertyError
from services.kernel.values import parse_names, parse_vector


async def start_registry(directory: MemoryDirectory, **options: Any) -> tuple[Registry, RegistryService]:
    registry = Registry(directory=directory, **options)
    service = RegistryService(registry)
    await directory.add("registry", service)
    return registry, service


@pytest.fixture
async def world() -> AsyncIterator[MemoryDirectory]:
    directory = MemoryDirectory()
    directory.devices["tcp://127.0.0.1:7001"] = lambda: sim_robot(5, 5)
    directory.devices["tcp://127.0.0.1:7002"] = lambda: sim_robot(6, 5)
    directory.devices["tcp://127.0.0.1:7003"] = lambda: sim_robot(20, 20)
    directory.devices["serial:///dev/ttyUSB0?baudrate=115200"] = lambda: LocalService(
        SimSensor(location=(5, 6))
    )
    directory.devices["tcp://127.0.0.1:7009"] = mute_robot
    yield directory
    await directory.aclose()


async def test_register_by_set_makes_the_service_reachable(world: MemoryDirectory) -> None:
    _, svc = await start_registry(world, period=0)
    joins: list[Change] = []
    await svc.listen("services", joins.append)
    assert await svc.set("services.scout1", "tcp://127.0.0.1:7001", {"type": "mobile_robot"}) == (
        "tcp://127.0.0.1:7001"
    )
    assert "scout1" in world.names()
    assert parse_vector(await world.backend("scout1").get("location"))[:2].tolist() == [5.0, 5.0]
    assert await svc.get("services.scout1") == "tcp://127.0.0.1:7001"
    assert await svc.get("services.scout1.type") == "mobile_robot"
    assert await svc.get("services.scout1.state") == "up"
    loc = await wait_for(svc, "services.scout1.location", lambda v: v != "()")
    assert parse_vector(loc)[:2].tolist() == [5.0, 5.0]
    assert parse_names(joins[-1].value) == ["registry", "scout1"]
    # The same registration again is a sign of life, not an error.
    assert await svc.set("services.scout1", "tcp://127.0.0.1:7001") == "tcp://127.0.0.1:7001"


async def test_unregister_by_setting_the_empty_value(world: MemoryDirectory) -> None:
    _, svc = await start_registry(world, period=0)
    await svc.set("services.scout1", "tcp://127.0.0.1:7001")
    leaves: list[Change] = []
    await svc.listen("services", leaves.append)
    assert await svc.set("services.scout1", "") == ""
    assert "scout1" not in world.names()
    assert parse_names(await svc.get("services")) == ["registry"]
    assert parse_names(leaves[-1].value) == ["registry"]
    with pytest.raises(PropertyError) as info:
        await svc.get("services.scout1")
    assert info.value.code is Code.NOT_FOUND
    with pytest.raises(PropertyError) as info:
        await svc.set("services.scout1", "")
    assert info.value.code is Code.NOT_FOUND
    with pytest.raises(PropertyError) as info:
        await svc.set("services.registry", "")
    assert info.value.code is Code.FAILED_PRECONDITION


@pytest.mark.parametrize(
    ("name", "url", "params", "code", "words"),
    [
        ("scout9", "tcp://127.0.0.1", {}, Code.INVALID_ARGUMENT, "host:port"),
        ("scout9", "tcp://127.0.0.1:99999", {}, Code.INVALID_ARGUMENT, "malformed URL"),
        ("scout9", "http://example.com:80", {}, Code.INVALID_ARGUMENT, "expected one of tcp://"),
        ("scout9", "local", {}, Code.INVALID_ARGUMENT, "config"),
        ("scout9", "serial://", {}, Code.INVALID_ARGUMENT, "serial:///dev/ttyUSB0"),
        ("scout9", "tcp://127.0.0.1:7001", {"colour": "red"}, Code.INVALID_ARGUMENT, "unknown parameter"),
        ("scout9", "tcp://127.0.0.1:7001", {"lease": "-1"}, Code.INVALID_ARGUMENT, "lease"),
        ("bad*name", "tcp://127.0.0.1:7001", {}, Code.INVALID_ARGUMENT, "bad service name"),
        ("scout1", "tcp://127.0.0.1:7002", {}, Code.ALREADY_EXISTS, "is taken"),
        ("registry", "tcp://127.0.0.1:7002", {}, Code.ALREADY_EXISTS, "is taken"),
        ("scout9", "tcp://127.0.0.1:7777", {}, Code.UNAVAILABLE, "nothing was registered"),
        # A device that never answers and one that is not there get the same answer.
        ("scout9", "tcp://127.0.0.1:7009", {}, Code.UNAVAILABLE, "nothing was registered"),
    ],
)
async def test_bad_registrations_get_clear_errors_and_change_nothing(  # noqa: PLR0917
    world: MemoryDirectory, name: str, url: str, params: dict[str, str], code: Code, words: str
) -> None:
    _, svc = await start_registry(world, period=0, register_timeout=0.3)
    await svc.set("services.scout1", "tcp://127.0.0.1:7001")
    before = (world.names(), await svc.get("services"))
    with pytest.raises(PropertyError) as info:
        await svc.set(f"services.{name}", url, params)
    assert info.value.code is code
    assert words in info.value.message
    assert (world.names(), await svc.get("services")) == before


async def test_a_name_the_directory_serves_outside_the_registry_is_taken(world: MemoryDirectory) -> None:
    _, svc = await start_registry(world, period=0)
    world.backends["hidden"] = sim_robot(1, 1)  # served, but never announced to the registry
    with pytest.raises(PropertyError) as info:
        await svc.set("services.hidden", "tcp://127.0.0.1:7001")
    assert info.value.code is Code.ALREADY_EXISTS
    assert "is taken (by another service)" in info.value.message
    assert parse_names(await svc.get("services")) == ["registry"]


def test_check_url_accepts_the_registrable_forms() -> None:
    for url in ("tcp://10.0.0.7:7000", "serial:///dev/ttyUSB0?baudrate=115200", "grpc://gw2:50051"):
        assert check_url(url) == url


async def test_liveness_marks_down_then_removes_after_grace(world: MemoryDirectory) -> None:
    link: list[Switchable] = []

    def flaky() -> Switchable:
        link.append(Switchable(sim_robot(1, 1)))
        return link[-1]

    world.devices["tcp://127.0.0.1:7100"] = flaky
    registry, svc = await start_registry(world, period=0, timeout=0.2, misses=2, grace=0)
    await svc.set("services.flaky", "tcp://127.0.0.1:7100")
    states: list[Change] = []
    await svc.listen("services.flaky.state", states.append)
    link[0].alive = False
    await registry.check_all()
    assert await svc.get("services.flaky.state") == "up"
    assert await svc.get("services.flaky.misses") == "1"
    link[0].alive = True
    await registry.check_all()
    assert await svc.get("services.flaky.misses") == "0"
    link[0].alive = False
    await registry.check_all()
    await registry.check_all()  # second miss in a row: down, and with no grace, removed
    assert [c.value for c in states][:1] == ["down"]
    assert "flaky" not in world.names()
    assert parse_names(await svc.get("services")) == ["registry"]


async def test_configured_services_go_down_but_stay(world: MemoryDirectory) -> None:
    dead = unreachable_robot("tcp://127.0.0.1:7200")
    await world.add("door", dead)
    registry, svc = await start_registry(world, period=0, misses=1, grace=0, static=["door"])
    watched: list[tuple[str, str]] = []
    registry.watch_states(lambda name, state: watched.append((name, state)))
    await registry.check_all()
    await registry.check_all()
    assert await svc.get("services.door.state") == "down"
    assert registry.state_of("door") == "down"
    assert watched == [("door", "down")]
    assert "door" in world.names()


async def test_a_lease_keeps_a_service_up_until_it_lapses(world: MemoryDirectory) -> None:
    registry, svc = await start_registry(world, period=0, grace=3600)
    await svc.set("services.scout1", "tcp://127.0.0.1:7001", {"lease": "30"})
    assert 29 < float(await svc.get("services.scout1.lease")) <= 30
    await registry.check_all()
    assert await svc.get("services.scout1.state") == "up"
    await svc.set("services.scout1.lease", "0.01")
    await asyncio.sleep(0.05)  # the lease lapses
    assert await svc.get("services.scout1.lease") == "0"
    await registry.check_all()
    assert await svc.get("services.scout1.state") == "down"
    await svc.set("services.scout1.lease", "30")  # renewing brings it back
    assert await svc.get("services.scout1.state") == "up"
    with pytest.raises(PropertyError) as info:
        await svc.set("services.scout1.lease", "-5")
    assert info.value.code is Code.INVALID_ARGUMENT


async def test_find_by_type_location_state_and_property(world: MemoryDirectory) -> None:
    _, svc = await start_registry(world, period=0)
    await svc.set("services.scout1", "tcp://127.0.0.1:7001")
    await svc.set("services.scout2", "tcp://127.0.0.1:7002")
    await svc.set("services.far", "tcp://127.0.0.1:7003")
    await svc.set("services.thermo", "serial:///dev/ttyUSB0?baudrate=115200")
    await world.backend("scout2").set("speed", "0.8")
    near = {"type": "mobile_robot", "near": "(5 5 0)", "radius": "3"}
    assert parse_names(await svc.get("find", near)) == ["scout1", "scout2"]
    assert parse_names(await svc.get("find", {"type": "mobile_robot"})) == ["far", "scout1", "scout2"]
    assert parse_names(await svc.get("find", {"near": "(5 5)", "radius": "3"})) == [
        "scout1",
        "scout2",
        "thermo",
    ]
    assert parse_names(await svc.get("find", {"type": "(sensor registry)"})) == ["registry", "thermo"]
    assert parse_names(await svc.get("find", {"where": "speed=0.8"})) == ["scout2"]
    assert parse_names(await svc.get("find", {"near": "(20 20)", "limit": "1"})) == ["far"]
    assert parse_names(await svc.get("find", {"state": "down"})) == []
    assert await svc.get("find.parameters") != "()"


@pytest.mark.parametrize(
    ("params", "words"),
    [
        ({"colour": "red"}, "colour"),
        ({"near": "(5)", "radius": "1"}, "near"),
        ({"radius": "3"}, "radius needs near"),
        ({"where": "speed"}, "property=value"),
    ],
)
async def test_find_with_bad_parameters_is_invalid(
    world: MemoryDirectory, params: dict[str, str], words: str
) -> None:
    _, svc = await start_registry(world, period=0)
    with pytest.raises(PropertyError) as info:
        await svc.get("find", params)
    assert info.value.code is Code.INVALID_ARGUMENT
    assert words in info.value.message


async def test_registrations_survive_a_restart_through_the_file(
    world: MemoryDirectory, tmp_path: Path
) -> None:
    file = tmp_path / "registrations.json"
    _, svc = await start_registry(world, period=0, persist=file)
    await svc.set("services.scout1", "tcp://127.0.0.1:7001", {"type": "mobile_robot"})
    await svc.set("services.scout2", "tcp://127.0.0.1:7002")
    await svc.set("services.scout2", "")
    await world.aclose()  # the gateway stops; the file stays
    saved = json.loads(file.read_text())
    assert list(saved["services"]) == ["scout1"]

    again = MemoryDirectory()
    again.devices = world.devices
    try:
        _, svc2 = await start_registry(again, period=0, persist=file)
        assert "scout1" in again.names()
        assert await svc2.get("services.scout1.type") == "mobile_robot"
    finally:
        await again.aclose()


async def test_find_scales_to_ten_thousand_entries(world: MemoryDirectory) -> None:
    registry, svc = await start_registry(world, period=0)
    rng = np.random.default_rng(3)
    for i, (x, y) in enumerate(rng.uniform(0, 100, size=(10_000, 2))):
        registry.add(f"r{i}", _info("mobile_robot" if i % 2 else "sensor"))
        registry.set_location(f"r{i}", np.array([x, y, 0.0]))
    query = {"type": "mobile_robot", "near": "(50 50 0)", "radius": "5"}
    found = parse_names(await svc.get("find", query))
    assert found and all(int(n[1:]) % 2 for n in found)


def _info(kind: str) -> Any:
    from services.kernel.backend import BackendInfo

    return BackendInfo(type=kind, url="tcp://127.0.0.1:1")

"""Groups with the full registry in-process: query membership kept current, query subgroups, scale.

The timings of moveto and find at scale are in ``bench/groups.py``; the test
here checks the results at those sizes, not their speed.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import numpy as np
import pytest
from support.group_support import MemoryDirectory, sim_robot, wait_for

from services.apps.formations import formation_targets
from services.apps.group import Group
from services.apps.registry import Registry, RegistryService
from services.apps.simulators import SimRobot, SimSensor
from services.kernel.backend import BackendInfo, Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, PropertyError
from services.kernel.values import parse_names, parse_vector


async def start(directory: MemoryDirectory) -> RegistryService:
    service = RegistryService(Registry(directory=directory, period=0))
    await directory.add("registry", service)
    return service


@pytest.fixture
async def world() -> AsyncIterator[MemoryDirectory]:
    directory = MemoryDirectory()
    for i, url in enumerate(["tcp://127.0.0.1:7001", "tcp://127.0.0.1:7002", "tcp://127.0.0.1:7003"]):
        directory.devices[url] = lambda i=i: sim_robot(4 + i, 5)
    directory.devices["tcp://127.0.0.1:7004"] = lambda: sim_robot(40, 40)
    yield directory
    await directory.aclose()


async def test_query_group_follows_registrations(world: MemoryDirectory) -> None:
    registry = await start(world)
    await world.add("thermo", LocalService(SimSensor(location=(5, 5))))
    group = await world.add(
        "near5",
        LocalService(Group(directory=world, query={"type": "mobile_robot", "near": [5, 5], "radius": 3})),
    )
    assert await group.get("query") == "type=mobile_robot&near=(5 5)&radius=3"
    assert parse_names(await group.get("robots")) == []
    changes: list[Change] = []
    await group.listen("robots", changes.append)
    await registry.set("services.scout1", "tcp://127.0.0.1:7001")
    await registry.set("services.scout2", "tcp://127.0.0.1:7002")
    await registry.set("services.far", "tcp://127.0.0.1:7004")
    await wait_for(group, "robots", lambda v: set(parse_names(v)) == {"scout1", "scout2"})
    await registry.set("services.scout1", "")
    robots = await wait_for(group, "robots", lambda v: parse_names(v) == ["scout2"])
    assert parse_names(robots) == ["scout2"]
    assert changes  # a Listen on robots heard the joins and the leave


async def test_query_subgroup_and_moveto_in_a_grid(world: MemoryDirectory) -> None:
    registry = await start(world)
    for i in (1, 2, 3):
        await registry.set(f"services.scout{i}", f"tcp://127.0.0.1:700{i}", {"type": "mobile_robot"})
    group = await world.add("swarm", LocalService(Group(directory=world, query={"type": "mobile_robot"})))
    await wait_for(group, "robots", lambda v: len(parse_names(v)) == 3)
    made = await group.set("subgroup", "left", {"query": "type=mobile_robot&near=(4 5)&radius=1.5"})
    assert parse_names(made) == ["scout1", "scout2"]
    await group.set(
        "subgroups.left.behaviors.moveto",
        "<marker><location>(0 0)</location></marker>",
        {"formation": "grid"},
    )
    places = formation_targets(["scout1", "scout2"], [0, 0], "grid", 1.0)
    for name, place in places.items():
        await wait_for(
            world.backend(name), "location", lambda v, p=place: np.allclose(parse_vector(v)[:2], p)
        )
    with pytest.raises(PropertyError) as info:
        await group.set("subgroup", "bad", {"query": "colour=red"})
    assert info.value.code is Code.INVALID_ARGUMENT


async def test_moveto_reaches_every_member_and_find_matches_a_full_search() -> None:
    """At benchmark sizes (timed in bench/groups.py): every member accepts, find misses no one."""
    directory = MemoryDirectory()
    names = [f"r{i}" for i in range(100)]
    for i, name in enumerate(names):
        await directory.add(name, LocalService(SimRobot(start=(i % 10, i // 10), tick_hz=0.1)))
    group = LocalService(Group(directory=directory, members=names))
    await group.start()
    try:
        accepted = await group.set(
            "behaviors.moveto", "<marker><location>(0 0)</location></marker>", {"formation": "circle"}
        )
    finally:
        await group.aclose()
        await directory.aclose()
    assert sorted(parse_names(accepted)) == sorted(names)

    registry = Registry(period=0)
    service = RegistryService(registry)
    await service.start()
    rng = np.random.default_rng(1)
    places = rng.uniform(0, 300, size=(1000, 2))
    kinds = ["mobile_robot" if i % 4 else "sensor" for i in range(1000)]
    for i, (x, y) in enumerate(places):
        registry.add(f"r{i}", BackendInfo(type=kinds[i], url="tcp://10.0.0.1:7000"))
        registry.set_location(f"r{i}", np.array([round(x, 3), round(y, 3), 0.0]))
    try:
        for cx, cy in rng.uniform(0, 300, size=(20, 2)):
            found = await service.get(
                "find", {"type": "mobile_robot", "near": f"({cx} {cy})", "radius": "30"}
            )
            near = np.hypot(places[:, 0] - cx, places[:, 1] - cy) <= 30
            expected = {f"r{i}" for i in np.flatnonzero(near) if kinds[i] == "mobile_robot"}
            assert set(parse_names(found)) == expected
    finally:
        await service.aclose()


async def test_a_group_reports_members_that_left_the_network(world: MemoryDirectory) -> None:
    registry = await start(world)
    await registry.set("services.scout1", "tcp://127.0.0.1:7001")
    group = await world.add("pair", LocalService(Group(directory=world, members=["scout1", "scout2"])))
    with pytest.raises(PropertyError) as info:
        await group.set("behaviors.moveto", "<marker><location>(1 1)</location></marker>")
    assert "scout2: UNAVAILABLE: not registered right now" in info.value.message
    await registry.set("services.scout2", "tcp://127.0.0.1:7002")
    await asyncio.sleep(0)
    assert parse_names(
        await group.set("behaviors.moveto", "<marker><location>(1 1)</location></marker>")
    ) == [
        "scout1",
        "scout2",
    ]

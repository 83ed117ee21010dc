"""The group service in-process: real simulated robots behind LocalService, a small in-memory directory."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from support.group_support import MemoryDirectory, mute_robot, unreachable_robot, wait_for

from services.apps.formations import formation_targets
from services.apps.group import Group, GroupCallFailed, query_params
from services.apps.simulators import SimRobot
from services.kernel.backend import Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, PropertyError
from services.kernel.values import parse_list, parse_names, parse_vector


def robot(x: float, y: float) -> LocalService:
    return LocalService(SimRobot(start=(x, y), speed=200.0, tick_hz=200.0))


async def make_group(directory: MemoryDirectory, **options: Any) -> LocalService:
    service = LocalService(Group(directory=directory, **options))
    await service.start()
    return service


@pytest.fixture
async def world() -> Any:
    directory = MemoryDirectory()
    for i, (x, y) in enumerate([(0, 0), (2, 0), (0, 2), (2, 2)], start=1):
        await directory.add(f"scout{i}", robot(x, y))
    yield directory
    for name in directory.names():
        await directory.unregister(name)


async def test_robots_lists_members_and_reaches_their_properties(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "scout2", "scout3"])
    try:
        assert parse_names(await group.get("robots")) == ["scout1", "scout2", "scout3"]
        assert parse_vector(await group.get("robots.scout2.location"))[:2].tolist() == [2.0, 0.0]
        await group.set("robots.scout3.speed", "1.5")
        assert await world.backend("scout3").get("speed") == "1.5"
        assert "robots.scout1.location" in await group.properties()
        with pytest.raises(PropertyError) as info:
            await group.get("robots.scout4.location")
        assert info.value.code is Code.NOT_FOUND
    finally:
        await group.aclose()


async def test_listen_on_a_member_property_through_the_group(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "scout2"])
    try:
        changes: list[Change] = []
        sub = await group.listen("robots.scout1.location", changes.append)
        await world.backend("scout1").set("behaviors.moveto", "<marker><location>(0 1)</location></marker>")
        value = await wait_for(group, "robots.scout1.location", lambda v: parse_vector(v)[1] == 1.0)
        assert parse_vector(value)[:2].tolist() == [0.0, 1.0]
        assert changes and all(c.path == "robots.scout1.location" for c in changes)
        await sub.close()
    finally:
        await group.aclose()


async def test_location_is_the_centroid_and_follows_the_members(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "scout2", "scout3", "scout4"])
    try:
        value = await wait_for(group, "location", lambda v: v != "")
        np.testing.assert_allclose(parse_vector(value)[:3], [1, 1, 0])
        await world.backend("scout4").set("behaviors.moveto", "<marker><location>(6 6)</location></marker>")
        value = await wait_for(group, "location", lambda v: np.allclose(parse_vector(v)[:2], [2, 2]))
        np.testing.assert_allclose(parse_vector(value)[:2], [2, 2])
    finally:
        await group.aclose()


async def test_moveto_circle_drives_every_member_to_its_place(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "scout2", "scout3", "scout4"])
    try:
        marker = "<marker><location>(10 5 0)</location><color>(1 0 0)</color></marker>"
        accepted = await group.set("behaviors.moveto", marker, {"formation": "circle", "spacing": "2"})
        assert parse_names(accepted) == ["scout1", "scout2", "scout3", "scout4"]
        places = formation_targets(world.names(), [10, 5, 0], "circle", 2.0)
        for name, place in places.items():
            value = await wait_for(world.backend(name), "location", lambda v, p=place: _near(v, p))
            assert _near(value, place)
        centre = await wait_for(group, "location", lambda v: _near(v, [10, 5, 0]))
        assert _near(centre, [10, 5, 0])
        spots = np.array([parse_vector(await world.backend(n).get("location"))[:2] for n in world.names()])
        sides = np.linalg.norm(spots - np.roll(spots, 1, axis=0), axis=1)
        np.testing.assert_allclose(sides, 2.0, atol=1e-6)  # a square of side = spacing
        assert parse_list(await group.get("failed")) == []
    finally:
        await group.aclose()


def _near(text: str, place: Any) -> bool:
    v = parse_vector(text)
    p = np.asarray(place, dtype=float)
    return bool(np.allclose(v[: p.size], p, atol=1e-6))


async def test_partial_failure_names_the_failed_members_and_the_others_act(world: MemoryDirectory) -> None:
    await world.add("scout5", LocalService(SimRobot(start=(0, 0), speed=200.0)))
    await world.add("dead", unreachable_robot())
    group = await make_group(world, members=["scout1", "dead", "scout5", "ghost"])
    try:
        assert parse_names(await group.get("robots")) == ["dead", "scout1", "scout5"]
        with pytest.raises(GroupCallFailed) as info:
            await group.set("behaviors.moveto", "<marker><location>(4 4)</location></marker>", {})
        err = info.value
        assert err.code is Code.UNAVAILABLE
        assert "failed on 2 of 4 members (the other 2 acted)" in err.message
        assert "dead: UNAVAILABLE: cannot reach tcp://127.0.0.1:9" in err.message
        assert "ghost: UNAVAILABLE: not registered right now" in err.message
        assert set(err.failures) == {"dead", "ghost"}
        assert parse_list(await group.get("failed")) == [["dead", "UNAVAILABLE"], ["ghost", "UNAVAILABLE"]]
        # The line formation kept a place for every named member; the live ones went to theirs.
        places = formation_targets(["scout1", "dead", "scout5", "ghost"], [4, 4], "line", 1.0)
        for name in ("scout1", "scout5"):
            value = await wait_for(world.backend(name), "location", lambda v, p=places[name]: _near(v, p))
            assert _near(value, places[name])
    finally:
        await group.aclose()


async def test_a_member_that_never_answers_is_reported_after_the_member_timeout(
    world: MemoryDirectory,
) -> None:
    await world.add("mute", mute_robot())
    group = await make_group(world, members=["scout1", "mute"], member_timeout=0.2)
    try:
        with pytest.raises(PropertyError) as info:
            await group.set("behaviors.moveto", "<marker><location>(1 1)</location></marker>")
        assert info.value.code is Code.DEADLINE_EXCEEDED
        assert "mute: DEADLINE_EXCEEDED: no answer within 0.2 s" in info.value.message
    finally:
        await group.aclose()


async def test_members_join_and_leave_with_the_directory(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "late"])
    try:
        changes: list[Change] = []
        sub = await group.listen("robots", changes.append)
        assert parse_names(await group.get("robots")) == ["scout1"]
        await world.add("late", robot(5, 5))
        assert parse_names(await group.get("robots")) == ["scout1", "late"]  # in the order they joined
        await world.unregister("scout1")
        assert parse_names(await group.get("robots")) == ["late"]
        assert [parse_names(c.value) for c in changes] == [["scout1", "late"], ["late"]]
        await sub.close()
        with pytest.raises(PropertyError) as info:
            await group.get("robots.scout1.location")
        assert info.value.code is Code.NOT_FOUND
    finally:
        await group.aclose()


async def test_subgroup_by_names_is_a_group(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "scout2", "scout3", "scout4"])
    try:
        made = await group.set("subgroup", "east", {"members": "(scout2 scout4)"})
        assert parse_names(made) == ["scout2", "scout4"]
        assert parse_names(await group.get("subgroups")) == ["east"]
        assert parse_names(await group.get("subgroups.east.robots")) == ["scout2", "scout4"]
        centre = await wait_for(group, "subgroups.east.location", lambda v: v != "")
        np.testing.assert_allclose(parse_vector(centre)[:2], [2, 1])
        await group.set("subgroups.east.behaviors.moveto", "<marker><location>(2 9)</location></marker>")
        await wait_for(world.backend("scout4"), "location", lambda v: _near(v, [2.5, 9]))
        # A member that leaves the parent leaves the subgroup too.
        await world.unregister("scout2")
        assert parse_names(await group.get("subgroups.east.robots")) == ["scout4"]
        with pytest.raises(PropertyError) as info:
            await group.set("subgroup", "east", {"members": "(scout4)"})
        assert info.value.code is Code.ALREADY_EXISTS
        await group.set("dissolve", "east")
        assert parse_names(await group.get("subgroups")) == []
    finally:
        await group.aclose()


@pytest.mark.parametrize(
    ("path", "value", "params", "words"),
    [
        ("behaviors.moveto", "<marker><location>(1 1)</location></marker>", {"formation": "vee"}, "vee"),
        ("behaviors.moveto", "<marker><location>(1 1)</location></marker>", {"spacing": "-1"}, "spacing"),
        ("behaviors.moveto", "<marker><color>(1 0 0)</color></marker>", {}, "no location"),
        ("behaviors.moveto", "(1 1)", {}, "marker"),
        ("behaviors.moveto", "<marker><location>(1 1)</location></marker>", {"speed": "2"}, "speed"),
        ("subgroup", "west", {"members": "(scout1 nobody)"}, "not members of this group: nobody"),
        ("subgroup", "west", {}, "a subgroup needs members (a list of names) or a query"),
        ("subgroup", "west", {"members": "(scout1)", "query": "type=mobile_robot"}, "not both"),
        ("subgroup", "bad.name", {"members": "(scout1)"}, "service name"),
    ],
)
async def test_bad_requests_are_invalid_arguments_and_change_nothing(
    world: MemoryDirectory, path: str, value: str, params: dict[str, str], words: str
) -> None:
    group = await make_group(world, members=["scout1", "scout2"])
    try:
        with pytest.raises(PropertyError) as info:
            await group.set(path, value, params)
        assert info.value.code is Code.INVALID_ARGUMENT
        assert words in info.value.message
        assert parse_names(await group.get("subgroups")) == []
        assert parse_vector(await world.backend("scout1").get("location"))[:2].tolist() == [0.0, 0.0]
    finally:
        await group.aclose()


def test_bad_options_are_refused_when_the_group_is_made() -> None:
    directory = MemoryDirectory()
    with pytest.raises(PropertyError, match="members or a query"):
        Group(directory=directory, members=["a"], query={"type": "mobile_robot"})
    with pytest.raises(PropertyError, match="unknown query parameter 'colour'"):
        Group(directory=directory, query={"colour": "red"})
    with pytest.raises(PropertyError, match="list of names"):
        Group(directory=directory, members="scout1")
    with pytest.raises(PropertyError, match="member_timeout"):
        Group(directory=directory, members=[], member_timeout=0)
    assert query_params({"type": "mobile_robot", "near": [5, 5, 0], "radius": 3}) == query_params(
        "type=mobile_robot&near=(5 5 0)&radius=3"
    )


async def test_velocity_is_the_mean_of_the_members(world: MemoryDirectory) -> None:
    group = await make_group(world, members=["scout1", "scout2"])
    try:
        np.testing.assert_allclose(parse_vector(await group.get("velocity")), np.zeros(6))
        assert parse_names(await group.set("behaviors.stop", "")) == ["scout1", "scout2"]
    finally:
        await group.aclose()


async def test_a_thousand_members_all_accept_their_targets() -> None:
    directory = MemoryDirectory()
    names = [f"r{i}" for i in range(1000)]
    for i, name in enumerate(names):
        await directory.add(name, LocalService(SimRobot(start=(i % 40, i // 40), tick_hz=0.1)))
    group = await make_group(directory, members=names)
    try:
        accepted = await group.set(
            "behaviors.moveto", "<marker><location>(0 0)</location></marker>", {"formation": "grid"}
        )
        assert parse_names(accepted) == sorted(names, key=lambda n: int(n[1:]))
    finally:
        await group.aclose()
        for name in directory.names():
            await directory.unregister(name)

"""Teleoperating a group: a velocity Set for every member, and one ``behaviors.stop`` for all."""

from __future__ import annotations

from collections.abc import AsyncIterator

import numpy as np
import pytest
from support.group_support import MemoryDirectory, unreachable_robot, wait_for

from services.apps.group import Group, GroupCallFailed
from services.apps.simulators import SimRobot
from services.kernel.core import LocalService
from services.kernel.errors import Code, PropertyError
from services.kernel.values import parse_list, parse_names, parse_vector

ZERO = "(0 0 0 0 0 0)"


def robot(x: float, *, max_speed: float, velocity_timeout: float = 30.0) -> LocalService:
    return LocalService(
        SimRobot(start=(x, 0), speed=1.0, max_speed=max_speed, velocity_timeout=velocity_timeout, tick_hz=50)
    )


@pytest.fixture
async def world() -> AsyncIterator[MemoryDirectory]:
    directory = MemoryDirectory()
    await directory.add("fast", robot(0, max_speed=1.0))
    await directory.add("slow", robot(2, max_speed=0.5))
    yield directory
    await directory.aclose()


@pytest.fixture
async def group(world: MemoryDirectory) -> AsyncIterator[LocalService]:
    service = LocalService(Group(directory=world, members=["fast", "slow"]))
    await service.start()
    yield service
    await service.aclose()


async def test_a_velocity_set_commands_every_member_within_its_own_limits(
    world: MemoryDirectory, group: LocalService
) -> None:
    assert parse_names(await group.set("velocity", "(2 0)")) == ["fast", "slow"]
    assert await world.backend("fast").get("velocity") == "(1 0 0 0 0 0)"
    assert await world.backend("slow").get("velocity") == "(0.5 0 0 0 0 0)"
    np.testing.assert_allclose(parse_vector(await group.get("velocity")), [0.75, 0, 0, 0, 0, 0])
    await wait_for(world.backend("slow"), "location", lambda v: parse_vector(v)[0] > 2.0)
    assert parse_list(await group.get("failed")) == []


async def test_members_stop_by_themselves_when_the_group_stops_renewing(world: MemoryDirectory) -> None:
    await world.add("brief", robot(5, max_speed=1.0, velocity_timeout=0.1))
    service = LocalService(Group(directory=world, members=["brief"]))
    await service.start()
    try:
        assert parse_names(await service.set("velocity", "(0 1)")) == ["brief"]
        await wait_for(world.backend("brief"), "velocity", lambda v: v == ZERO)
        assert 0.0 < parse_vector(await world.backend("brief").get("location"))[1] <= 0.1 + 1e-9
    finally:
        await service.aclose()


async def test_behaviors_stop_stops_every_member(world: MemoryDirectory, group: LocalService) -> None:
    assert parse_names(await group.get("behaviors")) == ["moveto", "stop"]
    await group.set("velocity", "(1 1)")
    await world.backend("slow").set("behaviors.moveto", "<marker><location>(2 50)</location></marker>")
    assert parse_names(await group.set("behaviors.stop", "")) == ["fast", "slow"]
    for name in ("fast", "slow"):
        assert await world.backend(name).get("velocity") == ZERO
    with pytest.raises(PropertyError) as info:
        await group.set("behaviors.halt", "")
    assert info.value.code is Code.NOT_FOUND


async def test_a_member_that_fails_is_named_and_the_others_drive(world: MemoryDirectory) -> None:
    await world.add("dead", unreachable_robot())
    service = LocalService(Group(directory=world, members=["dead", "fast"]))
    await service.start()
    try:
        with pytest.raises(GroupCallFailed) as info:
            await service.set("velocity", "(0.5 0)")
        assert info.value.code is Code.UNAVAILABLE
        assert "velocity failed on 1 of 2 members (the other 1 acted)" in info.value.message
        assert parse_list(await service.get("failed")) == [["dead", "UNAVAILABLE"]]
        assert await world.backend("fast").get("velocity") == "(0.5 0 0 0 0 0)"
    finally:
        await service.aclose()


async def test_bad_velocity_commands_are_invalid_arguments(
    world: MemoryDirectory, group: LocalService
) -> None:
    for bad in ["fast", "(1)"]:
        with pytest.raises(PropertyError) as info:
            await group.set("velocity", bad)
        assert info.value.code is Code.INVALID_ARGUMENT
    for name in ("fast", "slow"):
        assert await world.backend(name).get("velocity") == ZERO


async def test_a_get_never_carries_a_command(world: MemoryDirectory, group: LocalService) -> None:
    with pytest.raises(PropertyError) as info:
        await group.get("velocity", {"command": "(1 0)"})
    assert info.value.code is Code.INVALID_ARGUMENT
    assert await world.backend("fast").get("velocity") == ZERO


async def test_stopping_the_group_service_leaves_its_robots_driving(world: MemoryDirectory) -> None:
    service = LocalService(Group(directory=world, members=["fast", "slow"]))
    await service.start()
    await service.set("velocity", "(1 0)")
    await service.aclose()  # the lifecycle stop, as at gateway shutdown: not behaviors.stop
    assert await world.backend("fast").get("velocity") == "(1 0 0 0 0 0)"

"""Listen, children added and removed at runtime, remote children and the lifecycle of the class wrapper."""

from __future__ import annotations

import asyncio
from typing import Annotated

import numpy as np
import pytest

from services.kernel.backend import Change
from services.kernel.core import LocalService, Prop, Resource, functional
from services.kernel.errors import AlreadyExists, InvalidArgument, NotFound
from services.kernel.values import Marker, Vector, parse_marker, parse_names


class Tool(Resource):
    """A plug-in tool."""

    power: float = 0.0

    def __init__(self) -> None:
        self.started = 0
        self.stopped = 0

    async def start(self) -> None:
        self.started += 1

    async def stop(self) -> None:
        self.stopped += 1


class Tools(Resource):
    """Tools plugged in right now."""


class Robot(Resource):
    """A small robot."""

    resource_type = "mobile_robot"

    location: Annotated[Vector, Prop(readonly=True)]
    speed: float = 0.5
    tools: Tools

    def __init__(self) -> None:
        self.location = np.zeros(6)
        self.tools = Tools()
        self._charge = 1.0
        self.stops = 0

    @property
    def charge(self) -> float:
        return self._charge

    def drain(self, amount: float) -> None:
        self._charge -= amount
        self.changed("charge")

    @functional
    async def stop(self) -> None:
        self.stops += 1


def collector() -> tuple[list[Change], object]:
    changes: list[Change] = []
    return changes, changes.append


@pytest.fixture
def robot() -> Robot:
    return Robot()


@pytest.fixture
def svc(robot: Robot) -> LocalService:
    return LocalService(robot)


async def test_assignment_notifies_only_on_a_changed_text(svc: LocalService, robot: Robot) -> None:
    changes: list[Change] = []
    await svc.listen("speed", changes.append)
    robot.speed = 1.0
    robot.speed = 1.0
    robot.speed = 1.5
    assert changes == [Change("speed", "1"), Change("speed", "1.5")]


async def test_listen_does_not_send_the_current_value(svc: LocalService) -> None:
    changes: list[Change] = []
    await svc.listen("location", changes.append)
    assert changes == []


async def test_set_from_outside_notifies(svc: LocalService) -> None:
    changes: list[Change] = []
    await svc.listen("speed", changes.append)
    await svc.set("speed", "2")
    assert changes == [Change("speed", "2")]


async def test_sub_property_listeners_fire_only_when_their_element_changes(
    svc: LocalService, robot: Robot
) -> None:
    xs: list[Change] = []
    whole: list[Change] = []
    await svc.listen("location.x", xs.append)
    await svc.listen("location", whole.append)
    robot.location = np.array([0.0, 1.0, 0, 0, 0, 0])
    robot.location = np.array([2.0, 1.0, 0, 0, 0, 0])
    assert [c.value for c in whole] == ["(0 1 0 0 0 0)", "(2 1 0 0 0 0)"]
    assert xs == [Change("location.x", "2")]


async def test_computed_property_notifies_through_changed(svc: LocalService, robot: Robot) -> None:
    changes: list[Change] = []
    await svc.listen("charge", changes.append)
    robot.drain(0.25)
    robot.changed("charge")  # nothing new: nothing sent
    assert changes == [Change("charge", "0.75")]


async def test_many_listeners_and_idempotent_close(svc: LocalService, robot: Robot) -> None:
    a: list[Change] = []
    b: list[Change] = []
    sub_a = await svc.listen("speed", a.append)
    await svc.listen("speed", b.append)
    robot.speed = 3.0
    await sub_a.close()
    await sub_a.close()
    robot.speed = 4.0
    assert [c.value for c in a] == ["3"]
    assert [c.value for c in b] == ["3", "4"]


async def test_closing_the_last_listener_unhooks_the_attribute(svc: LocalService, robot: Robot) -> None:
    sub = await svc.listen("speed", lambda change: None)
    assert "speed" in robot._ps_watch
    await sub.close()
    assert "speed" not in robot._ps_watch


async def test_a_listener_that_raises_is_dropped_and_the_others_carry_on(
    svc: LocalService, robot: Robot, caplog: pytest.LogCaptureFixture
) -> None:
    good: list[Change] = []
    calls = 0

    def bad(change: Change) -> None:
        nonlocal calls
        calls += 1
        raise RuntimeError("listener bug")

    await svc.listen("speed", bad)
    await svc.listen("speed", good.append)
    robot.speed = 1.0
    robot.speed = 2.0
    assert calls == 1
    assert [c.value for c in good] == ["1", "2"]
    assert "listener bug" in caplog.text


async def test_listen_on_unknown_or_bad_path(svc: LocalService) -> None:
    with pytest.raises(NotFound):
        await svc.listen("sped", lambda change: None)
    with pytest.raises(InvalidArgument):
        await svc.listen("speed..x", lambda change: None)


async def test_attach_and_detach_change_properties_and_notify(svc: LocalService, robot: Robot) -> None:
    props: list[Change] = []
    names: list[Change] = []
    await svc.listen("properties", props.append)
    await svc.listen("tools", names.append)
    assert await svc.get("tools") == "()"

    gripper = Tool()
    robot.tools.attach("gripper", gripper)
    assert await svc.get("tools.gripper.power") == "0"
    assert "tools.gripper.power" in parse_names(await svc.get("properties"))
    assert [parse_names(c.value) for c in names] == [["gripper"]]
    assert len(props) == 1 and "tools.gripper.power" in parse_names(props[0].value)

    power: list[Change] = []
    await svc.listen("tools.gripper.power", power.append)
    gripper.power = 0.5
    assert robot.tools.detach("gripper") is gripper
    gripper.power = 0.9  # detached: no one hears it any more
    assert power == [Change("tools.gripper.power", "0.5"), Change("tools.gripper.power", "", removed=True)]
    assert [parse_names(c.value) for c in names] == [["gripper"], []]
    assert "tools.gripper.power" not in parse_names(props[-1].value)
    with pytest.raises(NotFound):
        await svc.get("tools.gripper.power")


async def test_attach_refuses_taken_and_bad_names(robot: Robot) -> None:
    robot.tools.attach("drill", Tool())
    with pytest.raises(AlreadyExists):
        robot.tools.attach("drill", Tool())
    with pytest.raises(AlreadyExists):
        robot.attach("speed", Tool())
    with pytest.raises(InvalidArgument):
        robot.tools.attach("bad name", Tool())
    with pytest.raises(NotFound):
        robot.tools.detach("saw")


async def test_child_assigned_as_attribute_is_a_namespace(svc: LocalService, robot: Robot) -> None:
    props: list[Change] = []
    await svc.listen("properties", props.append)
    robot.camera = Tool()
    assert parse_names(await svc.get("properties"))[-2:] == ["camera", "camera.power"]
    assert len(props) == 1


async def test_lifecycle_starts_children_and_stops_them(svc: LocalService, robot: Robot) -> None:
    early = Tool()
    robot.tools.attach("early", early)
    await svc.start()
    assert early.started == 1
    late = Tool()
    robot.tools.attach("late", late)
    for _ in range(10):
        if late.started:
            break
        await asyncio.sleep(0)
    assert late.started == 1
    robot.tools.detach("late")
    for _ in range(10):
        if late.stopped:
            break
        await asyncio.sleep(0)
    assert late.stopped == 1
    await svc.aclose()
    await svc.aclose()
    assert (early.started, early.stopped) == (1, 1)


async def test_functional_stop_is_not_the_lifecycle_hook(svc: LocalService, robot: Robot) -> None:
    await svc.start()
    await svc.aclose()
    assert robot.stops == 0
    assert await svc.set("stop", "") == ""
    assert robot.stops == 1


async def test_a_backend_child_is_reached_through_its_prefix() -> None:
    member = Robot()
    member_svc = LocalService(member)

    class Group(Resource):
        """Robots behind one service."""

        def __init__(self) -> None:
            self.robots = Tools()

    group = Group()
    svc = LocalService(group)
    group.robots.attach("scout1", member_svc)

    assert await svc.get("robots.scout1.speed") == "0.5"
    assert await svc.set("robots.scout1.speed", "2") == "2"
    assert member.speed == 2.0
    assert await svc.get("robots.scout1") == "(location speed tools charge stop)"
    props = parse_names(await svc.get("properties"))
    assert props[:4] == ["robots", "robots.scout1", "robots.scout1.location", "robots.scout1.speed"]

    changes: list[Change] = []
    await svc.listen("robots.scout1.speed", changes.append)
    member.speed = 3.0
    assert changes == [Change("robots.scout1.speed", "3")]

    group.robots.detach("scout1")
    member.speed = 4.0
    assert changes[-1] == Change("robots.scout1.speed", "", removed=True)
    for _ in range(10):
        if "speed" not in member._ps_watch:
            break
        await asyncio.sleep(0)
    assert "speed" not in member._ps_watch
    with pytest.raises(NotFound):
        await svc.get("robots.scout1.speed")


async def test_one_resource_cannot_sit_in_two_places(robot: Robot) -> None:
    tool = Tool()
    robot.tools.attach("a", tool)
    with pytest.raises(InvalidArgument, match="already attached"):
        robot.tools.attach("b", tool)


async def test_properties_follows_the_property_lists_of_remote_children() -> None:
    member = Robot()

    class Group(Resource):
        """Robots behind one service."""

        def __init__(self) -> None:
            self.robots = Tools()

    group = Group()
    svc = LocalService(group)
    changed = asyncio.Event()
    lists: list[list[str]] = []

    def on_properties(change: Change) -> None:
        lists.append(parse_names(change.value))
        changed.set()

    sub = await svc.listen("properties", on_properties)
    group.robots.attach("scout1", LocalService(member))
    await asyncio.wait_for(changed.wait(), timeout=5)
    assert "robots.scout1.speed" in lists[-1]

    changed.clear()
    member.tools.attach("drill", Tool())  # the member's own list changes
    await asyncio.wait_for(changed.wait(), timeout=5)
    assert "robots.scout1.tools.drill.power" in lists[-1]

    await sub.close()
    for _ in range(10):
        if not member._ps_tree_watchers[1:]:
            break
        await asyncio.sleep(0)
    assert member._ps_tree_watchers[1:] == []  # the member's own service stopped following it
    await svc.aclose()


async def test_marker_field_listeners_hear_only_their_field() -> None:
    class Beacon(Resource):
        """A beacon showing a marker."""

        target: Marker

        def __init__(self) -> None:
            self.target = parse_marker("<marker><location>(1 2)</location><color>red</color></marker>")

    beacon = Beacon()
    svc = LocalService(beacon)
    colors: list[Change] = []
    await svc.listen("target.color", colors.append)
    beacon.target = parse_marker("<marker><location>(5 5)</location><color>red</color></marker>")
    beacon.target = parse_marker("<marker><location>(5 5)</location><color>blue</color></marker>")
    assert colors == [Change("target.color", "blue")]

"""The environment model follows its sources through a real router: cameras, robots, readings, late ones."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated

import numpy as np
import pytest
from support.waiting import eventually, wait_until

import services.apps.environment.sources as sources_module
from gateway.engine.router import Router
from services.apps.environment import EnvironmentModel
from services.apps.simulators import SimRobot
from services.kernel.backend import NO_PARAMS, Notify, Subscription
from services.kernel.core import LocalService, Prop, Resource
from services.kernel.errors import Unavailable
from services.kernel.values import parse_list


class ScriptedCamera(Resource):
    """A camera whose ``markers`` the test writes."""

    resource_type = "camera"
    markers: Annotated[str, Prop(readonly=True, doc="markers in view, one after the other")]

    def __init__(self) -> None:
        self.markers = ""


def sources(model: EnvironmentModel) -> dict[str, str]:
    return {f"{service} {role}": state for service, role, _, state, _ in model.sources}


@pytest.fixture
async def router():
    router = Router()
    yield router
    for name in list(router.names()):
        await router.remove(name).aclose()


async def test_a_camera_that_comes_later_is_followed_and_its_markers_fused(router: Router) -> None:
    model = EnvironmentModel(directory=router, markers=["camera1"], ttl=60.0)
    env = LocalService(model)
    await env.start()
    router.add("env", env)
    try:
        await wait_until(lambda: sources(model)["camera1 markers"] == "absent", what="camera1 is waited for")
        camera = ScriptedCamera()
        cam = LocalService(camera)
        await cam.start()
        router.add("camera1", cam)  # the directory says it joined: no waiting out a pause
        await wait_until(lambda: sources(model)["camera1 markers"] == "following", what="camera1 followed")
        camera.markers = (
            "(<marker><id>a</id><class>cube</class><location>(1 1)</location><color>(1 0 0)</color>"
            "<confidence>0.5</confidence></marker> "
            "<marker><id>b</id><class>ball</class><location>(1.05 1)</location></marker>)"
        )
        await wait_until(lambda: len(model.fusion) == 2, what="both markers fused")
        camera.markers = "<marker><id>a</id><class>cube</class><location>(1.02 1)</location></marker>"
        await wait_until(lambda: model.fusion.get("a") is not None and model.fusion.get("a").count == 2)
        cube = model.fusion.get("a")
        assert cube is not None and cube.fields["color"] == "(1 0 0)"
        assert await env.get("grid.occupancy.info") != ""
        info = dict(parse_list(await env.get("grid.occupancy.info")))
        assert info["total"] == "2"  # a and b; a seen again in the same cell is not a new hit
        camera.markers = "not markers at all"  # a bad list is dropped, the model carries on
        camera.markers = "<marker><id>c</id><class>cube</class><location>(5 5)</location></marker>"
        await wait_until(lambda: "c" in model.fusion)
    finally:
        await env.aclose()


async def test_robots_and_their_temperature_readings(router: Router) -> None:
    # Steps of at most 0.2 m (5 ticks of a late loop): no cell of 0.5 m is stepped over.
    robot = SimRobot(start=(0.25, 0.25), speed=2.0, tick_hz=50.0, temperature_hz=1000.0, seed=1)
    bot = LocalService(robot)
    await bot.start()
    router.add("bot", bot)
    model = EnvironmentModel(
        directory=router,
        robots=["bot"],
        readings=[{"selector": "bot sensors.temperature"}],
        grid={"origin": [0, 0], "cell": 0.5, "shape": [2, 8]},
    )
    env = LocalService(model)
    await env.start()
    router.add("env", env)
    try:
        await wait_until(lambda: "bot" in model.fusion, what="the robot's own marker")
        await wait_until(lambda: all(s == "following" for s in sources(model).values()))
        # Drive along the bottom row: every cell of it gets readings.
        robot.drive_to(np.array([3.75, 0.25]), "world")
        info = await eventually(
            lambda: env.get("grid.temperature.info"), lambda v: dict(parse_list(v))["filled"] == "8"
        )
        assert dict(parse_list(info))["outside"] == "0"
        skipped = dict(parse_list(await env.get("skipped")))
        assert set(skipped) == {"unplaced", "unreadable"} and skipped["unreadable"] == "0"
        marker = model.fusion.get("bot")
        assert marker is not None and marker.cls == "mobile_robot" and marker.source == "bot"
        # Its marker follows it to where it stops (within the filter's lag behind the last report).
        await wait_until(lambda: abs(float(marker.position[0]) - 3.75) < 0.05, what="the marker at the end")
    finally:
        await env.aclose()


class FlakyService(LocalService):
    """A robot whose first Listens of ``location`` fail as a device out of reach answers."""

    def __init__(self, obj: Resource, failures: int) -> None:
        super().__init__(obj)
        self.failures = failures

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path == "location" and self.failures > 0:
            self.failures -= 1
            raise Unavailable("device out of reach")
        return await super().listen(path, notify, params)


async def test_a_source_that_fails_is_tried_again_and_the_others_carry_on(
    router: Router, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sources_module, "RETRY_FIRST_S", 0.01)
    flaky = FlakyService(SimRobot(start=(1.0, 1.0)), failures=3)
    steady = LocalService(SimRobot(start=(5.0, 5.0)))
    for name, backend in (("flaky", flaky), ("steady", steady)):
        await backend.start()
        router.add(name, backend)
    model = EnvironmentModel(directory=router, robots=["flaky", "steady"])
    env = LocalService(model)
    await env.start()
    router.add("env", env)
    try:
        await wait_until(lambda: "steady" in model.fusion, what="the steady robot, while the other fails")
        await wait_until(lambda: "flaky" in model.fusion, what="the flaky robot, once it answers")
        assert flaky.failures == 0
        assert {s: state for s, _, _, state, _ in model.sources} == {
            "flaky": "following",
            "steady": "following",
        }
    finally:
        await env.aclose()


async def test_what_a_camera_still_sees_does_not_expire(router: Router) -> None:
    # A camera tells only of changes: a still scene sends nothing, and must not age out.
    now = [1000.0]
    model = EnvironmentModel(directory=router, markers=["camera1"], ttl=10.0, clock=lambda: now[0])
    env = LocalService(model)
    await env.start()
    router.add("env", env)
    camera = ScriptedCamera()
    cam = LocalService(camera)
    await cam.start()
    router.add("camera1", cam)
    try:
        await wait_until(lambda: sources(model)["camera1 markers"] == "following", what="camera1 followed")
        camera.markers = (
            "(<marker><id>crate</id><class>box</class><location>(1 3)</location></marker> "
            "<marker><id>ball</id><class>ball</class><location>(-1 1.5)</location></marker>)"
        )
        await wait_until(lambda: len(model.fusion) == 2, what="both markers fused")
        cone = "<marker><id>cone</id><class>cone</class><location>(4 4)</location></marker>"
        await env.set("observe", cone)
        now[0] += 60.0
        assert model.expire() == ["cone"]  # seen once, by no camera that still sees it
        assert sorted(model.fusion.ids()) == ["ball", "crate"]
        # The ball leaves the view: from then on it ages as any marker does.
        camera.markers = "(<marker><id>crate</id><class>box</class><location>(1 3)</location></marker>)"
        await wait_until(lambda: model.fusion.get("crate").count == 2, what="the second list fused")
        now[0] += 60.0
        assert model.expire() == ["ball"]
        assert model.fusion.ids() == ["crate"]
    finally:
        await env.aclose()


async def test_a_camera_sighting_of_a_robot_and_its_own_report_are_one_marker(router: Router) -> None:
    robot = SimRobot(start=(1.0, 2.0), tick_hz=50.0, seed=1)
    bot = LocalService(robot)
    await bot.start()
    router.add("bot", bot)
    camera = ScriptedCamera()
    cam = LocalService(camera)
    await cam.start()
    router.add("camera1", cam)
    model = EnvironmentModel(directory=router, robots=["bot"], markers=["camera1"])
    env = LocalService(model)
    await env.start()
    router.add("env", env)
    try:
        await wait_until(lambda: all(s == "following" for s in sources(model).values()), what="both followed")
        await wait_until(lambda: "bot" in model.fusion, what="the robot's own marker")
        # What a camera says of a robot it sees: its name, the robot's resource type, near it.
        camera.markers = (
            "(<marker><id>bot</id><class>mobile_robot</class><location>(1.02 2 0)</location></marker>)"
        )
        await wait_until(lambda: model.fusion.get("bot").source == "camera1", what="the sighting fused")
        assert model.fusion.ids() == ["bot"]
    finally:
        await env.aclose()


async def test_an_object_that_stays_in_its_cell_counts_once_on_occupancy(router: Router) -> None:
    # A camera sends its whole list whenever anything in view moves: a crate that stays where it
    # is must not pile up hits each time a robot drives past it.
    model = EnvironmentModel(
        directory=router, markers=["camera1"], grid={"origin": [0.0, 0.0], "cell": 1.0, "shape": [10, 10]}
    )
    env = LocalService(model)
    await env.start()
    router.add("env", env)
    camera = ScriptedCamera()
    cam = LocalService(camera)
    await cam.start()
    router.add("camera1", cam)
    crate = "<marker><id>crate</id><class>box</class><location>(1.5 3.5)</location></marker>"

    def robot_at(x: float) -> str:
        return f"<marker><id>scout1</id><class>mobile_robot</class><location>({x} 5.5)</location></marker>"

    def hits() -> np.ndarray:
        return model.layers["occupancy"].values()

    try:
        await wait_until(lambda: sources(model)["camera1 markers"] == "following", what="camera1 followed")
        for lists, x in enumerate((0.5, 0.7, 1.5, 1.6, 2.5), start=1):
            camera.markers = f"({crate} {robot_at(x)})"
            await wait_until(lambda n=lists: model.fusion.get("crate").count == n, what=f"list {lists} fused")
        grid = hits()
        assert grid[model.spec.index(1.5, 3.5)] == 1  # the crate: once, in five lists
        # The robot: once per cell it entered (0.5 and 0.7 share one; 1.5 and 1.6 another).
        assert [grid[model.spec.index(x, 5.5)] for x in (0.5, 1.5, 2.5)] == [1, 1, 1]
        assert grid.sum() == 4
        # Gone from view and back: a new sighting, counted again.
        camera.markers = f"({robot_at(2.5)})"
        await wait_until(lambda: model.fusion.get("scout1").count == 6, what="the crate left the view")
        camera.markers = f"({crate} {robot_at(2.5)})"
        await wait_until(lambda: model.fusion.get("crate").count == 6, what="the crate back in view")
        assert hits()[model.spec.index(1.5, 3.5)] == 2
    finally:
        await env.aclose()

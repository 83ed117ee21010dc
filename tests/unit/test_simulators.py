"""The simulated robot and sensor, driven through LocalService as the gateway drives them."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator

import numpy as np
import pytest

from services.apps.catalog import CATALOG, create
from services.apps.simulators import SimRobot, SimSensor
from services.kernel.backend import Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, InvalidArgument, PropertyError
from services.kernel.values import parse_list, parse_names, parse_vector

# Fast enough that a few metres take well under a second of real time.
FAST = {"speed": 20.0, "tick_hz": 200.0}


@pytest.fixture
async def robot() -> AsyncIterator[LocalService]:
    svc = LocalService(SimRobot(**FAST))  # type: ignore[arg-type]
    await svc.start()
    yield svc
    await svc.aclose()


async def arrival(svc: LocalService) -> asyncio.Event:
    """An event set when the robot reports zero velocity."""
    stopped = asyncio.Event()

    def on_velocity(change: Change) -> None:
        if not np.any(parse_vector(change.value)):
            stopped.set()

    await svc.listen("velocity", on_velocity)
    return stopped


async def test_standard_mobile_robot_properties(robot: LocalService) -> None:
    assert robot.info.type == "mobile_robot"
    names = parse_names(await robot.get("properties"))
    for name in ["location", "velocity", "speed", "actuators", "sensors", "behaviors", "behaviors.moveto"]:
        assert name in names
    assert await robot.get("behaviors") == "(moveto stop)"
    assert await robot.get("location") == "(0 0 0 0 0 0)"
    assert await robot.get("location.gui") == "pose"
    assert parse_list(await robot.get("behaviors.moveto.parameters")) == [["frame", "text", "world"]]


async def test_moveto_reaches_the_target_and_location_goes_quiet(robot: LocalService) -> None:
    locations: list[Change] = []
    await robot.listen("location", locations.append)
    stopped = await arrival(robot)
    await robot.set("behaviors.moveto", "<marker><location>(3 4)</location></marker>")
    await asyncio.wait_for(stopped.wait(), timeout=5)

    assert parse_vector(await robot.get("location"))[:2].tolist() == [3.0, 4.0]
    assert await robot.get("velocity") == "(0 0 0 0 0 0)"
    assert len(locations) > 2
    # Straight toward the target, never past it.
    for change in locations:
        x, y = parse_vector(change.value)[:2]
        assert 0.0 <= x <= 3.0 and 0.0 <= y <= 4.0
        assert math.isclose(y * 3.0, x * 4.0, abs_tol=1e-9)
    assert parse_vector(locations[-1].value)[5] == pytest.approx(math.atan2(4, 3))

    heard = len(locations)
    for _ in range(20):  # several ticks' worth of idle time
        await asyncio.sleep(0.01)
    assert len(locations) == heard


async def test_moveto_in_the_robot_frame(robot: LocalService) -> None:
    stopped = await arrival(robot)
    await robot.set("behaviors.moveto", "<marker><location>(0 1)</location></marker>")
    await asyncio.wait_for(stopped.wait(), timeout=5)
    stopped.clear()
    # Now heading +y: 1 m ahead in the robot frame is +y in the world.
    await robot.set("behaviors.moveto", "<marker><location>(1 0)</location></marker>", {"frame": "robot"})
    await asyncio.wait_for(stopped.wait(), timeout=5)
    x, y = parse_vector(await robot.get("location"))[:2]
    assert x == pytest.approx(0.0, abs=1e-9)
    assert y == pytest.approx(2.0)


async def test_stop_halts_the_robot(robot: LocalService) -> None:
    await robot.set("speed", "1")
    await robot.set("behaviors.moveto", "<marker><location>(100 0)</location></marker>")
    moving = asyncio.Event()
    await robot.listen("location", lambda change: moving.set())
    await asyncio.wait_for(moving.wait(), timeout=5)
    await robot.set("behaviors.stop", "")
    assert await robot.get("velocity") == "(0 0 0 0 0 0)"
    here = await robot.get("location")
    for _ in range(5):
        await asyncio.sleep(0.01)
    assert await robot.get("location") == here
    assert parse_vector(here)[0] < 100.0


async def test_battery_drains_while_driving(robot: LocalService) -> None:
    stopped = await arrival(robot)
    await robot.set("behaviors.moveto", "<marker><location>(5 0)</location></marker>")
    await asyncio.wait_for(stopped.wait(), timeout=5)
    assert float(await robot.get("sensors.battery")) == pytest.approx(0.995, abs=1e-4)


async def test_moveto_refuses_bad_targets(robot: LocalService) -> None:
    with pytest.raises(InvalidArgument, match="no location"):
        await robot.set("behaviors.moveto", "<marker><color>red</color></marker>")
    with pytest.raises(InvalidArgument, match="frame"):
        await robot.set("behaviors.moveto", "<marker><location>(1 2)</location></marker>", {"frame": "moon"})
    with pytest.raises(InvalidArgument, match="2 to 6"):
        await robot.set("behaviors.moveto", "<marker><location>(1)</location></marker>")
    with pytest.raises(InvalidArgument):
        await robot.set("behaviors.moveto", "(1 2)")
    with pytest.raises(InvalidArgument):
        await robot.set("speed", "-1")


async def test_location_is_read_only_from_outside(robot: LocalService) -> None:
    with pytest.raises(PropertyError) as info:
        await robot.set("location", "(1 1)")
    assert info.value.code is Code.FAILED_PRECONDITION
    with pytest.raises(PropertyError) as info:
        await robot.get("behaviors.moveto")
    assert info.value.code is Code.FAILED_PRECONDITION


async def test_actuators_led_is_writable(robot: LocalService) -> None:
    assert await robot.set("actuators.led", "on") == "true"
    assert await robot.get("actuators.led") == "true"


def test_robot_options_are_checked() -> None:
    robot = SimRobot(start=[1, 2, 0, 0, 0, 1.5])
    assert robot.location.tolist() == [1, 2, 0, 0, 0, 1.5]
    for bad in [{"start": [1]}, {"start": "here"}, {"speed": -1}, {"tick_hz": 0}]:
        with pytest.raises(InvalidArgument):
            SimRobot(**bad)  # type: ignore[arg-type]


async def test_sensor_produces_data_at_its_rate() -> None:
    svc = LocalService(SimSensor(seed=7, rate_hz=100))
    assert svc.info.type == "sensor"
    assert parse_names(await svc.get("properties")) == ["location", "data", "rate_hz"]
    readings: list[Change] = []
    enough = asyncio.Event()

    def on_data(change: Change) -> None:
        readings.append(change)
        if len(readings) >= 5:
            enough.set()

    await svc.listen("data", on_data)
    await svc.start()
    try:
        await asyncio.wait_for(enough.wait(), timeout=5)
    finally:
        await svc.aclose()
    values = [float(c.value) for c in readings]
    assert all(15.0 < v < 25.0 for v in values)
    heard = len(readings)
    await asyncio.sleep(0.05)
    assert len(readings) == heard  # stopped with the service


def test_sensor_noise_is_deterministic_with_a_seed() -> None:
    a, b, c = SimSensor(seed=3), SimSensor(seed=3), SimSensor(seed=4)
    runs = []
    for sensor in (a, b, c):
        series = [sensor.data]
        for _ in range(5):
            sensor.sample(0.2)
            series.append(sensor.data)
        runs.append(series)
    assert runs[0] == runs[1]
    assert runs[0] != runs[2]


async def test_sensor_rate_is_writable_within_bounds() -> None:
    svc = LocalService(SimSensor(seed=1))
    assert await svc.set("rate_hz", "20") == "20"
    with pytest.raises(InvalidArgument):
        await svc.set("rate_hz", "0")
    with pytest.raises(PropertyError) as info:
        await svc.set("data", "1")
    assert info.value.code is Code.FAILED_PRECONDITION


def test_catalog_creates_by_kind() -> None:
    assert set(CATALOG) >= {"sim-robot", "sim-sensor"}
    robot = create("sim-robot", start=[1, 2], speed=1.0)
    assert isinstance(robot, SimRobot)
    assert robot.location[:2].tolist() == [1.0, 2.0]
    assert isinstance(create("sim-sensor", seed=1, rate_hz=2.0), SimSensor)


def test_catalog_refuses_unknown_kinds_and_options() -> None:
    with pytest.raises(InvalidArgument, match="sim-robot, sim-sensor"):
        create("sim-robott")
    with pytest.raises(InvalidArgument, match="spede") as info:
        create("sim-robot", spede=1)
    assert "speed" in info.value.message
    with pytest.raises(InvalidArgument, match="start"):
        create("sim-robot", start=[1])
    with pytest.raises(InvalidArgument, match="seed"):
        create("sim-sensor", seed="abc")

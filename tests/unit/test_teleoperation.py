"""Teleoperating a simulated robot: velocity commands, their limits and their watchdog.

Most tests run the simulation on their own clock (``SimRobot.advance``, no
motion task), so what they assert is exact; the ones that need the motion
task bound their waits generously and assert nothing about timing.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator

import numpy as np
import pytest
from support.waiting import wait_until

from services.apps.simulators import DEFAULT_VELOCITY_TIMEOUT, SimRobot
from services.kernel.backend import Change
from services.kernel.core import LocalService
from services.kernel.errors import Code, InvalidArgument, PropertyError
from services.kernel.values import parse_vector

MOVETO_FAR = "<marker><location>(0 100)</location></marker>"


def xy_yaw(robot: SimRobot) -> list[float]:
    return [float(robot.location[0]), float(robot.location[1]), float(robot.location[5])]


@pytest.fixture
def sim() -> SimRobot:
    """A robot whose motion task never runs: the tests move it with ``advance``."""
    return SimRobot(speed=1.0, max_speed=1.0, max_turn_rate=0.5, velocity_timeout=0.5)


@pytest.fixture
def service(sim: SimRobot) -> LocalService:
    return LocalService(sim)


async def test_a_set_outside_the_limits_is_clipped_and_answers_what_is_commanded(
    service: LocalService,
) -> None:
    # 5 m/s along (3 4) becomes 1 m/s in the same direction; roll and pitch rates are zero; 2 rad/s → 0.5.
    answer = await service.set("velocity", "(3 4 0 0.2 0.3 2)")
    np.testing.assert_allclose(parse_vector(answer), [0.6, 0.8, 0, 0, 0, 0.5])
    assert await service.get("velocity") == answer
    # Within the limits nothing changes; 2 and 3 numbers are vx vy and vx vy vz.
    assert await service.set("velocity", "(0.25 -0.5)") == "(0.25 -0.5 0 0 0 0)"
    assert await service.set("velocity", "(0 0 0 0 0 -0.4)") == "(0 0 0 0 0 -0.4)"


async def test_the_limits_are_properties_with_units_and_ranges(service: LocalService) -> None:
    assert await service.get("max_speed") == "1"
    assert await service.get("max_turn_rate") == "0.5"
    assert await service.get("velocity_timeout") == "0.5"
    model = {p.name: p for p in (await service.describe()).properties}
    assert model["max_speed"].unit == "m/s"
    assert model["max_turn_rate"].unit == "rad/s"
    assert model["velocity_timeout"].unit == "s"
    assert (model["velocity"].unit, model["velocity"].length, model["velocity"].access) == (
        "m/s, rad/s",
        6,
        "read-write",
    )
    for name, bad in [("max_speed", "-1"), ("max_turn_rate", "1000"), ("velocity_timeout", "0")]:
        with pytest.raises(InvalidArgument, match="out of range"):
            await service.set(name, bad)
    with pytest.raises(InvalidArgument, match="out of range"):
        await service.set("velocity_timeout", "3600")
    # The clipping follows the limits as they are now.
    await service.set("max_speed", "0.1")
    np.testing.assert_allclose(parse_vector(await service.set("velocity", "(1 0)")), [0.1, 0, 0, 0, 0, 0])


async def test_bad_velocity_commands_are_refused(service: LocalService, sim: SimRobot) -> None:
    for bad in ["(1)", "(1 2 3 4)", "fast", "((1 2) (3 4))"]:
        with pytest.raises(InvalidArgument):
            await service.set("velocity", bad)
    assert not np.any(sim.velocity)
    with pytest.raises(PropertyError) as info:
        await service.set("velocity.roll", "nan")
    assert info.value.code is Code.INVALID_ARGUMENT
    assert not np.any(sim.velocity)


async def test_one_element_set_is_a_command_too(service: LocalService, sim: SimRobot) -> None:
    # velocity.x is the whole command with vx changed: clipped and timed like any other.
    assert await service.set("velocity.x", "3") == "1"
    assert await service.get("velocity") == "(1 0 0 0 0 0)"
    assert await service.set("velocity.yaw", "-1") == "-0.5"
    assert await service.get("velocity") == "(1 0 0 0 0 -0.5)"


def test_robot_options_for_teleoperation_are_checked() -> None:
    robot = SimRobot()
    assert (robot.max_speed, robot.max_turn_rate, robot.velocity_timeout) == (
        1.0,
        2.0,
        DEFAULT_VELOCITY_TIMEOUT,
    )
    for bad in [{"max_speed": -1}, {"max_turn_rate": "fast"}, {"velocity_timeout": 0}]:
        with pytest.raises(InvalidArgument):
            SimRobot(**bad)  # type: ignore[arg-type]


async def test_the_command_is_integrated_into_location_in_the_world_frame(service: LocalService) -> None:
    sim = SimRobot(start=[1, 1, 0, 0, 0, math.pi / 2], velocity_timeout=10.0)
    robot = LocalService(sim)
    # Heading +y, yet vx moves it along the world's x axis, as moveto's velocity reads.
    await robot.set("velocity", "(0.5 0 0 0 0 0.25)")
    sim.advance(0.2)
    sim.advance(0.2)
    x, y, yaw = xy_yaw(sim)
    assert x == pytest.approx(1.2)
    assert y == pytest.approx(1.0)
    assert yaw == pytest.approx(math.pi / 2 + 0.1)
    # The heading wraps around like moveto's atan2 does: within (-pi, pi].
    await robot.set("velocity", "(0 0 0 0 0 2)")
    sim.advance(2.0)
    assert -math.pi <= sim.location[5] <= math.pi
    assert float(await robot.get("sensors.battery")) < 1.0  # driving costs charge


async def test_a_command_holds_only_while_it_is_renewed(service: LocalService, sim: SimRobot) -> None:
    heard: list[str] = []
    await service.listen("velocity", lambda change: heard.append(change.value))
    await service.set("velocity", "(1 0)")
    sim.advance(0.3)
    await service.set("velocity", "(1 0)")  # renewed: another 0.5 s from now
    sim.advance(0.3)
    assert sim.location[0] == pytest.approx(0.6)
    assert np.any(sim.velocity)
    sim.advance(1.0)  # not renewed: it drives the 0.2 s it has left, then stops by itself
    assert sim.location[0] == pytest.approx(0.8)
    assert await service.get("velocity") == "(0 0 0 0 0 0)"
    assert heard[-1] == "(0 0 0 0 0 0)"  # listeners see it stop
    assert await service.get("actuators.wheels") == "(0 0)"
    sim.advance(1.0)
    assert sim.location[0] == pytest.approx(0.8)


async def test_a_longer_timeout_applies_to_the_running_command(service: LocalService, sim: SimRobot) -> None:
    await service.set("velocity", "(1 0)")
    sim.advance(0.4)
    await service.set("velocity_timeout", "2")
    sim.advance(1.0)
    assert np.any(sim.velocity)
    sim.advance(5.0)
    assert sim.location[0] == pytest.approx(2.0)
    assert not np.any(sim.velocity)


async def test_moveto_cancels_a_velocity_command_and_the_reverse(
    service: LocalService, sim: SimRobot
) -> None:
    await service.set("velocity", "(1 0)")
    sim.advance(0.1)
    await service.set("behaviors.moveto", MOVETO_FAR)
    sim.advance(0.1)
    np.testing.assert_allclose(sim.location[:2], [0.1, 0.1], atol=1e-2)  # turned toward the target
    assert sim.location[1] > 0.09
    # Far longer than the command's timeout: moveto keeps driving, the command is gone.
    for _ in range(10):
        sim.advance(0.1)
    assert sim.location[1] > 1.0

    answer = await service.set("velocity", "(0 0 0 0 0 0.5)")  # turn in place
    assert answer == "(0 0 0 0 0 0.5)"
    where = sim.location[:3].copy()
    sim.advance(0.2)
    np.testing.assert_allclose(sim.location[:3], where)  # no longer driving toward the target
    sim.advance(1.0)
    assert not np.any(sim.velocity)
    sim.advance(1.0)
    np.testing.assert_allclose(sim.location[:3], where)  # and the dropped target does not come back


async def test_stop_and_a_zero_command_end_a_velocity_command(service: LocalService, sim: SimRobot) -> None:
    await service.set("velocity", "(1 0)")
    await service.set("behaviors.stop", "")
    assert await service.get("velocity") == "(0 0 0 0 0 0)"
    sim.advance(0.2)
    assert sim.location[0] == 0.0
    await service.set("velocity", "(1 0)")
    assert await service.set("velocity", "(0 0)") == "(0 0 0 0 0 0)"
    sim.advance(0.2)
    assert sim.location[0] == 0.0
    await service.set("behaviors.moveto", MOVETO_FAR)
    await service.set("velocity", "(0 0 0 0 0 0)")  # a zero command stops a moveto too
    sim.advance(0.2)
    assert sim.location[1] == 0.0


@pytest.fixture
async def running() -> AsyncIterator[tuple[SimRobot, LocalService]]:
    sim = SimRobot(max_speed=1.0, velocity_timeout=0.1, tick_hz=50.0)
    service = LocalService(sim)
    await service.start()
    yield sim, service
    await service.aclose()


async def test_the_robot_stops_by_itself_and_then_sends_nothing(
    running: tuple[SimRobot, LocalService],
) -> None:
    sim, service = running
    velocities: list[str] = []
    locations: list[Change] = []
    await service.listen("velocity", lambda change: velocities.append(change.value))
    await service.listen("location", locations.append)
    await service.set("velocity", "(1 0)")
    await wait_until(lambda: velocities[-1:] == ["(0 0 0 0 0 0)"], what="the robot stops by itself")
    # However late the loop ran, the command drove 0.1 s at 1 m/s and no more.
    assert 0.0 < sim.location[0] <= 0.1 + 1e-9
    assert locations
    heard = len(locations)
    for _ in range(10):  # several ticks' and timeouts' worth of idle time
        await asyncio.sleep(0.02)
    assert len(locations) == heard
    assert velocities[-1] == "(0 0 0 0 0 0)"


async def test_renewed_commands_keep_the_robot_moving(running: tuple[SimRobot, LocalService]) -> None:
    sim, service = running
    await service.set("velocity_timeout", "5")
    for _ in range(5):
        await service.set("velocity", "(0 1)")
        await asyncio.sleep(0.02)
    await wait_until(lambda: sim.location[1] > 0.05, what="the robot drives along y")
    assert np.any(sim.velocity)
    await service.set("behaviors.stop", "")
    assert not np.any(sim.velocity)

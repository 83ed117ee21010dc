"""A simulated robot's temperature sensor reads the world's temperature field where the robot is."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.apps.simulators import SimRobot
from services.apps.temperature_field import DEFAULT_FIELD, TemperatureField, WarmSpot
from services.kernel.core import LocalService
from services.kernel.errors import InvalidArgument, ReadOnly


def test_the_field_is_a_base_plus_gaussian_spots() -> None:
    field = TemperatureField(18.0, (WarmSpot(0.0, 0.0, 10.0, 1.0), WarmSpot(5.0, 0.0, -4.0, 2.0)))
    assert field.at(0.0, 0.0) == pytest.approx(18.0 + 10.0 + -4.0 * math.exp(-25 / 8))
    assert field.at(1.0, 0.0) == pytest.approx(18.0 + 10.0 * math.exp(-0.5) - 4.0 * math.exp(-16 / 8))
    assert field.at(100.0, 100.0) == pytest.approx(18.0)
    assert DEFAULT_FIELD.at(3.0, 2.0) == pytest.approx(28.0, abs=0.01)  # the demo's warm spot


def test_field_options_are_checked() -> None:
    assert TemperatureField.from_options(None) is DEFAULT_FIELD
    custom = TemperatureField.from_options({"base": 15, "spots": [[1, 2, 3, 0.5]]})
    assert custom == TemperatureField(15.0, (WarmSpot(1.0, 2.0, 3.0, 0.5),))
    assert TemperatureField.from_options({"base": 10}).spots == DEFAULT_FIELD.spots
    for bad, words in [
        ({"spots": [[1, 2, 3]]}, "spots\\[0\\] is \\[x, y, delta, radius\\]"),
        ({"spots": [[1, 2, 3, 0]]}, "positive radius"),
        ({"base": "warm"}, "base is a temperature"),
        ({"hot": 1}, "base and spots, not hot"),
    ]:
        with pytest.raises(InvalidArgument, match=words):
            TemperatureField.from_options(bad)


def test_a_robot_reads_the_field_where_it_drives_and_a_standing_one_reads_nothing_new() -> None:
    field = {"base": 20.0, "spots": [[2.0, 0.0, 10.0, 1.0]]}
    robot = SimRobot(start=(0.0, 0.0), speed=1.0, temperature=field, temperature_noise=0.0, temperature_hz=10)
    expected = TemperatureField.from_options(field)
    assert robot.sensors.temperature == pytest.approx(expected.at(0.0, 0.0), abs=0.005)
    robot.drive_to(np.array([2.0, 0.0]), "world")
    readings = []
    for _ in range(20):  # 2 s of driving at 10 ticks a second: a reading each tick
        robot.advance(0.1)
        readings.append(robot.sensors.temperature)
        assert robot.sensors.temperature == pytest.approx(
            expected.at(float(robot.location[0]), 0.0), abs=0.005
        )
    assert readings == sorted(readings) and readings[-1] == pytest.approx(30.0, abs=0.005)
    robot.advance(5.0)  # standing: no reading, nothing changes
    assert robot.sensors.temperature == readings[-1]


def test_readings_come_at_the_sensor_rate_with_seeded_noise() -> None:
    one = SimRobot(start=(0.0, 0.0), temperature_hz=2.0, temperature_noise=0.5, seed=7)
    two = SimRobot(start=(0.0, 0.0), temperature_hz=2.0, temperature_noise=0.5, seed=7)
    assert one.sensors.temperature == two.sensors.temperature  # the same seed, the same noise
    for robot in (one, two):
        robot.command_velocity([0.1, 0.0])
    first = one.sensors.temperature
    one.advance(0.3)  # less than 1 / 2 Hz driven: no reading yet
    assert one.sensors.temperature == first
    one.advance(0.3)
    assert one.sensors.temperature != first
    with pytest.raises(InvalidArgument, match="seed must be an integer"):
        SimRobot(seed="x")  # type: ignore[arg-type]
    with pytest.raises(InvalidArgument, match="temperature_hz"):
        SimRobot(temperature_hz=0.0)


async def test_the_sensor_is_a_read_only_property_in_degrees_celsius() -> None:
    robot = LocalService(SimRobot(start=(3.0, 2.0), temperature_noise=0.0))
    assert float(await robot.get("sensors.temperature")) == pytest.approx(28.0, abs=0.01)
    model = {p.name: p for p in (await robot.describe()).properties}
    assert (model["sensors.temperature"].unit, model["sensors.temperature"].type) == ("degC", "number")
    with pytest.raises(ReadOnly, match="read-only"):
        await robot.set("sensors.temperature", "5")

"""The environment model in a real gateway process: a swarm drives across the grid and fills it.

A ``psgateway serve`` process with two simulated robots (fast, their temperature sensors
reading at every tick), a swarm of them, and an ``environment`` service fed by the swarm's
locations and temperatures and by ``camera1``'s markers, a camera that is not there. The
robots drive along two rows of the grid; ``grid.temperature`` (read as bytes with the
generated stub, decoded with numpy) holds the world's temperature in the cells they crossed;
``grid.temperature.image`` is a PNG; a marker observed by hand appears on a ``markers.*``
Listen and expires after the ttl; a robot drives to the nearest red marker ``find`` names.
"""

from __future__ import annotations

import asyncio
import io
from typing import Any

import grpc
import numpy as np
import pytest
from PIL import Image
from support.waiting import eventually

from clients.aio import AsyncClient
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.apps.environment.observations import parse_marker_list
from services.apps.temperature_field import DEFAULT_FIELD
from services.kernel.values import parse_list, parse_marker

WAIT = 15.0
# Steps of at most 0.5 m (5 ticks of a late loop): no cell of 1 m is stepped over.
ROBOT = "speed = 5.0, tick_hz = 50, temperature_hz = 50, temperature_noise = 0.05"
CONFIG = f"""
[[services]]
name = "scout1"
type = "sim-robot"
options = {{ start = [0.5, 0.5], {ROBOT}, seed = 1 }}

[[services]]
name = "scout2"
type = "sim-robot"
options = {{ start = [0.5, 2.5], {ROBOT}, seed = 2 }}

[[services]]
name = "swarm"
type = "group"
options = {{ query = {{ type = "mobile_robot" }} }}

[[services]]
name = "environment"
type = "environment"
options = {{ robots = ["swarm"], markers = ["camera1"], ttl = 1.0, \
readings = [{{ selector = "swarm robots.*.sensors.temperature", layer = "temperature" }}], \
grid = {{ origin = [0, 0], cell = 1.0, shape = [4, 6] }} }}
"""


async def binary(stub: pb_grpc.PropertyServiceStub, prop: str) -> bytes:
    reply = await stub.Get(pb.GetRequest(service="environment", property=prop))
    assert reply.HasField("data") and reply.value == "", prop
    return reply.data


@pytest.mark.timeout(60)
async def test_robots_fill_the_temperature_grid_and_markers_come_and_go(gateway_process: Any) -> None:
    gw = gateway_process(CONFIG)
    async with (
        AsyncClient(gw.address, timeout=WAIT) as client,
        grpc.aio.insecure_channel(gw.address) as channel,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)

        def states(value: str) -> dict[str, str]:
            return {f"{s} {role}": state for s, role, _, state, _ in parse_list(value)}

        sources = await eventually(
            lambda: client.get("environment", "sources"),
            lambda v: all(
                state == "following" for key, state in states(v).items() if key.startswith("swarm ")
            ),
        )
        assert states(sources)["camera1 markers"] == "absent"  # not there: waited for, quietly

        # Both robots are markers of class mobile_robot, from their own reports.
        for name in ("scout1", "scout2"):
            marker = parse_marker(await eventually(lambda n=name: client.get("environment", f"markers.{n}")))
            assert marker.get("class") == "mobile_robot" and marker.get("source") == name

        # Drive along rows 0 and 2 of the grid, from x = 0.5 to x = 5.5: twelve cells.
        await client.set("scout1", "behaviors.moveto", "<marker><location>(5.5 0.5)</location></marker>")
        await client.set("scout2", "behaviors.moveto", "<marker><location>(5.5 2.5)</location></marker>")
        info = await eventually(
            lambda: client.get("environment", "grid.temperature.info"),
            lambda v: dict(parse_list(v))["filled"] == "12",
            within=WAIT,
        )
        assert dict(parse_list(info))["unit"] == "degC"
        grid = np.load(io.BytesIO(await binary(stub, "grid.temperature")), allow_pickle=False)
        assert grid.dtype == np.float32 and grid.shape == (4, 6)
        assert np.isfinite(grid[0]).all() and np.isfinite(grid[2]).all()
        assert np.isnan(grid[1]).all() and np.isnan(grid[3]).all()
        for row in (0, 2):
            for col in range(6):
                # Readings across the cell: within the field's change over a cell and the noise.
                x, y = col + 0.5, row + 0.5
                nearby = [DEFAULT_FIELD.at(x + dx, y) for dx in (-0.5, 0.0, 0.5)]
                assert min(nearby) - 0.3 <= grid[row, col] <= max(nearby) + 0.3, (row, col, grid[row, col])
        png = await binary(stub, "grid.temperature.image")
        image = Image.open(io.BytesIO(png))
        assert image.format == "PNG" and image.size[0] / image.size[1] == pytest.approx(6 / 4)

        # A marker seen by hand appears on a Listen, and expires after the ttl (1 s).
        events = client.listen("environment", "markers.*")
        try:
            box = "<marker><id>crate</id><class>box</class><location>(2 3)</location></marker>"
            assert await client.set("environment", "observe", box, source="tester") == "crate"
            async with asyncio.timeout(WAIT):
                event = await anext(events)
                while event.property != "markers.crate":
                    event = await anext(events)
                assert not event.removed and parse_marker(event.value).get("class") == "box"
                while not (event.property == "markers.crate" and event.removed):
                    event = await anext(events)
        finally:
            await events.aclose()
        # The robots, standing but followed, stay.
        assert sorted(await client.get_names("environment", "markers")) == ["scout1", "scout2"]
        found = await client.get(
            "environment", "find", **{"class": "mobile_robot", "near": "(5 3)", "count": "1"}
        )
        assert [m.get("id") for m in parse_marker_list(found)] == ["scout2"]

        # "Move to the nearest red marker": the marker find names is a target for moveto.
        for place, rgb in (("(1 3)", "(1 0 0)"), ("(4 3.5)", "(1 0 0)"), ("(5 1)", "(0 0 1)")):
            seen = f"<marker><class>cone</class><location>{place}</location><color>{rgb}</color></marker>"
            await client.set("environment", "observe", seen)
        found = await client.get("environment", "find", near="(5.5 0.5)", where="color=(1 0 0)", count="1")
        (target,) = parse_marker_list(found)
        assert target.get("location") == "(4 3.5 0)"
        await client.set("scout1", "behaviors.moveto", target.to_xml())
        await eventually(
            lambda: client.get_vector("scout1", "location"), lambda v: bool(np.allclose(v[:2], [4, 3.5]))
        )

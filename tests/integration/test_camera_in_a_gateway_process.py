"""A camera in a real gateway process: it sees the gateway's robots, and its frames travel as bytes."""

from __future__ import annotations

import asyncio
import io
from collections.abc import AsyncIterator

import grpc
import pytest
from PIL import Image
from support.gateway_process import StartGateway
from support.waiting import eventually

from clients import AsyncClient
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.values import parse_vector
from services.kernel.values.markers import parse_markers

WAIT = 10.0

CONFIG = """
    [[services]]
    name = "scout1"
    type = "sim-robot"
    options = { start = [3.0, 0.0], speed = 20.0 }

    [[services]]
    name = "scout2"
    type = "sim-robot"
    options = { start = [5.0, 1.0] }

    [[services]]
    name = "cam"
    type = "camera"
    [services.options]
    location = [0.0, 0.0, 1.2]
    fov = 60.0
    range = 10.0
    resolution = [320, 240]
    rate_hz = 10.0
    objects = [{ id = "crate", class = "box", location = [4.0, -1.0], colour = "red" }]
"""


def ids(text: str) -> list[str]:
    return [m.get("id") for m in parse_markers(text)]


@pytest.fixture
async def gateway(gateway_process: StartGateway) -> AsyncIterator[str]:
    yield gateway_process(CONFIG).address


async def test_markers_of_the_robots_seen_and_a_robot_driven_out_of_view(gateway: str) -> None:
    async with AsyncClient(gateway, timeout=WAIT) as client:
        text = await eventually(
            lambda: client.get("cam", "markers"), lambda t: {"scout1", "scout2"} <= set(ids(t))
        )
        assert ids(text) == ["scout1", "crate", "scout2"]  # nearest first
        scout1 = parse_markers(text)[0]
        assert scout1.get("class") == "mobile_robot"
        assert parse_vector(scout1.get("location")).tolist() == [3.0, 0.0, 0.0]
        local = parse_markers(await client.get("cam", "markers", frame="camera"))
        assert parse_vector(local[0].get("location")).tolist() == [3.0, 0.0, -1.2]
        assert await client.get("cam", "data") == "3"
        events = client.listen("cam", "markers")
        try:
            assert "scout1" in ids((await anext(events)).value)  # the current value first
            await client.set("scout1", "behaviors.moveto", "<marker><location>(3 -9)</location></marker>")
            async with asyncio.timeout(WAIT):
                async for event in events:
                    if "scout1" not in ids(event.value):
                        break
            assert ids(event.value) == ["crate", "scout2"]
        finally:
            await events.aclose()
        assert await client.get("cam", "data") == "2"


async def next_frames(call: grpc.aio.UnaryStreamCall, wanted: int) -> list[bytes]:
    frames: list[bytes] = []
    async with asyncio.timeout(WAIT):
        while len(frames) < wanted:
            message = await call.read()
            assert message is not grpc.aio.EOF
            frames += [e.data for e in message.events]
    return frames


async def test_a_frame_by_get_is_byte_for_byte_one_that_listen_delivered(gateway: str) -> None:
    async with grpc.aio.insecure_channel(gateway) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        model = await stub.Describe(pb.DescribeRequest(service="cam"), timeout=WAIT)
        (frame_info,) = [p for p in model.properties if p.name == "frame"]
        assert frame_info.type == "bytes" and frame_info.media_type == "image/jpeg"
        call = stub.Listen(pb.ListenRequest(service="cam", property="frame"))
        try:
            heard = await next_frames(call, 2)
            reply = await stub.Get(pb.GetRequest(service="cam", property="frame"), timeout=WAIT)
            assert reply.HasField("data") and reply.value == ""  # an old client sees "" (Describe says why)
            # The Get answers the latest frame: one Listen delivered already, or is about to.
            heard += await next_frames(call, 1)
            assert reply.data in heard
            assert len(set(heard)) == len(heard)  # consecutive frames differ
        finally:
            call.cancel()
        image = Image.open(io.BytesIO(reply.data))
        assert image.format == "JPEG" and image.size == (320, 240)


async def test_the_sdk_gets_and_listens_to_frames_as_bytes(gateway: str) -> None:
    async with AsyncClient(gateway, timeout=WAIT) as client:
        events = client.listen("cam", "frame")
        try:
            heard = [(await anext(events)).value, (await anext(events)).value]
            frame = await client.get_bytes("cam", "frame")
            heard.append((await anext(events)).value)
        finally:
            await events.aclose()
        assert all(isinstance(v, bytes) for v in heard)
        assert frame in heard
        assert Image.open(io.BytesIO(frame)).size == (320, 240)

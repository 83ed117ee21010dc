"""The Foxglove endpoint of a real gateway process, driven message by message with aiohttp's
WebSocket client: refusals, bad input answered without losing the connection, camera frames as
``foxglove.CompressedImage``, bounded places, and a slow reader held to the latest frame.

Foxglove's own client runs against it in ``tests/interop/test_foxglove_client.py``.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import psutil
import pytest
from support.blobs import BLOBS_CONFIG, start_blobs
from support.gateway_process import GatewayProcess, StartGateway

SUBPROTOCOL = "foxglove.websocket.v1"
WAIT = 10.0
ROBOT = """
[[services]]
name = "bot"
type = "sim-robot"
"""
MESSAGE_HEAD = struct.Struct("<BIQ")


class Client:
    """A Foxglove connection read message by message: JSON ones as dicts, binary ones as bytes."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}
        self.services: dict[str, dict[str, Any]] = {}

    async def receive(self) -> dict[str, Any] | bytes:
        message = await asyncio.wait_for(self.ws.receive(), WAIT)
        if message.type is aiohttp.WSMsgType.BINARY:
            data: bytes = message.data
            return data
        assert message.type is aiohttp.WSMsgType.TEXT, message
        body: dict[str, Any] = json.loads(message.data)
        return body

    async def json(self, op: str) -> dict[str, Any]:
        """The next JSON message of ``op`` (messages on channels are passed over)."""
        while True:
            message = await self.receive()
            if isinstance(message, dict) and message["op"] == op:
                return message

    async def message(self, subscription: int) -> tuple[int, dict[str, Any]]:
        """The next message on ``subscription``: its time and its JSON body."""
        while True:
            message = await self.receive()
            if isinstance(message, bytes):
                op, sub, stamp = MESSAGE_HEAD.unpack_from(message)
                assert op == 1
                if sub == subscription:
                    return stamp, json.loads(message[MESSAGE_HEAD.size :])

    async def send(self, body: dict[str, Any]) -> None:
        await self.ws.send_str(json.dumps(body))

    async def subscribe(self, subscription: int, topic: str) -> None:
        channel = self.channels[topic]["id"]
        await self.send({"op": "subscribe", "subscriptions": [{"id": subscription, "channelId": channel}]})


async def connect(session: aiohttp.ClientSession, gw: GatewayProcess, path: str = "foxglove") -> Client:
    ws = await session.ws_connect(f"{gw.http_url}{path}", protocols=[SUBPROTOCOL])
    client = Client(ws)
    assert (await client.json("serverInfo"))["name"] == "psgateway"
    client.channels = {c["topic"]: c for c in (await client.json("advertise"))["channels"]}
    client.services = {s["name"]: s for s in (await client.json("advertiseServices"))["services"]}
    return client


@pytest.fixture
async def session() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


async def test_a_websocket_that_offers_no_foxglove_subprotocol_is_refused_saying_which(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT)
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await session.ws_connect(f"{gw.http_url}foxglove", protocols=["something.else"])
    assert refused.value.status == 400
    async with session.get(f"{gw.http_url}foxglove", headers={"Upgrade": "websocket"}) as answer:
        body = await answer.json()
    assert "foxglove.websocket.v1 or foxglove.sdk.v1" in body["error"]["message"]
    # The root path without an upgrade is still the console.
    async with session.get(gw.http_url) as root:
        assert root.status == 200
        assert "<html" in (await root.text()).lower()


async def test_bad_messages_get_error_statuses_and_the_connection_goes_on(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT)
    client = await connect(session, gw)
    bad: list[tuple[str | bytes, str]] = [
        ("not json", "a text message must be a JSON object"),
        ('{"op": "dance"}', "unknown op 'dance'"),
        ('{"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 99999}]}', "no channel 99999"),
        ('{"op": "subscribe", "subscriptions": [{"id": -1, "channelId": 1}]}', "subscription id must be"),
        ('{"op": "subscribeConnectionGraph"}', "is not supported"),
        (b"\x07", "unknown binary opcode 0x07"),
        (b"\x01\x05\x00\x00\x00{}", "no client channel 5: advertise it first"),
        (
            '{"op": "advertise", "channels": [{"id": 1, "topic": "/bot/nowhere", "encoding": "json",'
            ' "schemaName": ""}]}',
            "no property at topic '/bot/nowhere'",
        ),
        (
            '{"op": "advertise", "channels": [{"id": 1, "topic": "/bot/sensors/battery", "encoding": "json",'
            ' "schemaName": ""}]}',
            "/bot/sensors/battery is not writable (read)",
        ),
    ]
    for frame, expected in bad:
        if isinstance(frame, bytes):
            await client.ws.send_bytes(frame)
        else:
            await client.ws.send_str(frame)
        status = await client.json("status")
        assert status["level"] == 2
        assert expected in status["message"], status

    # A publish whose value does not parse is refused by the service, named as INVALID_ARGUMENT.
    await client.send(
        {
            "op": "advertise",
            "channels": [{"id": 3, "topic": "/bot/speed", "encoding": "json", "schemaName": ""}],
        }
    )
    await client.ws.send_bytes(b"\x01\x03\x00\x00\x00" + json.dumps({"value": "fast"}).encode())
    status = await client.json("status")
    assert status["message"].startswith("publish /bot/speed: INVALID_ARGUMENT"), status

    # Still serving: a subscription's current value, then a published one.
    await client.subscribe(4, "/bot/speed")
    assert (await client.message(4))[1] == {"value": 0.5}
    await client.ws.send_bytes(b"\x01\x03\x00\x00\x00" + json.dumps({"value": 0.25}).encode())
    assert (await client.message(4))[1] == {"value": 0.25}
    await client.ws.close()
    gw.stop()


async def test_service_calls_run_actions_and_queries_and_failures_name_the_code(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT)
    client = await connect(session, gw, path="")

    def call(name: str, call_id: int, body: dict[str, Any], encoding: str = "json") -> bytes:
        service = client.services[name]["id"]
        return (
            struct.pack("<BIII", 2, service, call_id, len(encoding))
            + encoding.encode()
            + json.dumps(body).encode()
        )

    await client.subscribe(1, "/bot/pose")
    await client.message(1)  # where it stands
    marker = "<marker><location>(0.3 0 0 0 0 0)</location></marker>"
    await client.ws.send_bytes(call("/bot/behaviors/moveto", 7, {"value": marker}))
    response = await client.receive()
    assert isinstance(response, bytes) and response[0] == 3
    _, service, call_id, length = struct.unpack_from("<BIII", response)
    assert (service, call_id) == (client.services["/bot/behaviors/moveto"]["id"], 7)
    assert response[13 : 13 + length] == b"json"
    assert json.loads(response[13 + length :]) == {"value": ""}
    # The robot drives there: its pose follows.
    deadline = time.monotonic() + WAIT
    while True:
        _, pose = await client.message(1)
        if pose["pose"]["position"]["x"] == pytest.approx(0.3):
            break
        assert time.monotonic() < deadline, pose

    await client.ws.send_bytes(call("/registry/service_names", 8, {"parameters": {"limit": 1}}))
    response = await client.receive()
    assert isinstance(response, bytes) and response[0] == 3
    assert json.loads(response[17:]) == {"value": "(bot)"}

    await client.ws.send_bytes(call("/bot/behaviors/moveto", 9, {"value": "<marker/>"}))
    failure = await client.json("serviceCallFailure")
    assert failure["callId"] == 9
    assert "INVALID_ARGUMENT" in failure["message"]
    await client.ws.send_bytes(call("/bot/behaviors/stop", 10, {}, encoding="cdr"))
    failure = await client.json("serviceCallFailure")
    assert failure["callId"] == 10 and "json" in failure["message"]
    await client.ws.close()
    gw.stop()


async def test_camera_frames_arrive_as_compressed_images(
    tmp_path: Path, session: aiohttp.ClientSession
) -> None:
    gw = start_blobs(tmp_path, BLOBS_CONFIG, *BLOBS_HTTP)
    try:
        client = await connect(session, gw)
        channel = client.channels["/blobs/frame"]
        assert channel["schemaName"] == "foxglove.CompressedImage"
        await set_values(client, {"frame_bytes": 1000, "rate_hz": 20, "stream": True})
        await client.subscribe(1, "/blobs/frame")
        while True:
            _, image = await client.message(1)
            data = base64.b64decode(image["data"])
            if data:
                break
        assert image["format"] == "jpeg"
        assert len(data) == 1000
        await set_values(client, {"stream": False})
        await client.ws.close()
    finally:
        gw.stop()


BLOBS_HTTP = ("--http", "127.0.0.1:0")


async def set_values(client: Client, values: dict[str, Any]) -> None:
    """Set parameters and wait for their values."""
    parameters = [{"name": f"/blobs/{name}", "value": value} for name, value in values.items()]
    await client.send({"op": "setParameters", "parameters": parameters, "id": "set"})
    answer = await client.json("parameterValues")
    assert {p["name"] for p in answer["parameters"]} == {p["name"] for p in parameters}, answer


async def test_a_slow_foxglove_reader_gets_the_latest_frame_and_the_gateway_stays_flat(
    tmp_path: Path, session: aiohttp.ClientSession
) -> None:
    """100 KB frames at 25 a second and a reader that stops reading for 6 s: the gateway does not
    queue the 15 MB it missed, and the reader's next frames are fresh."""
    gw = start_blobs(tmp_path, BLOBS_CONFIG, *BLOBS_HTTP)
    gateway = psutil.Process(gw.proc.pid)
    try:
        client = await connect(session, gw)
        await set_values(client, {"frame_bytes": 100_000, "rate_hz": 25, "stream": True})
        await client.subscribe(1, "/blobs/frame")
        loop = asyncio.get_running_loop()
        until = loop.time() + 2.0
        while loop.time() < until:
            await client.message(1)
        before = gateway.memory_info().rss
        await asyncio.sleep(6.0)  # the reader stops: 150 frames go by
        stalled = gateway.memory_info().rss
        read_again = time.time_ns()
        frames = 0
        while True:
            stamp, _ = await client.message(1)
            frames += 1
            if stamp >= read_again:
                break
        await set_values(client, {"stream": False})
        await client.ws.close()
    finally:
        gw.stop()
    growth = stalled - before
    print(
        f"rss before {before / 1e6:.1f} MB, after stall {stalled / 1e6:.1f} MB;"
        f" {frames} frames to a fresh one"
    )
    assert frames < 100, f"{frames} stale frames were kept for the slow reader"
    assert growth < 25 * 1024 * 1024, f"the gateway grew by {growth / 1e6:.1f} MB while the reader stalled"


async def test_foxglove_connections_take_the_http_fronts_stream_places(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT + "\n[http]\nmax_streams_per_client = 2\n")
    first = await connect(session, gw)
    second = await connect(session, gw, path="")
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await session.ws_connect(f"{gw.http_url}foxglove", protocols=[SUBPROTOCOL])
    assert refused.value.status == 429
    await first.ws.close()
    # Its place is free again once it has gone.
    deadline = time.monotonic() + WAIT
    while True:
        try:
            third = await connect(session, gw)
            break
        except aiohttp.WSServerHandshakeError:
            assert time.monotonic() < deadline
            await asyncio.sleep(0.1)
    await second.ws.close()
    await third.ws.close()
    gw.stop()


async def test_a_service_that_joins_is_advertised_and_unadvertised_when_it_leaves(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT)
    elsewhere = gateway_process(ROBOT.replace('"bot"', '"rover"'))
    client = await connect(session, gw)
    assert "/rover/speed" not in client.channels

    async def register(url: str) -> None:
        async with session.put(
            f"{gw.http_url}api/v1/services/registry/properties/services.rover", json={"value": url}
        ) as answer:
            assert answer.status == 200, await answer.text()

    await register(f"grpc://{elsewhere.address}")  # rover joins, served by another gateway
    channels = {c["topic"]: c for c in (await client.json("advertise"))["channels"]}
    assert channels["/rover/speed"]["schemaName"] == "propertyservice.Number"
    assert "/bot/speed" not in channels  # only what is new
    services = {s["name"]: s for s in (await client.json("advertiseServices"))["services"]}
    assert "/rover/behaviors/moveto" in services
    client.channels.update(channels)
    await client.subscribe(1, "/rover/speed")
    assert (await client.message(1))[1] == {"value": 0.5}

    await register("")  # and leaves
    gone = await client.json("unadvertise")
    assert set(gone["channelIds"]) == {c["id"] for t, c in channels.items() if t.startswith("/rover/")}
    unoffered = await client.json("unadvertiseServices")
    assert set(unoffered["serviceIds"]) == {s["id"] for s in services.values()}
    # The rest goes on.
    await client.subscribe(2, "/bot/speed")
    assert (await client.message(2))[1] == {"value": 0.5}
    await client.ws.close()
    gw.stop()
    elsewhere.stop()


async def test_a_page_of_another_origin_opens_the_socket_only_when_the_config_names_its_origin(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    foxglove_app = {"Origin": "https://app.foxglove.dev"}
    gw = gateway_process(ROBOT)
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await session.ws_connect(f"{gw.http_url}foxglove", protocols=[SUBPROTOCOL], headers=foxglove_app)
    assert refused.value.status == 403
    gw.stop()

    allowed = gateway_process(ROBOT + '\n[http]\nwebsocket_origins = ["https://app.foxglove.dev"]\n')
    ws = await session.ws_connect(f"{allowed.http_url}", protocols=[SUBPROTOCOL], headers=foxglove_app)
    assert json.loads((await ws.receive()).data)["op"] == "serverInfo"
    await ws.close()
    # The origin opens the WebSocket, not the JSON routes.
    async with session.get(f"{allowed.http_url}api/v1/services", headers=foxglove_app) as answer:
        assert answer.status == 403
    allowed.stop()


async def test_a_client_that_answers_no_ping_is_closed_and_gives_its_place_back(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT + "\n[http]\nheartbeat = 0.5\nmax_streams_per_client = 1\n")
    ws = await session.ws_connect(f"{gw.http_url}foxglove", protocols=[SUBPROTOCOL], autoping=False)
    kinds = []
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        message = await asyncio.wait_for(ws.receive(), WAIT)
        kinds.append(message.type)
        if message.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING):
            break
    assert aiohttp.WSMsgType.PING in kinds
    assert kinds[-1] in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING), kinds
    await ws.close()
    # The one place this address has is free again.
    deadline = time.monotonic() + WAIT
    while True:
        try:
            client = await connect(session, gw)
            break
        except aiohttp.WSServerHandshakeError:
            assert time.monotonic() < deadline
            await asyncio.sleep(0.1)
    await client.ws.close()
    gw.stop()


async def test_parameters_are_read_written_and_followed_as_properties(
    gateway_process: StartGateway, session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT)
    client = await connect(session, gw)
    await client.send({"op": "getParameters", "parameterNames": [], "id": "all"})
    every = await client.json("parameterValues")
    assert every["id"] == "all"
    values = {p["name"]: p["value"] for p in every["parameters"]}
    assert values["/bot/speed"] == 0.5
    assert values["/bot/actuators/led"] is False
    assert "/bot/location" not in values  # read-only, and no scalar

    await client.send({"op": "subscribeParameterUpdates", "parameterNames": ["/bot/speed"]})
    update = await client.json("parameterValues")
    assert update == {"op": "parameterValues", "parameters": [{"name": "/bot/speed", "value": 0.5}]}
    await client.send({"op": "setParameters", "parameters": [{"name": "/bot/speed", "value": 0.25}]})
    update = await client.json("parameterValues")
    assert update["parameters"] == [{"name": "/bot/speed", "value": 0.25}]

    await client.send({"op": "unsubscribeParameterUpdates", "parameterNames": ["/bot/speed"]})
    await client.send(
        {"op": "setParameters", "parameters": [{"name": "/bot/speed", "value": 0.75}], "id": "s"}
    )
    answer = await client.json("parameterValues")
    assert answer == {
        "op": "parameterValues",
        "parameters": [{"name": "/bot/speed", "value": 0.75}],
        "id": "s",
    }
    await client.send({"op": "setParameters", "parameters": [{"name": "/bot/speed", "value": "fast"}]})
    status = await client.json("status")
    assert status["message"].startswith("set parameter /bot/speed: INVALID_ARGUMENT"), status
    await client.ws.close()
    gw.stop()

"""The rosbridge endpoint speaks the protocol as rosbridge does, to a plain WebSocket client of a
real gateway process: fragments that join into the message, ``status`` errors for what it cannot
do (naming the op and id, the connection going on), rules refusing subscribe and publish, the
bearer token refused before the upgrade, a bad ``auth`` op ending the connection."""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiohttp
import jwt
import pytest
from support.gateway_process import GatewayProcess

WAIT = 10.0
SECRET = "a shared secret of the lab, long enough for HS256"
ROBOT = """
[[services]]
name = "scout1"
type = "sim-robot"
"""
RULES = """
[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[rules]]
subject = "*"
service = "scout1"
operations = ["read"]
effect = "permit"

[[rules]]
subject = "*"
service = "scout1"
path = "sensors.**"
operations = ["read"]
effect = "deny"
"""


def token(subject: str) -> str:
    return jwt.encode(
        {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}, SECRET, algorithm="HS256"
    )


@pytest.fixture
def robot(gateway_process: Callable[[str], GatewayProcess]) -> GatewayProcess:
    return gateway_process(ROBOT)


@pytest.fixture
def secured(gateway_process: Callable[[str], GatewayProcess], tmp_path: Path) -> GatewayProcess:
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(ROBOT + RULES)


@pytest.fixture
async def session() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as client:
        yield client


async def next_of(ws: aiohttp.ClientWebSocketResponse, op: str) -> dict[str, Any]:
    """The next message of ``op`` (publish messages of earlier subscriptions are passed over)."""
    while True:
        message = await ws.receive_json(timeout=WAIT)
        if message["op"] == op:
            return message


async def test_a_large_message_comes_in_fragments_that_join_into_it(
    robot: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    async with session.ws_connect(f"ws://{robot.http_address}/rosbridge") as ws:
        await ws.send_json({"op": "call_service", "id": "whole", "service": "/rosapi/topics"})
        whole = await next_of(ws, "service_response")
        await ws.send_json(
            {"op": "call_service", "id": "split", "service": "/rosapi/topics", "fragment_size": 300}
        )
        pieces = []
        while not pieces or len(pieces) < pieces[0]["total"]:
            piece = await next_of(ws, "fragment")
            assert piece["id"] == "split" and piece["num"] == len(pieces)
            assert len(piece["data"]) <= 300
            pieces.append(piece)
        joined = json.loads("".join(piece["data"] for piece in pieces))
    assert len(pieces) > 3
    assert joined == {**whole, "id": "split"}


async def test_what_cannot_be_done_is_a_status_error_and_the_connection_goes_on(
    robot: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    async with session.ws_connect(f"ws://{robot.http_address}/rosbridge") as ws:
        cases = [
            ("not json", "the message is not JSON", None),
            ([1, 2], "a message must be a JSON object", None),
            ({"op": "dance", "id": "d1"}, "unknown op 'dance'", "d1"),
            ({"op": "subscribe", "id": "s1"}, "subscribe: 'topic' must be a non-empty string", "s1"),
            ({"op": "subscribe", "id": "s2", "topic": "location"}, "must be /SERVICE/PATH", "s2"),
            ({"op": "subscribe", "id": "s3", "topic": "/scout1/nothing"}, "NOT_FOUND", "s3"),
            ({"op": "subscribe", "id": "s4", "topic": "/nobody/location"}, "NOT_FOUND", "s4"),
            (
                {"op": "subscribe", "id": "s5", "topic": "/scout1/location", "compression": "cbor"},
                "cbor",
                "s5",
            ),
            (
                {"op": "subscribe", "id": "s6", "topic": "/scout1/speed", "type": "std_msgs/Bool"},
                "Float64",
                "s6",
            ),
            (
                {"op": "subscribe", "id": "s7", "topic": "/scout1/behaviors/stop"},
                "call it as a service",
                "s7",
            ),
            (
                {"op": "subscribe", "id": "s8", "topic": "/scout1/speed", "throttle_rate": -1},
                "at least 0",
                "s8",
            ),
            (
                {"op": "publish", "id": "p1", "topic": "/scout1/speed", "msg": {"data": "fast"}},
                "finite number",
                "p1",
            ),
            (
                {"op": "publish", "id": "p2", "topic": "/scout1/speed", "msg": {"data": -1}},
                "INVALID_ARGUMENT",
                "p2",
            ),
            (
                {"op": "publish", "id": "p3", "topic": "/scout1/location", "msg": {"data": []}},
                "location",
                "p3",
            ),
            ({"op": "publish", "id": "p4", "topic": "/scout1/cmd_vel", "msg": {"linear": 1}}, "linear", "p4"),
            ({"op": "set_level", "id": "l1", "level": "loud"}, "level must be one of", "l1"),
        ]
        for sent, expected, ident in cases:
            await ws.send_str(sent if isinstance(sent, str) else json.dumps(sent))
            status = await next_of(ws, "status")
            assert status["level"] == "error"
            assert expected in status["msg"], (sent, status)
            assert status.get("id") == ident
        await ws.send_bytes(b"\x00\x01")
        assert "not JSON" in (await next_of(ws, "status"))["msg"]
        # Still serving: a call answers.
        await ws.send_json({"op": "call_service", "id": "c", "service": "/scout1/speed"})
        assert (await next_of(ws, "service_response"))["values"]["data"] == 0.5


async def test_unsubscribe_ends_the_messages_of_a_topic(
    robot: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    async with session.ws_connect(f"ws://{robot.http_address}/rosbridge") as ws:
        await ws.send_json({"op": "subscribe", "id": "a", "topic": "/scout1/speed"})
        assert (await next_of(ws, "publish"))["msg"] == {"data": 0.5}
        await ws.send_json({"op": "unsubscribe", "id": "a", "topic": "/scout1/speed"})
        await ws.send_json({"op": "publish", "topic": "/scout1/speed", "msg": {"data": 0.75}})
        await ws.send_json({"op": "call_service", "id": "c", "service": "/scout1/speed"})
        # The Set is done before the call answers; no publish of it came first.
        message = await ws.receive_json(timeout=WAIT)
        assert message["op"] == "service_response" and message["values"]["data"] == 0.75


async def test_the_rules_refuse_a_subscribe_and_a_publish_with_the_code_and_the_rule(
    secured: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    async with session.ws_connect(f"ws://{secured.http_address}/rosbridge") as ws:
        await ws.send_json({"op": "subscribe", "id": "b", "topic": "/scout1/sensors/battery"})
        refused = await next_of(ws, "status")
        assert refused["id"] == "b"
        assert "read scout1/sensors.battery" in refused["msg"]
        assert "refused by rules[1] (deny * read scout1/sensors.**)" in refused["msg"]
        await ws.send_json({"op": "publish", "id": "p", "topic": "/scout1/speed", "msg": {"data": 0.1}})
        refused = await next_of(ws, "status")
        assert refused["id"] == "p" and refused["msg"].startswith("publish /scout1/speed: ")
        assert "UNAUTHENTICATED" in refused["msg"] or "PERMISSION_DENIED" in refused["msg"]
        await ws.send_json({"op": "subscribe", "id": "l", "topic": "/scout1/location"})
        assert (await next_of(ws, "publish"))["topic"] == "/scout1/location"


async def test_a_bad_bearer_token_is_refused_before_the_upgrade(
    secured: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    url = f"ws://{secured.http_address}/rosbridge"
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await session.ws_connect(url, headers={"Authorization": "Bearer not-a-token"})
    assert refused.value.status == 401
    session.cookie_jar.update_cookies({"ps_token": token("viewer")})
    async with session.ws_connect(url) as ws:  # the console's cookie names the caller too
        await ws.send_json({"op": "call_service", "id": "c", "service": "/scout1/speed"})
        assert (await next_of(ws, "service_response"))["result"] is True


async def test_a_bad_auth_op_ends_the_connection_saying_why(
    secured: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    async with session.ws_connect(f"ws://{secured.http_address}/rosbridge") as ws:
        await ws.send_json({"op": "auth", "mac": "not-a-token", "client": "", "dest": "", "rand": "", "t": 0})
        status = await next_of(ws, "status")
        assert "UNAUTHENTICATED" in status["msg"]
        closing = await ws.receive(timeout=WAIT)
        assert closing.type == aiohttp.WSMsgType.CLOSE
        assert closing.data == aiohttp.WSCloseCode.POLICY_VIOLATION
        assert "auth refused" in closing.extra


async def test_a_page_of_another_origin_and_a_plain_get_are_refused(
    robot: GatewayProcess, session: aiohttp.ClientSession
) -> None:
    url = f"ws://{robot.http_address}/rosbridge"
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await session.ws_connect(url, origin="http://evil.example")
    assert refused.value.status == 403
    async with session.get(f"http://{robot.http_address}/rosbridge") as plain:
        assert plain.status == 400
        assert "speaks WebSocket only" in (await plain.json())["error"]["message"]


async def test_a_page_of_an_origin_named_in_websocket_origins_may_open_rosbridge(
    gateway_process: Callable[[str], GatewayProcess], session: aiohttp.ClientSession
) -> None:
    gw = gateway_process(ROBOT + '[http]\nwebsocket_origins = ["http://teleop.example"]\n')
    url = f"ws://{gw.http_address}/rosbridge"
    async with session.ws_connect(url, origin="http://teleop.example") as ws:
        await ws.send_json({"op": "call_service", "id": "c", "service": "/scout1/speed"})
        assert (await next_of(ws, "service_response"))["result"] is True
    # Its pages still may not use the JSON routes, nor may another origin's open the socket.
    async with session.get(
        f"http://{gw.http_address}/api/v1/health", headers={"Origin": "http://teleop.example"}
    ) as r:
        assert r.status == 403
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        await session.ws_connect(url, origin="http://evil.example")
    assert refused.value.status == 403

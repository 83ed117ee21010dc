"""The gateway's raw-TCP line listener: in process over a real socket, and in a real gateway process."""

from __future__ import annotations

import asyncio

import grpc
import pytest
from line_device_support import LineClient, tcp_device
from support.ports import free_port

from gateway.engine.router import Router
from gateway.fronts.line.listener import LineListener
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.apps.catalog import create
from services.kernel.core import LocalService


async def test_a_microcontroller_reaches_every_service_through_the_listener() -> None:
    router = Router()
    bot = LocalService(create("sim-robot"))
    await bot.start()
    router.add("bot", bot)
    listener = LineListener(router)
    host, port = await listener.start("127.0.0.1", 0)
    try:
        c = await LineClient.tcp(host, port)
        assert await c.line() == "HELLO 1 name=gateway type=gateway push=1 maxline=1024"
        await c.send("get properties", "#1 GET bot.speed", "#2 SET bot.speed 1.5")
        assert await c.lines(3) == ["OK (bot)", "#1 OK 0.5", "#2 OK 1.5"]
        await c.send("#3 LISTEN bot.speed")
        assert await c.line() == "#3 OK 1.5"
        await bot.set("speed", "2")
        assert await c.line() == "EVENT bot.speed 2"
        await c.send("#4 LISTEN properties")
        assert await c.line() == "#4 OK (bot)"
        other = LocalService(create("sim-sensor"))
        router.add("light1", other)
        assert await c.line() == "EVENT properties (bot light1)"
        await c.send(
            "#5 GET nobody.x", "#6 GET bot.", "#7 GET bot.nosuch", "#8 SET properties x", "#9 GET bot"
        )
        replies = sorted(await c.replies(5))
        assert replies[0].startswith("#5 ERR 5 unknown service 'nobody'")
        assert replies[1].startswith("#6 ERR 3 ")
        assert replies[2].startswith("#7 ERR 5 ")
        assert replies[3].startswith("#8 ERR 9 ")
        # A service's name alone reads as a namespace: the names of its properties.
        assert replies[4].startswith("#9 OK (") and " speed " in replies[4]
        await c.close()
        await other.aclose()
    finally:
        await listener.aclose()
        await bot.aclose()


async def test_real_gateway_proxies_a_tcp_device_and_speaks_lines(gateway_process) -> None:  # type: ignore[no-untyped-def]
    line_port = free_port()
    with tcp_device("--service", "sim-robot", "--name", "wifi-bot") as (host, port):
        gw = gateway_process(f"""
            [gateway]
            line_listen = "127.0.0.1:{line_port}"

            [[services]]
            name = "wifibot"
            url = "tcp://{host}:{port}"
            options = {{ timeout = 2.0 }}
        """)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            for _ in range(100):  # the proxy connects in the background
                try:
                    reply = await stub.Get(pb.GetRequest(service="wifibot", property="speed"))
                    break
                except grpc.aio.AioRpcError as exc:
                    assert exc.code() == grpc.StatusCode.UNAVAILABLE, exc
                    await asyncio.sleep(0.1)
            assert reply.value == "0.5"
            await stub.Set(pb.SetRequest(service="wifibot", property="speed", value="1.25"))
            with pytest.raises(grpc.aio.AioRpcError) as missing:
                await stub.Get(pb.GetRequest(service="wifibot", property="nosuch"))
            assert missing.value.code() == grpc.StatusCode.NOT_FOUND
        c = await LineClient.tcp("127.0.0.1", line_port)
        assert "name=gateway" in await c.line()
        await c.send("#1 GET wifibot.speed")
        assert await c.line() == "#1 OK 1.25"
        await c.close()

"""The registry and the demo's swarm as a user meets them through a real gateway process."""

from __future__ import annotations

import asyncio

import grpc
from support.gateway_process import GatewayProcess

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 15.0


async def get(stub: pb_grpc.PropertyServiceStub, service: str, prop: str) -> str:
    reply = await stub.Get(pb.GetRequest(service=service, property=prop), timeout=WAIT)
    return str(reply.value)


async def eventually(stub: pb_grpc.PropertyServiceStub, service: str, prop: str, want: str) -> str:
    """The value of ``service``/``prop`` once it equals ``want``, or the last one after WAIT seconds."""
    value = ""
    for _ in range(int(WAIT / 0.1)):
        value = await get(stub, service, prop)
        if value == want:
            break
        await asyncio.sleep(0.1)
    return value


async def test_demo_devices_are_mobile_robots_in_the_swarm(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # The rovers greet with type=mobile_robot; the registry learns it from the greeting.
        for rover in ("rover1", "rover2"):
            assert await eventually(stub, "registry", f"services.{rover}.type", "mobile_robot") == (
                "mobile_robot"
            )
        robots = await eventually(stub, "swarm", "robots", "(scout1 scout2 rover1 rover2)")
        assert sorted(robots.strip("()").split()) == ["rover1", "rover2", "scout1", "scout2"]
        reply = await stub.Get(
            pb.GetRequest(service="registry", property="find", parameters={"type": "mobile_robot"}),
            timeout=WAIT,
        )
        assert reply.value == "(rover1 rover2 scout1 scout2)"

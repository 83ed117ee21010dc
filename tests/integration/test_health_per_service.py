"""gRPC health per Property Service, through a real gateway process and a device process on TCP.

A probe asks for one device by its service name: SERVING while it is up, NOT_SERVING once the
registry marks it down, SERVING again when it is back; a name nobody serves is NOT_FOUND (Check)
or SERVICE_UNKNOWN (Watch), as the health protocol says. The empty name stays the whole gateway.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
from line_device_support import device_process, tcp_device
from support.gateway_process import StartGateway
from support.waiting import WAIT

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

SERVING = health_pb2.HealthCheckResponse.SERVING
NOT_SERVING = health_pb2.HealthCheckResponse.NOT_SERVING
SERVICE_UNKNOWN = health_pb2.HealthCheckResponse.SERVICE_UNKNOWN

#: Quick liveness checks: a device that stops answering is down within a second.
QUICK_CHECKS = """
    [registry]
    period = 0.2
    timeout = 0.5
    misses = 1
"""


def config(port: int) -> str:
    return f"""
        {QUICK_CHECKS}
        [[services]]
        name = "rover"
        url = "tcp://127.0.0.1:{port}"
    """


async def check(channel: grpc.aio.Channel, name: str) -> int:
    reply = await health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=name))
    return int(reply.status)


async def next_status(statuses: AsyncIterator[health_pb2.HealthCheckResponse]) -> int:
    async with asyncio.timeout(WAIT):
        return int((await anext(statuses)).status)


async def test_a_device_that_goes_down_and_comes_back(gateway_process: StartGateway) -> None:
    with contextlib.ExitStack() as device:
        _, port = device.enter_context(tcp_device("--service", "sim-robot", "--name", "rover"))
        gw = gateway_process(config(port))
        async with grpc.aio.insecure_channel(gw.address) as channel:
            watch = health_pb2_grpc.HealthStub(channel).Watch(health_pb2.HealthCheckRequest(service="rover"))
            statuses = aiter(watch)
            # NOT_SERVING while the registry has not reached it yet ("connecting"), then SERVING.
            if await next_status(statuses) == NOT_SERVING:
                assert await next_status(statuses) == SERVING
            assert await check(channel, "rover") == SERVING
            assert await check(channel, "registry") == SERVING
            assert await check(channel, "") == SERVING

            device.close()  # the device process ends: the registry marks it down
            assert await next_status(statuses) == NOT_SERVING
            assert await check(channel, "rover") == NOT_SERVING
            assert await check(channel, "") == SERVING  # the gateway itself still serves

            again = ("--service", "sim-robot", "--name", "rover", "--tcp", f"127.0.0.1:{port}")
            with device_process(*again):
                assert await next_status(statuses) == SERVING
                assert await check(channel, "rover") == SERVING
            watch.cancel()


async def test_unknown_names_and_services_that_come_and_go(gateway_process: StartGateway) -> None:
    gw = gateway_process(QUICK_CHECKS)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        try:
            await health.Check(health_pb2.HealthCheckRequest(service="scout9"))
            raise AssertionError("an unknown name answered")
        except grpc.aio.AioRpcError as exc:
            assert exc.code() == grpc.StatusCode.NOT_FOUND
            assert "scout9" in (exc.details() or "")
        watch = health.Watch(health_pb2.HealthCheckRequest(service="scout9"))
        statuses = aiter(watch)
        assert await next_status(statuses) == SERVICE_UNKNOWN

        stub = pb_grpc.PropertyServiceStub(channel)
        with tcp_device("--service", "sim-robot", "--name", "scout9") as (_, port):
            # Registered while a probe watches: the Watch call goes on and reports it
            # (NOT_SERVING first, for as long as the registry has not reached the device).
            await stub.Set(
                pb.SetRequest(service="registry", property="services.scout9", value=f"tcp://127.0.0.1:{port}")
            )
            if await next_status(statuses) == NOT_SERVING:
                assert await next_status(statuses) == SERVING
            assert await check(channel, "scout9") == SERVING
            await stub.Set(pb.SetRequest(service="registry", property="services.scout9", value=""))
            assert await next_status(statuses) == SERVICE_UNKNOWN
        watch.cancel()


async def test_a_stopping_gateway_serves_no_name(gateway_process: StartGateway) -> None:
    gw = gateway_process(QUICK_CHECKS)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        whole = aiter(health.Watch(health_pb2.HealthCheckRequest(service="")))
        registry = aiter(health.Watch(health_pb2.HealthCheckRequest(service="registry")))
        assert await next_status(whole) == SERVING
        assert await next_status(registry) == SERVING
        gw.proc.terminate()
        assert await next_status(whole) == NOT_SERVING
        assert await next_status(registry) == NOT_SERVING

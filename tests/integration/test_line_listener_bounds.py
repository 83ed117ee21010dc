"""The line listener's bounds against a real gateway process: silent connections cannot lock out
devices, and one source address cannot register any number of services by greeting."""

from __future__ import annotations

import asyncio

import grpc
from line_device_support import LineClient, device_process
from support.bystander import get_p99, registry_state, rss_mb
from support.gateway_process import StartGateway
from support.ports import free_port
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 15.0
IDLE_CONNECTIONS = 1024


async def test_idle_connections_cannot_lock_out_a_device_and_greetings_are_bounded(
    gateway_process: StartGateway,
) -> None:
    line_port = free_port()
    gw = gateway_process(f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"
        [limits]
        line_idle_timeout = 3.0
        max_greetings_per_source = 1
        [[services]]
        name = "bot"
        type = "sim-robot"
    """)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await get_p99(stub, "bot", "location")
        rss_before, p99_before = rss_mb(gw.proc.pid), await get_p99(stub, "bot", "location")
        idle = [await asyncio.open_connection("127.0.0.1", line_port) for _ in range(IDLE_CONNECTIONS)]
        await asyncio.sleep(1.5)  # silent long enough to be made room for
        address = f"127.0.0.1:{line_port}"
        with device_process("--service", "sim-robot", "--name", "rover", "--connect", address):
            assert (
                await eventually(
                    lambda: registry_state(stub, "rover"), lambda s: s == "up", within=WAIT, what="rover"
                )
                == "up"
            )

            # A second device from the same source address is one too many.
            client = await LineClient.tcp("127.0.0.1", line_port)
            try:
                await client.send("HELLO 1 name=intruder type=robot")
                refusal = (await asyncio.wait_for(client.reader.read(), WAIT)).decode()
            finally:
                await client.close()
            assert "\nERR 8 " in refusal and "max_greetings_per_source" in refusal
            names = await stub.Get(pb.GetRequest(service="registry", property="services"), timeout=WAIT)
            assert "intruder" not in names.value

            # The silent ones are closed once line_idle_timeout has passed: each reads to its end.
            ended = await asyncio.wait_for(asyncio.gather(*(reader.read() for reader, _ in idle)), WAIT)
            assert len(ended) == IDLE_CONNECTIONS
            assert all(reader.at_eof() for reader, _ in idle)
            reply = await stub.Get(pb.GetRequest(service="rover", property="location"), timeout=WAIT)
            assert reply.value
        for _, writer in idle:
            writer.close()
        rss_after, p99_after = rss_mb(gw.proc.pid), await get_p99(stub, "bot", "location")
        figures = (rss_before, rss_after, p99_before * 1e3, p99_after * 1e3)
        print("RSS {:.1f} -> {:.1f} MB; bystander Get p99 {:.1f} -> {:.1f} ms".format(*figures))
        assert rss_after - rss_before < 30
        assert p99_after < 0.1

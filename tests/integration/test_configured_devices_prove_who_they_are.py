"""A configured device that dials in proves who it is with its secret; nobody else takes its name."""

from __future__ import annotations

import asyncio
from pathlib import Path

import grpc
from line_device_support import LineClient, device_process
from support.bystander import registry_state
from support.gateway_process import StartGateway
from support.ports import free_port
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 15.0


async def greeting_answer(port: int, greeting: str) -> str:
    client = await LineClient.tcp("127.0.0.1", port)
    try:
        await client.send(greeting)
        return (await asyncio.wait_for(client.reader.read(), WAIT)).decode()
    finally:
        await client.close()


async def test_only_the_device_with_the_secret_takes_its_configured_name(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    secret = tmp_path / "rover.secret"
    secret.write_text("s3cr3t-rover\n", encoding="utf-8")
    line_port = free_port()
    gw = gateway_process(f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"
        [[services]]
        name = "rover"
        url = "tcp-in://"
        secret_file = "{secret}"
    """)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        for greeting in ("HELLO 1 name=rover type=robot", "HELLO 1 name=rover type=robot secret=guess"):
            answer = await greeting_answer(line_port, greeting)
            assert "\nERR 16 " in answer and "configured device" in answer, answer
        names = await stub.Get(pb.GetRequest(service="registry", property="services"), timeout=WAIT)
        assert "rover" not in names.value

        address = f"127.0.0.1:{line_port}"
        with device_process(
            "--service", "sim-robot", "--name", "rover", "--connect", address, "--secret-file", str(secret)
        ):
            assert (
                await eventually(
                    lambda: registry_state(stub, "rover"), lambda s: s == "up", within=WAIT, what="rover"
                )
                == "up"
            )
            reply = await stub.Get(pb.GetRequest(service="rover", property="location"), timeout=WAIT)
            assert reply.value
            impostor = await greeting_answer(line_port, "HELLO 1 name=rover type=robot")
            assert "\nERR 16 " in impostor
            try:
                await stub.Set(
                    pb.SetRequest(service="registry", property="services.rover", value=""), timeout=WAIT
                )
            except grpc.aio.AioRpcError as exc:
                assert exc.code() == grpc.StatusCode.PERMISSION_DENIED
            else:
                raise AssertionError("a configured device was unregistered from outside")
        assert "s3cr3t-rover" not in gw.output

"""A configured device that dials in proves who it is with its secret; nobody else takes its name."""

from __future__ import annotations

import asyncio
import ssl
from pathlib import Path

import grpc
from line_device_support import LineClient, device_process
from support.bystander import registry_state
from support.certs import make_certificates
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


async def test_a_client_certificate_named_after_the_device_proves_it_over_tls(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    certs = make_certificates(tmp_path / "certs", clients=("rover", "alice"))
    secret = tmp_path / "rover.secret"
    secret.write_text("s3cr3t-rover\n", encoding="utf-8")
    line_port = free_port()
    gw = gateway_process(f"""
        [gateway]
        line_listen = "127.0.0.1:{line_port}"
        [tls.line]
        cert = "{certs.server.cert}"
        key = "{certs.server.key}"
        client_ca = "{certs.ca}"
        [[services]]
        name = "rover"
        url = "tcp-in://"
        secret_file = "{secret}"
    """)

    async def greet_as(client: str) -> tuple[str, asyncio.StreamWriter]:
        pair = certs.clients[client]
        context = ssl.create_default_context(cafile=str(certs.ca))
        context.load_cert_chain(pair.cert, pair.key)
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", line_port, ssl=context, server_hostname="localhost"
        )
        writer.write(b"HELLO 1 name=rover type=mobile_robot\n")  # no secret: the certificate proves it
        await writer.drain()
        lines = []
        try:
            while True:
                line = await asyncio.wait_for(reader.readline(), 1.5)
                if not line:
                    break
                lines.append(line.decode())
        except TimeoutError:
            pass  # taken up: the gateway now speaks to it as a device and waits
        return "".join(lines), writer

    answer, impostor = await greet_as("alice")
    assert "ERR 16 " in answer and "configured device" in answer, answer
    impostor.close()
    answer, device = await greet_as("rover")
    assert "ERR 16" not in answer, answer
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        names = await stub.Get(pb.GetRequest(service="registry", property="services"), timeout=WAIT)
        assert "rover" in names.value
    device.close()

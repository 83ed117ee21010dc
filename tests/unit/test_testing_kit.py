"""gateway.testing as a user sees it: their own class served in the test's process, called with the SDK."""

from __future__ import annotations

import asyncio
from pathlib import Path

import grpc
import pytest
from support.fake_backend import DictBackend
from support.lamp import Lamp

from clients import Event, FailedPrecondition, NotFound, ResourceExhausted
from gateway.config import Config, Limits
from gateway.testing import running_gateway, serve, serve_sync
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 10.0


def socket_of(target: str) -> Path:
    assert target.startswith("unix:"), target
    return Path(target.removeprefix("unix:"))


async def test_get_set_and_a_set_error_with_its_code() -> None:
    lamp = Lamp()
    async with serve(lamp, name="lamp") as client:
        assert await client.properties("lamp") == ["on", "watts", "blink"]
        assert await client.get("lamp", "on") == "false"
        assert await client.set("lamp", "on", True) == "true"
        assert lamp.on is True
        assert await client.set("lamp", "blink", 3, period=0.2) == "blinking 3 times every 0.2 s"
        with pytest.raises(FailedPrecondition) as refused:
            await client.set("lamp", "watts", 5)
        assert refused.value.code is grpc.StatusCode.FAILED_PRECONDITION
        with pytest.raises(NotFound):
            await client.get("lamp", "colour")
        assert await client.get("registry", "services.lamp.type") == "light"


async def test_listen_sees_the_current_value_then_changes() -> None:
    lamp = Lamp()
    async with serve(lamp, name="lamp") as client:
        values: list[str] = []
        async with asyncio.timeout(WAIT):
            async for event in client.listen("lamp", "on"):
                assert isinstance(event, Event)
                values.append(event.value)
                if event.sequence == 1:
                    lamp.on = True  # a change from the inside, as the service itself would make
                else:
                    break
        assert values == ["false", "true"]


async def test_the_socket_is_a_file_while_served_and_gone_after() -> None:
    async with serve(Lamp(), name="lamp") as client:
        path = socket_of(client.target)
        assert path.is_socket()
    assert not path.exists()
    assert not path.parent.exists()


async def test_several_services_by_a_dict_and_limits_from_a_config() -> None:
    dev = DictBackend({"a": "1"})
    config = Config(limits=Limits(max_streams=1))
    async with serve({"lamp": Lamp(), "dev": dev}, config=config) as client:
        assert await client.services() == ["registry", "lamp", "dev"]
        held = client.listen("dev", "a")
        assert (await anext(held)).value == "1"
        with pytest.raises(ResourceExhausted, match="max_streams"):
            await anext(client.listen("lamp", "on"))
        await held.aclose()
    assert dev.closed


async def test_the_generated_stub_reaches_the_running_gateway() -> None:
    async with (
        running_gateway(Lamp(), name="lamp") as gateway,
        grpc.aio.insecure_channel(gateway.address) as channel,
    ):
        reply = await pb_grpc.PropertyServiceStub(channel).Get(
            pb.GetRequest(service="lamp", property="on"), timeout=WAIT
        )
        assert reply.value == "false"


def test_the_blocking_client_against_a_served_class() -> None:
    lamp = Lamp()
    with serve_sync(lamp, name="lamp") as client:
        assert client.set("lamp", "on", True) == "true"
        assert client.get("lamp", "on") == "true"
        with pytest.raises(FailedPrecondition):
            client.set("lamp", "watts", 5)
        with client.listen("lamp", "on") as events:
            assert next(events).value == "true"
        path = socket_of(client.target)
    assert lamp.on is True
    assert not path.exists()


async def test_one_service_needs_a_name_and_a_dict_names_its_own() -> None:
    with pytest.raises(TypeError, match="name="):
        async with serve(Lamp()):
            pass
    with pytest.raises(TypeError, match="dict"):
        async with serve({"lamp": Lamp()}, name="lamp"):
            pass

"""A registry of 10,000 services: listed through the SDK and HTTP, followed by a Listen within its limit.

A real gateway in this process (gateway.testing) serves 10,000 services (in-process backends: a
registration without a device costs the registry what a device's does); its ``services`` value
passes 64 KiB, so the SDK and the HTTP front end read the names a page at a time. A Listen on
``services.*.state`` matches every registration and the registry's own entry, 10,001 properties:
one more than ``limits.max_stream_properties`` allows by default, and it says so; raised to the
registry's size, the Listen follows every service.
"""

from __future__ import annotations

import aiohttp
import pytest
from support.fake_backend import DictBackend

from clients import AsyncClient
from clients.aio import Event, Mark
from clients.errors import ResourceExhausted
from gateway.config import Config, HttpSection, Limits
from gateway.testing import running_gateway

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

COUNT = 10_000
NAMES = [f"device{i:05d}" for i in range(COUNT)]


def _backends() -> dict[str, DictBackend]:
    return {name: DictBackend({"a": "1"}) for name in NAMES}


async def test_ten_thousand_services_are_listed_and_followed_within_the_listen_limit() -> None:
    config = Config(http=HttpSection(listen="127.0.0.1:0"))
    async with running_gateway(_backends(), config=config) as gateway:
        async with AsyncClient(gateway.address, timeout=30.0) as client:
            assert await client.services() == sorted(["registry", *NAMES])
            pages = [len(page) async for page in client.service_pages()]
            assert pages == [1000] * 10 + [1]

            refused = client.listen("registry", "services.*.state")
            with pytest.raises(
                ResourceExhausted, match=r"more than 10000 properties \(limits.max_stream_properties\)"
            ):
                async for _ in refused:
                    pass

        assert gateway.http is not None
        async with aiohttp.ClientSession() as http:
            url = f"{gateway.http.url}api/v1/services"
            async with http.get(url, params={"limit": "2000", "after": NAMES[8999]}) as reply:
                assert reply.status == 200, await reply.text()
                body = await reply.json()
            assert [row["name"] for row in body["services"]] == [*NAMES[9000:], "registry"]
            assert body["next"] == "registry"


async def test_a_listen_limit_raised_to_the_registrys_size_follows_every_service() -> None:
    config = Config(limits=Limits(max_stream_properties=COUNT + 1))
    async with (
        running_gateway(_backends(), config=config) as gateway,
        AsyncClient(gateway.address, timeout=30.0) as client,
    ):
        states: dict[str, str] = {}
        async for item in client.listen("registry", "services.*.state", marks=True):
            if item is Mark.SYNC:
                break
            assert isinstance(item, Event)
            states[item.property] = str(item.value)
        assert len(states) == COUNT + 1 and set(states.values()) == {"up"}

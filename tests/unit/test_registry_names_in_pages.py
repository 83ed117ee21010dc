"""A registry whose ``services`` passes one value's 64 KiB is listed page by page, through every front.

1,100 services with names of 64 characters (the longest a name may be) make a ``services``
value past the 64 KiB a value may hold (what about 6,000 ordinary names do), in-process: the
registry's ``service_names`` query, then a real gateway served in this process
(gateway.testing) read through the SDK, the HTTP front end and psctl. The 10,000-service registry is in
tests/integration/test_a_registry_of_ten_thousand_services.py.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import aiohttp
import pytest
from support.fake_backend import DictBackend

from clients import Client
from clients.cli import main as psctl
from clients.values import ValueFormatError
from gateway.config import Config, HttpSection
from gateway.engine.router import Router
from gateway.testing import running_gateway, serve_sync
from services.apps.registry import Registry
from services.kernel.errors import InvalidArgument
from services.kernel.values import MAX_VALUE_LENGTH, format_names, parse_names

#: Enough long names that the registry's ``services`` value passes 64 KiB.
NAMES = [f"{'sensor-' * 8}unit{i:04d}" for i in range(1_100)]


def _backends() -> dict[str, DictBackend]:
    return {name: DictBackend({"a": "1"}) for name in NAMES}


async def test_names_pages_every_service_in_name_order_each_page_within_one_value() -> None:
    router = Router()
    registry = Registry(directory=router.directory, period=0)
    await registry.start()
    try:
        for name in reversed(NAMES):
            router.add(name, DictBackend({"a": "1"}))
        assert len(format_names(registry._table.names())) > MAX_VALUE_LENGTH

        pages: list[list[str]] = []
        after = ""
        while page := await registry.service_names(after=after, limit="10000"):
            assert len(format_names(page)) <= MAX_VALUE_LENGTH
            pages.append(page)
            after = page[-1]
            if len(pages) == 1:  # services that join and leave between pages
                router.add("aaa-before-the-cursor", DictBackend({"a": "1"}))
                router.remove(NAMES[-1])
                router.add("zzz-after-the-cursor", DictBackend({"a": "1"}))
        assert len(pages) == 2, "the first page ends where 64 KiB would be passed"
        read = [name for page in pages for name in page]
        assert read == sorted(read), "name order"
        assert read == [*NAMES[:-1], "zzz-after-the-cursor"], "each name registered throughout exactly once"

        assert len(await registry.service_names()) == 1_000, "a page holds 1,000 names by default"
        assert await registry.service_names(limit="3") == ["aaa-before-the-cursor", *NAMES[:2]]
        assert await registry.service_names(after=NAMES[3], limit="2") == NAMES[4:6]
        for bad in ("0", "-1", "ten", "10001"):
            with pytest.raises(InvalidArgument, match="limit"):
                await registry.service_names(limit=bad)
    finally:
        await registry.stop()


@pytest.fixture(scope="module")
def client() -> Iterator[Client]:
    with serve_sync(_backends()) as client:
        yield client


def test_the_sdk_lists_a_registry_past_one_value_page_by_page(client: Client) -> None:
    with pytest.raises(ValueFormatError, match="the limit is 65536"):
        client.get_names("registry", "services")  # the one value: past what a value may hold
    assert client.services() == sorted(["registry", *NAMES])


def test_psctl_ls_lists_a_registry_past_one_value(client: Client, capsys: pytest.CaptureFixture[str]) -> None:
    target = client.target
    assert psctl(["-t", target, "ls"]) == 0
    assert capsys.readouterr().out.split() == sorted(["registry", *NAMES])
    assert psctl(["-t", target, "--json", "ls"]) == 0
    assert json.loads(capsys.readouterr().out) == sorted(["registry", *NAMES])


async def test_the_http_front_lists_a_registry_past_one_value_whole_or_a_page_at_a_time() -> None:
    config = Config(http=HttpSection(listen="127.0.0.1:0"))
    async with running_gateway(_backends(), config=config) as gateway, aiohttp.ClientSession() as http:
        assert gateway.http is not None
        base = f"{gateway.http.url}api/v1/services"
        async with http.get(base) as whole:
            assert whole.status == 200, await whole.text()
            listed = [row["name"] for row in (await whole.json())["services"]]
        assert listed == sorted(["registry", *NAMES])

        paged: list[str] = []
        after: str | None = ""
        while after is not None:
            async with http.get(base, params={"limit": "300", "after": after}) as reply:
                assert reply.status == 200, await reply.text()
                body = await reply.json()
            assert len(body["services"]) <= 300
            assert all(row["state"] == "up" for row in body["services"])
            paged += [row["name"] for row in body["services"]]
            after = body["next"]
        assert paged == listed
        async with http.get(base, params={"limit": "many"}) as refused:
            assert refused.status == 400
            assert "limit" in (await refused.json())["error"]["message"]


def test_a_registry_within_one_value_is_listed_in_joining_order() -> None:
    with serve_sync({"lamp": DictBackend({"on": "0"}), "dev": DictBackend({"a": "1"})}) as small:
        assert small.services() == ["registry", "lamp", "dev"]
        assert parse_names(small.get("registry", "service_names", limit="2")) == ["dev", "lamp"]

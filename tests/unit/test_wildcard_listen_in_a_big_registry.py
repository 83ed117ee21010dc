"""A wildcard Listen on a registry of thousands of services matches every one of them.

The registry's ``properties`` list passes the 64 KiB a value may hold at about 250 services;
a ``services.*.state`` Listen must not depend on it. In-process, as the gateway builds it: a
router, the registry following it, the listen hub; the services are
:class:`~support.fake_backend.DictBackend`s added to the router (a registration without a device).
Also: a wildcard that cannot be expanded says so, and one that could not ask its service about
a change asks again once it answers.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
from support.fake_backend import DictBackend
from support.hub_reader import Reader
from support.waiting import wait_until

from gateway.config import Limits
from gateway.engine.listen import ListenHub, Selector
from gateway.engine.listen import stream as stream_module
from gateway.engine.router import Router
from services.apps.registry import Registry, RegistryService
from services.kernel.errors import Code, Internal, PropertyError
from services.kernel.model import ServiceModel
from services.kernel.values import MAX_VALUE_LENGTH

REGISTRY = "registry"


class Gateway:
    """The router, the registry following it, and a listen hub, as the gateway wires them."""

    def __init__(self, limits: Limits) -> None:
        self.router = Router()
        self.registry = Registry(directory=self.router.directory, period=0)
        self.service = RegistryService(self.registry)
        self.hub = ListenHub(self.router, limits, call_timeout=5.0)

    async def start(self, services: int) -> None:
        await self.service.start()
        self.router.add(REGISTRY, self.service)
        await self.registry.start()
        for i in range(services):
            self.router.add(f"dev{i:05d}", DictBackend({"a": "1"}))

    async def aclose(self) -> None:
        await self.hub.aclose()
        await self.registry.stop()
        await self.service.aclose()


async def a_gateway(services: int, limits: Limits | None = None) -> Gateway:
    gateway = Gateway(limits or Limits())
    await gateway.start(services)
    return gateway


@pytest.fixture
async def thousand() -> AsyncIterator[Gateway]:
    gateway = await a_gateway(1_000)
    yield gateway
    await gateway.aclose()


def states(reader: Reader) -> dict[str, str]:
    """``services.NAME.state`` → its latest value on the stream."""
    return {prop: value for service, prop, value, _ in reader.events if service == REGISTRY}


async def test_services_state_matches_every_one_of_1000_services_and_those_that_come_later(
    thousand: Gateway,
) -> None:
    registry_list = await thousand.service.get("properties")
    assert len(registry_list) > MAX_VALUE_LENGTH  # past what one value may hold
    reader = Reader(thousand.hub, Selector(REGISTRY, "services.*.state"))
    await reader.start()
    seen = states(reader)
    assert len(seen) == 1_001 and set(seen.values()) == {"up"}  # every service and the registry itself
    assert "services.dev00999.state" in seen and f"services.{REGISTRY}.state" in seen

    thousand.router.add("late", DictBackend({"a": "1"}))
    await reader.until((REGISTRY, "services.late.state", "up", False))
    thousand.registry.set_state("dev00500", "down")
    await reader.until((REGISTRY, "services.dev00500.state", "down", False))
    thousand.router.remove("dev00007")
    await wait_until(
        lambda: (REGISTRY, "services.dev00007.state") in reader.removed,
        what="the state of a service that left",
    )
    assert reader.stream.error is None
    reader.stream.close()


async def test_services_star_matches_every_entry_with_its_url(thousand: Gateway) -> None:
    reader = Reader(thousand.hub, Selector(REGISTRY, "services.*"))
    await reader.start()
    seen = states(reader)
    assert len(seen) == 1_001 and seen["services.dev00123"] == "local"
    thousand.router.add("late", DictBackend({"a": "1"}, url="tcp://127.0.0.1:7000"))
    await reader.until((REGISTRY, "services.late", "tcp://127.0.0.1:7000", False))
    reader.stream.close()


async def test_matches_that_fill_the_limit_and_one_more_end_the_stream_saying_so() -> None:
    # 299 registrations and the registry's own entry: exactly limits.max_stream_properties, lowered
    # from its 10,000 so that the bound is met in milliseconds (the 10,000 of the default are met in
    # tests/integration/test_a_registry_of_ten_thousand_services.py).
    gateway = await a_gateway(299, Limits(max_stream_properties=300))
    try:
        reader = Reader(gateway.hub, Selector(REGISTRY, "services.*.state"))
        await reader.start()
        assert len(states(reader)) == 300
        gateway.router.add("one-more", DictBackend({"a": "1"}))
        await wait_until(lambda: reader.stream.error is not None, what="the stream to end")
        assert reader.stream.error is not None
        assert reader.stream.error.code is Code.RESOURCE_EXHAUSTED
        assert "limits.max_stream_properties" in reader.stream.error.message
    finally:
        await gateway.aclose()


async def test_a_larger_limit_follows_every_service_and_one_that_comes_later() -> None:
    # One service more than the lowered limit above allows, and a late one: a raised limit holds them.
    gateway = await a_gateway(300, Limits(max_stream_properties=600))
    try:
        reader = Reader(gateway.hub, Selector(REGISTRY, "services.*.state"))
        await reader.start()
        assert len(states(reader)) == 301
        gateway.router.add("late", DictBackend({"a": "1"}))
        await reader.until((REGISTRY, "services.late.state", "up", False))
        reader.stream.close()
    finally:
        await gateway.aclose()


def a_device_with_a_long_list() -> DictBackend:
    """A service whose ``properties`` list is longer than a value may be, and which only has that list."""
    return DictBackend({f"p{i:05d}": "1" for i in range(MAX_VALUE_LENGTH // 6)})


async def test_a_wildcard_on_a_service_whose_list_cannot_be_read_fails_saying_why() -> None:
    router = Router()
    router.add("big", a_device_with_a_long_list())
    router.add("small", DictBackend({"p1": "1"}))
    hub = ListenHub(router, Limits(max_stream_properties=20_000), call_timeout=5.0)
    reader = Reader(hub, Selector("big", "*"))
    with pytest.raises(PropertyError) as err:
        await reader.stream.start()
    assert err.value.code is Code.INVALID_ARGUMENT
    assert "big: match *" in err.value.message and str(MAX_VALUE_LENGTH) in err.value.message
    reader.stream.close()
    # A `*` service skips it (logged), as it skips any service a selector cannot follow.
    every = Reader(hub, Selector("*", "*"))
    await every.start()
    assert [(s, p) for s, p, _, _ in every.events] == [("small", "p1")]
    every.stream.close()
    await hub.aclose()


class Failing(DictBackend):
    """A service whose model can no longer be read once ``broken`` is set."""

    broken = False

    async def describe(self) -> ServiceModel:
        if self.broken:
            raise Internal("the model is broken")
        return await super().describe()


async def listening_to(device: DictBackend) -> tuple[ListenHub, Reader]:
    """A hub serving ``device`` as ``dev``, and a started ``dev/*`` Listen on it."""
    router = Router()
    router.add("dev", device)
    hub = ListenHub(router, Limits(), call_timeout=5.0)
    reader = Reader(hub, Selector("dev", "*"))
    await reader.start()
    return hub, reader


async def test_a_match_that_fails_later_ends_the_stream_with_the_error() -> None:
    device = Failing({"a": "1"})
    hub, reader = await listening_to(device)
    device.broken = True
    device.add("b", "2")
    await wait_until(lambda: reader.stream.error is not None, what="the stream to end")
    assert reader.stream.error is not None and reader.stream.error.code is Code.INTERNAL
    assert reader.stream.error.message == "dev: match *: the model is broken"
    await hub.aclose()


@pytest.fixture
def quick_retries(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tries again after 10 ms to 50 ms, not 0.5 s to 10 s."""
    monkeypatch.setattr(stream_module, "RETRY_FIRST_S", 0.01)
    monkeypatch.setattr(stream_module, "RETRY_MAX_S", 0.05)


@pytest.mark.usefixtures("quick_retries")
async def test_a_change_asked_about_while_the_service_is_away_is_asked_again_once_it_answers() -> None:
    device = DictBackend({"a": "1"})
    hub, reader = await listening_to(device)
    device.unreachable = True
    device.add("b", "2")
    await wait_until(lambda: reader.stream.retrying == 1, what="the change to be asked about again later")
    device.unreachable = False
    await reader.until(("dev", "b", "2", True))
    await wait_until(lambda: reader.stream.retrying == 0, what="the retry to end")
    assert reader.stream.error is None
    await hub.aclose()

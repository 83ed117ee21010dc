"""The registry keeping its registrations in a real etcd: registrations are keys, the ``store``
property follows etcd going away and coming back, and registrations wait for it."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator

import pytest
from support.etcd import EtcdServer
from support.group_support import MemoryDirectory, sim_robot
from support.waiting import eventually, wait_until

from gateway.stores import EtcdStore, parse_store_url
from services.apps.registry import Registry, RegistryService
from services.apps.registry.store import Kind
from services.kernel.backend import Change
from services.kernel.errors import Code, PropertyError

pytestmark = pytest.mark.slow


@pytest.fixture
async def world() -> AsyncIterator[MemoryDirectory]:
    directory = MemoryDirectory()
    directory.devices["tcp://127.0.0.1:7001"] = lambda: sim_robot(5, 5)
    directory.devices["tcp://127.0.0.1:7002"] = lambda: sim_robot(6, 5)
    yield directory
    await directory.aclose()


@pytest.fixture
async def store(etcd: EtcdServer) -> AsyncIterator[EtcdStore]:
    store = EtcdStore(parse_store_url(etcd.url), gateway_id="gw-a", lease=2.0)
    await store.start()
    yield store
    await store.aclose()


async def serve_registry(directory: MemoryDirectory, store: EtcdStore) -> RegistryService:
    """A registry keeping its registrations in ``store``, served in ``directory`` (and started)."""
    service = RegistryService(Registry(directory=directory, period=0, store=store))
    await directory.add("registry", service)
    return service


async def test_registrations_are_kept_in_etcd_and_come_back(
    world: MemoryDirectory, store: EtcdStore, etcd: EtcdServer
) -> None:
    service = await serve_registry(world, store)
    assert await service.get("store") == etcd.url

    await service.set("services.scout1", "tcp://127.0.0.1:7001", {"type": "mobile_robot"})
    await service.set("services.scout2", "tcp://127.0.0.1:7002")
    kept = await store.read(Kind.SERVICE)
    assert json.loads(kept["scout1"]) == {"url": "tcp://127.0.0.1:7001", "options": {"type": "mobile_robot"}}
    await service.set("services.scout2", "")
    # The registration that left is dropped from etcd as it leaves the registry's table.
    await eventually(
        lambda: store.read(Kind.SERVICE), lambda kept: "scout2" not in kept, what="scout2 leaves etcd"
    )

    # Another registry on the same etcd (the gateway started again) registers what etcd keeps.
    await world.aclose()  # the registry stops first: what it keeps stays in etcd
    again = MemoryDirectory()
    again.devices = world.devices
    try:
        second = await serve_registry(again, store)
        assert "scout1" in again.names() and "scout2" not in again.names()
        assert await second.get("services.scout1.type") == "mobile_robot"
    finally:
        await again.aclose()


async def test_registrations_wait_while_etcd_is_away(
    world: MemoryDirectory, store: EtcdStore, etcd: EtcdServer
) -> None:
    service = await serve_registry(world, store)
    heard: list[Change] = []
    await service.listen("store", heard.append)

    etcd.stop()
    await wait_until(lambda: any("read-only" in str(c.value) for c in heard), what="store says read-only")
    value = await service.get("store")
    assert value.startswith(f"{etcd.url} (read-only: etcd at {etcd.endpoint} cannot be reached (")
    with pytest.raises(PropertyError) as info:
        await service.set("services.scout1", "tcp://127.0.0.1:7001")
    assert info.value.code is Code.UNAVAILABLE
    assert info.value.message.startswith(
        f"registering 'scout1': the registry is read-only: etcd at {etcd.endpoint} cannot be reached ("
    )
    assert "scout1" not in world.names()

    etcd.start()
    await wait_until(lambda: bool(heard) and heard[-1].value == etcd.url, what="store is writable again")
    assert await service.set("services.scout1", "tcp://127.0.0.1:7001") == "tcp://127.0.0.1:7001"
    assert "scout1" in await store.read(Kind.SERVICE)
